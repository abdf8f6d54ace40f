/* A dense layer over a block of DENSE_BLOCK states held feature-major: in[i * DENSE_BLOCK + s]
 * is input i of state s. Each output is the bias plus the products added in the order of the
 * inputs, one state per vector lane, so no sum is reassociated whatever the vector width.
 *
 * The wheel must run on any x86_64 CPU, so the baseline build is portable; gcc compiles the
 * layer once more for AVX2 with FMA and once for AVX-512 and picks the widest the CPU has when
 * the module loads. A fused multiply-add rounds once where the baseline rounds twice: both stay
 * within the error bound of a float32 dot product. */
#ifndef PLANNING_DENSE_H
#define PLANNING_DENSE_H

#define DENSE_BLOCK 16
#define DENSE_UNITS 4 /* outputs computed together: independent sums keep the FMA units busy */

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define DENSE_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define DENSE_CLONES
#endif

/* Half a block: DENSE_HALF states' values of one feature, one AVX register (GCC's generic
 * vectors, lowered to the registers each clone has; loads and stores need no alignment). A block
 * is computed as its two halves: gcc 12 lowers a whole block's 64-byte vector on AVX2 through the
 * stack at every product (BENCHMARKS.md, "Half blocks"), and two halves are two independent sums
 * for the FMA units. Each lane's arithmetic is the same either way. */
#define DENSE_HALF (DENSE_BLOCK / 2)
typedef float dense_half __attribute__((vector_size(DENSE_HALF * sizeof(float)), aligned(4)));

/* The network's standardization of DENSE_BLOCK states read feature-major (feature i of
 * state s at states[i * stride + s]), in float32 as planning.networks computes it. */
DENSE_CLONES
static void dense_standardize(const float *restrict states, long stride, int features,
                              const float *restrict mean, const float *restrict std,
                              float *restrict out)
{
    dense_half *y = (dense_half *)out;
    for (int i = 0; i < features; i++) {
        const dense_half *x = (const dense_half *)(states + i * stride);
        y[2 * i] = (x[0] - mean[i]) / std[i];
        y[2 * i + 1] = (x[1] - mean[i]) / std[i];
    }
}

DENSE_CLONES
static void dense_layer(const float *restrict weight, const float *restrict bias, int inputs,
                        int outputs, const float *restrict in, float *restrict out, int relu)
{
    const dense_half *x = (const dense_half *)in; /* x[2 i], x[2 i + 1]: input i's halves */
    dense_half *y = (dense_half *)out;
    int first = 0;
    for (; first + DENSE_UNITS <= outputs; first += DENSE_UNITS) {
        const float *w0 = weight + first * inputs, *w1 = w0 + inputs, *w2 = w1 + inputs,
                    *w3 = w2 + inputs;
        dense_half a0 = {0}, b0 = {0}, a1 = {0}, b1 = {0}, a2 = {0}, b2 = {0}, a3 = {0},
                   b3 = {0};
        for (int i = 0; i < inputs; i++) {
            a0 += w0[i] * x[2 * i];
            b0 += w0[i] * x[2 * i + 1];
            a1 += w1[i] * x[2 * i];
            b1 += w1[i] * x[2 * i + 1];
            a2 += w2[i] * x[2 * i];
            b2 += w2[i] * x[2 * i + 1];
            a3 += w3[i] * x[2 * i];
            b3 += w3[i] * x[2 * i + 1];
        }
        y[2 * first] = a0 + bias[first];
        y[2 * first + 1] = b0 + bias[first];
        y[2 * first + 2] = a1 + bias[first + 1];
        y[2 * first + 3] = b1 + bias[first + 1];
        y[2 * first + 4] = a2 + bias[first + 2];
        y[2 * first + 5] = b2 + bias[first + 2];
        y[2 * first + 6] = a3 + bias[first + 3];
        y[2 * first + 7] = b3 + bias[first + 3];
    }
    for (; first < outputs; first++) {
        const float *w = weight + first * inputs;
        dense_half a = {0}, b = {0};
        for (int i = 0; i < inputs; i++) {
            a += w[i] * x[2 * i];
            b += w[i] * x[2 * i + 1];
        }
        y[2 * first] = a + bias[first];
        y[2 * first + 1] = b + bias[first];
    }
    if (relu)
        for (int k = 0; k < outputs * DENSE_BLOCK; k++)
            out[k] = out[k] < 0.0f ? 0.0f : out[k];
}

#endif
