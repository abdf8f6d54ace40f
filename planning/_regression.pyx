# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True
# cython: initializedcheck=False
"""A network's Adam step on a batch, compiled (``planning/_regression.h``): the value network's
on its mean squared error (``ValueRegression``; ``cloud_service.value_learner`` trains with it
on the CPU), the SINR map's on the cross-entropy of its levels (``LevelRegression``;
``cloud_service.sinr_training``). torch's own step is their reference. Each reads and writes
the network's tensors and Adam's moments in place, through the arrays it is built on."""

import numpy as np

from libc.stdint cimport int64_t
from libc.stdlib cimport free, malloc


cdef extern from *:
    """
    #ifndef COMPILED_SOURCE_DIGEST
    #define COMPILED_SOURCE_DIGEST ""
    #endif
    """
    const char *COMPILED_SOURCE_DIGEST

SOURCE_DIGEST = COMPILED_SOURCE_DIGEST.decode()


cdef extern from "_regression.h" nogil:
    enum: REGRESSION_MAX_LAYERS
    enum: DENSE_BLOCK
    ctypedef struct regression_layer:
        int inputs, outputs
        float *weight
        float *bias
        float *weight_mean
        float *weight_square
        float *bias_mean
        float *bias_square
    ctypedef struct adam_settings:
        double learning_rate, beta1, beta2, eps, weight_decay
        long step
    ctypedef struct regression_head:
        const float *targets
        float value_scale
        const int64_t *labels
    double regression_step(const regression_layer *layers, int count, const float *mean,
                           const float *std, const regression_head *head, const float *states,
                           long batch, float *act, float *grads, float *param_grad,
                           const adam_settings *adam)


cdef float *writable(object array, tuple shape) except NULL:
    """The float32 memory of ``array``, which must be C-contiguous, writable and ``shape``."""
    cdef float[::1] flat
    if not isinstance(array, np.ndarray) or array.dtype != np.float32 \
            or array.shape != shape or not array.flags.c_contiguous \
            or not array.flags.writeable:
        raise ValueError(f"expected a writable C-contiguous float32 array of shape {shape}")
    flat = array.reshape(-1)
    return &flat[0]


cdef class _Regression:
    """Adam steps of one network: ``layers`` lists each linear layer's (weight, bias, weight's
    first and second moments, bias's first and second moments), the arrays the step updates in
    place; ``mean`` and ``std`` are its standardization."""

    cdef regression_layer layers[REGRESSION_MAX_LAYERS]
    cdef int count
    cdef list kept  # the arrays whose memory the layers point into
    cdef float[::1] mean, std
    cdef long widths_sum, widest, largest
    # Scratch of the step, kept from step to step for batches up to ``padded_room`` states.
    cdef float *act
    cdef float *grads
    cdef float *param_grad
    cdef long padded_room

    def __init__(self, list layers, mean, std):
        if not 1 <= len(layers) <= REGRESSION_MAX_LAYERS:
            raise ValueError(f"1 to {REGRESSION_MAX_LAYERS} layers, not {len(layers)}")
        self.count = len(layers)
        self.kept = []
        self.mean = np.ascontiguousarray(mean, dtype=np.float32)
        self.std = np.ascontiguousarray(std, dtype=np.float32)
        self.widths_sum = self.widest = self.largest = 0
        cdef int l, inputs, outputs
        for l, arrays in enumerate(layers):
            weight, bias, weight_mean, weight_square, bias_mean, bias_square = arrays
            outputs, inputs = weight.shape
            if l > 0 and inputs != self.layers[l - 1].outputs:
                raise ValueError(f"layer {l} takes {inputs} inputs after "
                                 f"{self.layers[l - 1].outputs} outputs")
            self.layers[l].inputs, self.layers[l].outputs = inputs, outputs
            self.layers[l].weight = writable(weight, (outputs, inputs))
            self.layers[l].bias = writable(bias, (outputs,))
            self.layers[l].weight_mean = writable(weight_mean, (outputs, inputs))
            self.layers[l].weight_square = writable(weight_square, (outputs, inputs))
            self.layers[l].bias_mean = writable(bias_mean, (outputs,))
            self.layers[l].bias_square = writable(bias_square, (outputs,))
            self.kept.append(arrays)
            self.widths_sum += inputs
            self.widest = max(self.widest, outputs)
            self.largest = max(self.largest, outputs * (inputs + 1))
        self.widths_sum += self.layers[self.count - 1].outputs
        if self.mean.shape[0] != self.layers[0].inputs or self.std.shape[0] != self.mean.shape[0]:
            raise ValueError("the standardization does not match the first layer")

    cdef double _step(self, const float[:, ::1] states, long batch, regression_head *head,
                      long step, double learning_rate, double beta1, double beta2, double eps,
                      double weight_decay) except? -1:
        if batch < 1 or states.shape[0] != batch or states.shape[1] != self.layers[0].inputs:
            raise ValueError(f"states of shape ({states.shape[0]}, {states.shape[1]}) and "
                             f"{batch} targets for a network of "
                             f"{self.layers[0].inputs} inputs")
        cdef long padded = (batch + DENSE_BLOCK - 1) // DENSE_BLOCK * DENSE_BLOCK
        cdef adam_settings adam
        adam.learning_rate, adam.beta1, adam.beta2 = learning_rate, beta1, beta2
        adam.eps, adam.weight_decay, adam.step = eps, weight_decay, step
        cdef double loss
        if padded > self.padded_room:
            self._make_room(padded)
        with nogil:
            loss = regression_step(self.layers, self.count, &self.mean[0], &self.std[0], head,
                                   &states[0, 0], batch, self.act, self.grads,
                                   self.param_grad, &adam)
        return loss

    cdef _make_room(self, long padded):
        """Scratch for batches of up to ``padded`` states (a whole number of blocks)."""
        self._release()
        self.act = <float *>malloc(self.widths_sum * padded * sizeof(float))
        self.grads = <float *>malloc(2 * self.widest * padded * sizeof(float))
        self.param_grad = <float *>malloc(self.largest * sizeof(float))
        if self.act == NULL or self.grads == NULL or self.param_grad == NULL:
            self._release()
            raise MemoryError()
        self.padded_room = padded

    cdef void _release(self):
        free(self.act)
        free(self.grads)
        free(self.param_grad)
        self.act = self.grads = self.param_grad = NULL
        self.padded_room = 0

    def __dealloc__(self):
        self._release()


cdef class ValueRegression(_Regression):
    """The value network's steps, on the mean squared error of ``value_scale`` tanh of its
    output against target values."""

    cdef float value_scale

    def __init__(self, list layers, mean, std, float value_scale):
        _Regression.__init__(self, layers, mean, std)
        if self.layers[self.count - 1].outputs != 1:
            raise ValueError("a value network ends in one output")
        self.value_scale = value_scale

    def step(self, const float[:, ::1] states, const float[::1] targets, long step,
             double learning_rate, double beta1, double beta2, double eps,
             double weight_decay):
        """Adam's step number ``step`` (from 1) on ``states`` (batch, features) and their
        ``targets``; returns the batch's mean squared error before it."""
        cdef regression_head head
        head.targets, head.value_scale, head.labels = &targets[0], self.value_scale, NULL
        return self._step(states, targets.shape[0], &head, step, learning_rate, beta1, beta2,
                          eps, weight_decay)


cdef class LevelRegression(_Regression):
    """The SINR map's steps, on the cross-entropy of the softmax of its outputs (a logit per
    level) against the levels reported."""

    def step(self, const float[:, ::1] states, const int64_t[::1] labels, long step,
             double learning_rate, double beta1, double beta2, double eps,
             double weight_decay):
        """Adam's step number ``step`` (from 1) on ``states`` (batch, features) and their
        ``labels``; returns the batch's mean cross-entropy before it."""
        cdef long levels = self.layers[self.count - 1].outputs
        if labels.shape[0] and not 0 <= np.min(labels) <= np.max(labels) < levels:
            raise ValueError(f"labels outside the network's {levels} levels")
        cdef regression_head head
        head.targets, head.value_scale, head.labels = NULL, 0.0, &labels[0]
        return self._step(states, labels.shape[0], &head, step, learning_rate, beta1, beta2,
                          eps, weight_decay)
