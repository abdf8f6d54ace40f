"""How far a float32 computation may stray from its exact value, derived from the arithmetic.

Two float32 forwards of one network (numpy's, torch's; AVX-512 kernels or plain ones) sum their
dot products in different orders, so they agree with each other only as far as float32
rounding lets each stray from the exact result. The tests compare each with a float64
reference of the same network, within the bound computed here for every output. float64
rounds 2^29 times finer, so the reference's own error is left out of the bounds.

The bounds are worst cases: whatever order, blocking or fused multiply-add a kernel uses. A
wrong weight, layer or activation moves outputs by orders of magnitude more.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planning.networks import Network, ValueNetwork, layer_widths

UNIT_ROUNDOFF = 2.0**-24  # one float32 operation's relative error is at most this
# float32 exp and tanh, numpy's SIMD kernels and torch's (SLEEF), stay within 4 units in the
# last place, and one unit in the last place of y is at most 2u|y|.
TRANSCENDENTAL_ERROR = 4 * 2 * UNIT_ROUNDOFF
FLOAT32_TINY = float(np.finfo(np.float32).tiny)


def gamma(n: int) -> float:
    """Relative error bound of a float32 sum of n products, in any order (Higham, Thm 3.1)."""
    return n * UNIT_ROUNDOFF / (1 - n * UNIT_ROUNDOFF)


def rounded_once(magnitude: float) -> float:
    """The most a value up to ``magnitude`` moves when rounded to float32 once: half a unit in
    its last place. One rounding is exact arithmetic, the same on every CPU."""
    return float(np.spacing(np.float32(magnitude))) / 2


@dataclass(frozen=True)
class Bounded:
    """Exact outputs (float64) and, per output, the most a float32 forward may differ."""

    exact: np.ndarray
    bound: np.ndarray


def layers(network: Network, inputs: np.ndarray,
           input_error: np.ndarray | float = 0.0) -> list[Bounded]:
    """Each linear layer's outputs before its ReLU (..., units) for float32 inputs
    (..., input_size), each input read off by up to ``input_error`` (a forward that computed
    its inputs itself); the standardized inputs first."""
    tensors = {name: t.astype(np.float64) for name, t in network.tensors.items()}
    widths = layer_widths(network.architecture())
    standardized = (inputs.astype(np.float64) - tensors["standardize.mean"]) \
        / tensors["standardize.std"]
    off = input_error / tensors["standardize.std"]
    # The inputs' error passes the standardization scaled; its subtract and divide round.
    activation, error = standardized, off + gamma(2) * (np.abs(standardized) + off)
    found = [Bounded(standardized, error)]
    for layer, fan_in in enumerate(widths[:-1]):
        weight = tensors[f"body.{2 * layer}.weight"].T
        bias = tensors[f"body.{2 * layer}.bias"]
        read = np.abs(activation) + error  # the float32 forward's input to this layer
        # Its input's error passes through |W|; its own n products and the bias add
        # gamma(n + 1) of the magnitudes; subnormal weights read as zeros add FLT_MIN each.
        error = (error @ np.abs(weight) + gamma(fan_in + 1) * (read @ np.abs(weight)
                 + np.abs(bias)) + FLOAT32_TINY * read.sum(-1, keepdims=True))
        outputs = activation @ weight + bias
        found.append(Bounded(outputs, error))
        activation = np.maximum(outputs, 0.0)  # ReLU moves no output further from the exact
    return found


def last_layer(network: Network, inputs: np.ndarray,
               input_error: np.ndarray | float = 0.0) -> Bounded:
    """The last linear layer's outputs (..., units), as ``layers`` bounds them."""
    return layers(network, inputs, input_error)[-1]


def values(network: ValueNetwork, states: np.ndarray,
           state_error: np.ndarray | float = 0.0) -> Bounded:
    """The value network's outputs, scale * tanh(last layer): tanh is 1-Lipschitz, and it and
    the scaling round once more. ``state_error``: as ``last_layer``'s ``input_error``."""
    logit = last_layer(network, states, state_error)
    squashed = np.tanh(logit.exact[..., 0])
    error = logit.bound[..., 0] + (TRANSCENDENTAL_ERROR + UNIT_ROUNDOFF) * (np.abs(squashed)
                                                                            + logit.bound[..., 0])
    return Bounded(network.value_scale * squashed, network.value_scale * error)


def probabilities(logits: Bounded) -> Bounded:
    """Softmax of logits known within their bounds, as numpy's and torch's float32 compute it:
    subtract the largest, exp, sum, divide (or multiply by the reciprocal). Every factor of a
    probability is then within exp(+-A) of exact, where A adds the logits' errors (its own and
    the worst in the sum), the rounded subtraction, exp's error and the sum's and division's
    roundings; so |p' - p| <= p (exp(A) - 1). Below float32's normal range a probability is
    kept only to FLT_MIN, absolutely (subnormal or flushed to zero)."""
    exact, bound = logits.exact, logits.bound
    shifted = exact - exact.max(axis=-1, keepdims=True)
    argument = bound + UNIT_ROUNDOFF * (np.abs(shifted) + 2 * bound.max(axis=-1, keepdims=True))
    levels = exact.shape[-1]
    rounding = TRANSCENDENTAL_ERROR + gamma(levels + 1)
    spread = argument + argument.max(axis=-1, keepdims=True) + 2 * rounding
    chances = np.exp(shifted)
    chances /= chances.sum(axis=-1, keepdims=True)
    return Bounded(chances, chances * np.expm1(spread) + FLOAT32_TINY)


def decided(scores: Bounded) -> np.ndarray:
    """Rows (..., choices) whose best choice no float32 forward within the bounds can change:
    the best beats every other by more than the two bounds together. Closer is a tie."""
    best = scores.exact.argmax(axis=-1)[..., None]
    lead = np.take_along_axis(scores.exact, best, -1) - scores.exact
    margin = np.take_along_axis(scores.bound, best, -1) + scores.bound
    np.put_along_axis(lead, best, np.inf, -1)
    return (lead > margin).all(axis=-1)


def assert_within(got: np.ndarray, expected: Bounded) -> None:
    """Every float32 output within its bound of the exact one."""
    assert got.dtype == np.float32 and got.shape == expected.exact.shape
    excess = np.abs(got.astype(np.float64) - expected.exact) - expected.bound
    worst = np.unravel_index(np.argmax(excess), excess.shape)
    assert excess[worst] <= 0, (f"output {worst}: {got[worst]} against exact "
                                f"{expected.exact[worst]}, bound {expected.bound[worst]:.3g}")
