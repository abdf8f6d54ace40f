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

/* A block of states' values of one feature: GCC's generic vectors, lowered to the widest
 * registers each clone has; loads and stores need no alignment. */
typedef float dense_lanes __attribute__((vector_size(DENSE_BLOCK * sizeof(float)), aligned(4)));

/* The network's standardization of DENSE_BLOCK states read feature-major (feature i of
 * state s at states[i * stride + s]), in float32 as planning.networks computes it. */
DENSE_CLONES
static void dense_standardize(const float *restrict states, long stride, int features,
                              const float *restrict mean, const float *restrict std,
                              float *restrict out)
{
    dense_lanes *y = (dense_lanes *)out;
    for (int i = 0; i < features; i++)
        y[i] = (*(const dense_lanes *)(states + i * stride) - mean[i]) / std[i];
}

DENSE_CLONES
static void dense_layer(const float *restrict weight, const float *restrict bias, int inputs,
                        int outputs, const float *restrict in, float *restrict out, int relu)
{
    const dense_lanes *x = (const dense_lanes *)in;
    dense_lanes *y = (dense_lanes *)out;
    int first = 0;
    for (; first + DENSE_UNITS <= outputs; first += DENSE_UNITS) {
        const float *w0 = weight + first * inputs, *w1 = w0 + inputs, *w2 = w1 + inputs,
                    *w3 = w2 + inputs;
        dense_lanes s0 = {0}, s1 = {0}, s2 = {0}, s3 = {0};
        for (int i = 0; i < inputs; i++) {
            s0 += w0[i] * x[i];
            s1 += w1[i] * x[i];
            s2 += w2[i] * x[i];
            s3 += w3[i] * x[i];
        }
        y[first] = s0 + bias[first];
        y[first + 1] = s1 + bias[first + 1];
        y[first + 2] = s2 + bias[first + 2];
        y[first + 3] = s3 + bias[first + 3];
    }
    for (; first < outputs; first++) {
        const float *w = weight + first * inputs;
        dense_lanes sum = {0};
        for (int i = 0; i < inputs; i++)
            sum += w[i] * x[i];
        y[first] = sum + bias[first];
    }
    if (relu)
        for (int k = 0; k < outputs * DENSE_BLOCK; k++)
            out[k] = out[k] < 0.0f ? 0.0f : out[k];
}

#endif
