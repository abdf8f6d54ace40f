/* One Adam step of a network on a batch: the value network on the mean squared error of its
 * values, the SINR map on the cross-entropy of its levels. The forward with its activations
 * kept, the backward, and torch's Adam (L2 weight decay added to the gradient) applied to each
 * layer as soon as its gradient is whole. torch's own step is the reference
 * (cloud_service.adam_step); this one spares its fixed cost per operation, which is most of a
 * step on networks this small.
 *
 * Activations are held feature-major over the batch padded to whole blocks (value i of state s
 * at act[i * padded + s]), so every product runs one state per vector lane as in _dense.h. The
 * padding states carry a zero output gradient: they add nothing to any gradient. */
#ifndef PLANNING_REGRESSION_H
#define PLANNING_REGRESSION_H

#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_dense.h"

#define REGRESSION_MAX_LAYERS 8

/* A lane mask: a comparison of two halves gives all ones where it holds, zeros elsewhere. */
typedef int regression_mask __attribute__((vector_size(DENSE_HALF * sizeof(int)), aligned(4)));

/* ``value`` where ``gate`` is positive, zero elsewhere. */
static inline dense_half regression_where_positive(dense_half gate, dense_half value)
{
    const dense_half zero = {0};
    return (dense_half)((regression_mask)value & (gate > zero));
}

/* The lanes of a block's two halves added in order, the first half's lane 0 first. */
static inline float regression_lanes_sum(dense_half first, dense_half second)
{
    float total = 0.0f;
    for (int lane = 0; lane < DENSE_HALF; lane++)
        total += first[lane];
    for (int lane = 0; lane < DENSE_HALF; lane++)
        total += second[lane];
    return total;
}

typedef struct {
    int inputs, outputs;
    float *weight; /* outputs x inputs, torch's layout */
    float *bias;
    float *weight_mean, *weight_square, *bias_mean, *bias_square; /* Adam's moments */
} regression_layer;

typedef struct {
    double learning_rate, beta1, beta2, eps, weight_decay;
    long step; /* this step's number, from 1 */
} adam_settings;

/* torch's Adam on n parameters with their gradients. The bias corrections and the step size
 * are computed in double; the moments, the parameters and the constants the loop multiplies by
 * (1 - beta1, beta2, 1 - beta2, the decay, eps) in float32. */
DENSE_CLONES
static void regression_adam(float *restrict param, const float *restrict grad,
                            float *restrict mean, float *restrict square, long n,
                            const adam_settings *adam)
{
    const double correction1 = 1.0 - pow(adam->beta1, (double)adam->step);
    const double correction2 = 1.0 - pow(adam->beta2, (double)adam->step);
    const float step_size = (float)(adam->learning_rate / correction1);
    const float correction2_sqrt = (float)sqrt(correction2);
    const float keep1 = (float)(1.0 - adam->beta1), beta2 = (float)adam->beta2,
                keep2 = (float)(1.0 - adam->beta2), decay = (float)adam->weight_decay,
                eps = (float)adam->eps;
    for (long k = 0; k < n; k++) {
        const float g = grad[k] + decay * param[k];
        mean[k] += (g - mean[k]) * keep1;
        square[k] = beta2 * square[k] + keep2 * g * g;
        param[k] -= step_size * mean[k] / (sqrtf(square[k]) / correction2_sqrt + eps);
    }
}

/* Sum over the padded batch of a[s] * b[s], the lanes of each block added in a fixed order. */
DENSE_CLONES
static float regression_dot(const float *restrict a, const float *restrict b, long padded)
{
    dense_half first = {0}, second = {0};
    for (long s = 0; s < padded; s += DENSE_BLOCK) {
        const dense_half *x = (const dense_half *)(a + s), *y = (const dense_half *)(b + s);
        first += x[0] * y[0];
        second += x[1] * y[1];
    }
    return regression_lanes_sum(first, second);
}

/* Sum over the padded batch of a[s], the lanes of each block added in a fixed order. */
DENSE_CLONES
static float regression_total(const float *restrict a, long padded)
{
    dense_half first = {0}, second = {0};
    for (long s = 0; s < padded; s += DENSE_BLOCK) {
        const dense_half *x = (const dense_half *)(a + s);
        first += x[0];
        second += x[1];
    }
    return regression_lanes_sum(first, second);
}

/* z = W a + b over the padded batch; ReLU unless it is the output layer. */
DENSE_CLONES
static void regression_forward_layer(const regression_layer *layer, const float *restrict in,
                                     float *restrict out, long padded, int relu)
{
    for (int o = 0; o < layer->outputs; o++) {
        float *restrict z = out + o * padded;
        const float *w = layer->weight + (long)o * layer->inputs;
        for (long s = 0; s < padded; s += DENSE_BLOCK) {
            dense_half first = {0}, second = {0};
            for (int i = 0; i < layer->inputs; i++) {
                const dense_half *x = (const dense_half *)(in + i * padded + s);
                first += w[i] * x[0];
                second += w[i] * x[1];
            }
            first += layer->bias[o];
            second += layer->bias[o];
            if (relu) {
                first = regression_where_positive(first, first);
                second = regression_where_positive(second, second);
            }
            dense_half *y = (dense_half *)(z + s);
            y[0] = first;
            y[1] = second;
        }
    }
}

/* The gradient of the layer's inputs, W^T g, masked where the input's ReLU was off. */
DENSE_CLONES
static void regression_back_layer(const regression_layer *layer, const float *restrict grad,
                                  const float *restrict in, float *restrict in_grad, long padded)
{
    for (int i = 0; i < layer->inputs; i++) {
        for (long s = 0; s < padded; s += DENSE_BLOCK) {
            dense_half first = {0}, second = {0};
            for (int o = 0; o < layer->outputs; o++) {
                const float w = layer->weight[(long)o * layer->inputs + i];
                const dense_half *g = (const dense_half *)(grad + o * padded + s);
                first += w * g[0];
                second += w * g[1];
            }
            const dense_half *on = (const dense_half *)(in + i * padded + s);
            dense_half *y = (dense_half *)(in_grad + i * padded + s);
            y[0] = regression_where_positive(on[0], first);
            y[1] = regression_where_positive(on[1], second);
        }
    }
}

/* What the step fits the network's output to: a value per state (``targets``, the output scaled
 * by ``value_scale`` through tanh, mean squared error) or a class per state (``labels``, the
 * outputs read as logits, mean cross-entropy); ``labels`` NULL for the first. */
typedef struct {
    const float *targets;
    float value_scale;
    const int64_t *labels; /* each in [0, the output layer's width) */
} regression_head;

/* d/dz of the batch's mean squared error of scale tanh z against the targets, zero on the
 * padding; returns that mean. */
static double regression_value_grad(const float *out, const regression_head *head, long batch,
                                    long padded, float *grad)
{
    double squares = 0.0;
    for (long s = 0; s < padded; s++) {
        if (s >= batch) {
            grad[s] = 0.0f;
            continue;
        }
        const float t = tanhf(out[s]);
        const float error = head->value_scale * t - head->targets[s];
        squares += (double)error * error;
        grad[s] = 2.0f * error / (float)batch * head->value_scale * (1.0f - t * t);
    }
    return squares / (double)batch;
}

/* d/dz of the batch's mean cross-entropy of the softmax of the ``classes`` logits against the
 * labels: (softmax - one-hot) / batch, zero on the padding; returns that mean. Each state's
 * softmax subtracts its largest logit first, as torch's log-softmax does. */
static double regression_level_grad(const float *out, int classes, const regression_head *head,
                                    long batch, long padded, float *grad)
{
    double losses = 0.0;
    for (long s = 0; s < padded; s++) {
        if (s >= batch) {
            for (int k = 0; k < classes; k++)
                grad[k * padded + s] = 0.0f;
            continue;
        }
        float largest = out[s];
        for (int k = 1; k < classes; k++)
            largest = fmaxf(largest, out[k * padded + s]);
        float total = 0.0f;
        for (int k = 0; k < classes; k++) {
            const float e = expf(out[k * padded + s] - largest);
            grad[k * padded + s] = e;
            total += e;
        }
        const long label = head->labels[s];
        losses += (double)logf(total) + largest - out[label * padded + s];
        for (int k = 0; k < classes; k++)
            grad[k * padded + s] = (grad[k * padded + s] / total - (k == label)) / (float)batch;
    }
    return losses / (double)batch;
}

/* The batch standardized into ``act`` feature-major and every layer's outputs after it;
 * ``inputs[l]`` points at layer l's inputs, ``inputs[count]`` at the network's output. */
static void regression_forward(const regression_layer *layers, int count, const float *mean,
                               const float *std, const float *states, long batch, long padded,
                               float *act, float **inputs)
{
    const int features = layers[0].inputs;
    inputs[0] = act;
    for (int l = 0; l < count; l++)
        inputs[l + 1] = inputs[l] + (long)layers[l].inputs * padded;
    for (int i = 0; i < features; i++) {
        float *row = inputs[0] + i * padded;
        for (long s = 0; s < batch; s++)
            row[s] = (states[s * features + i] - mean[i]) / std[i];
        memset(row + batch, 0, (padded - batch) * sizeof(float));
    }
    for (int l = 0; l < count; l++)
        regression_forward_layer(&layers[l], inputs[l], inputs[l + 1], padded, l < count - 1);
}

/* Each layer's gradient from the output's (``grad``) down, and Adam applied to it at once. */
static void regression_backward(const regression_layer *layers, int count, float **inputs,
                                float *grad, float *in_grad, long padded, float *param_grad,
                                const adam_settings *adam)
{
    for (int l = count - 1; l >= 0; l--) {
        const regression_layer *layer = &layers[l];
        if (l > 0)
            regression_back_layer(layer, grad, inputs[l], in_grad, padded);
        float *weight_grad = param_grad, *bias_grad = param_grad
                                                      + (long)layer->outputs * layer->inputs;
        for (int o = 0; o < layer->outputs; o++) {
            for (int i = 0; i < layer->inputs; i++)
                weight_grad[(long)o * layer->inputs + i] =
                    regression_dot(grad + o * padded, inputs[l] + i * padded, padded);
            bias_grad[o] = regression_total(grad + o * padded, padded);
        }
        regression_adam(layer->weight, weight_grad, layer->weight_mean, layer->weight_square,
                        (long)layer->outputs * layer->inputs, adam);
        regression_adam(layer->bias, bias_grad, layer->bias_mean, layer->bias_square,
                        layer->outputs, adam);
        float *swap = grad;
        grad = in_grad;
        in_grad = swap;
    }
}

/* One step on ``batch`` states (row-major, batch x features) and what ``head`` fits them to;
 * returns the batch's mean loss before the step. ``act`` holds the sum of the widths times the
 * padded batch, ``grads`` twice the widest layer times it, ``param_grad`` the largest layer's
 * weights and biases. */
static double regression_step(const regression_layer *layers, int count, const float *mean,
                              const float *std, const regression_head *head,
                              const float *states, long batch, float *act, float *grads,
                              float *param_grad, const adam_settings *adam)
{
    const long padded = (batch + DENSE_BLOCK - 1) / DENSE_BLOCK * DENSE_BLOCK;
    float *inputs[REGRESSION_MAX_LAYERS + 1];
    regression_forward(layers, count, mean, std, states, batch, padded, act, inputs);
    long widest = 0;
    for (int l = 0; l < count; l++)
        widest = layers[l].outputs > widest ? layers[l].outputs : widest;
    float *grad = grads, *in_grad = grads + widest * padded;
    const double loss = head->labels == NULL
        ? regression_value_grad(inputs[count], head, batch, padded, grad)
        : regression_level_grad(inputs[count], layers[count - 1].outputs, head, batch, padded,
                                grad);
    regression_backward(layers, count, inputs, grad, in_grad, padded, param_grad, adam);
    return loss;
}

#endif
