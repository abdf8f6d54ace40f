"""The value network's compiled training step (planning/_regression.pyx) against exact
arithmetic: its gradients within a bound derived from float32 arithmetic, its Adam step as
torch defines it on the moments it keeps, and the state it shares with torch's own step."""

from __future__ import annotations

import copy
import io

import numpy as np
import pytest
import torch

from cloud_service.adam_step import CompiledStep, adam_step, torch_step
from cloud_service.torch_networks import TorchNetwork, TorchSinrMapNetwork, TorchValueNetwork
from planning import PLANNER_VARIABLE
from planning.compiled import compiled_module
from tests import float32_bounds as bounds

U = bounds.UNIT_ROUNDOFF
STATE_SIZE, BATCH = 36, 200
MAP_INPUTS, LEVELS = 60, 3  # icc2021's SINR map
# A step of Adam with both betas 0, no decay and lr = eps = E moves a parameter by
# E g / (|g| + E), within |g| / E of g itself: a power of two keeps E g exact.
REVEALING = {"lr": 2.0**20, "betas": (0.0, 0.0), "eps": 2.0**20, "weight_decay": 0.0}
PAPER = {"lr": 1e-3, "betas": (0.9, 0.999), "eps": 1e-8, "weight_decay": 1e-4}


def rounded(exact: np.ndarray, error: np.ndarray) -> np.ndarray:
    """The error bound of one float32 operation's result: its operands' ``error`` carried to
    ``exact``, then the rounding, u of the computed magnitude."""
    return error + U * (np.abs(exact) + error)


def network_and_batch(seed: int) -> tuple[TorchValueNetwork, np.ndarray, np.ndarray]:
    """A network as training starts it, standardized on its inputs, and a batch with targets
    across the value range."""
    torch.manual_seed(seed)
    net = TorchValueNetwork(STATE_SIZE, 2.0)
    rng = np.random.default_rng(seed)
    states = (rng.standard_normal((BATCH, STATE_SIZE)) * 5 + 2).astype(np.float32)
    net.standardize.fit(torch.from_numpy(states))
    targets = rng.uniform(-1.9, 1.9, BATCH).astype(np.float32)
    return net, states, targets


def gradients(net: TorchValueNetwork, states: np.ndarray,
              targets: np.ndarray) -> list[bounds.Bounded]:
    """The exact gradient of the batch's mean squared error with respect to each parameter
    (weight, bias of each layer in order), and the most a float32 backward (any order of
    summation) may stray from it, carried op by op from the forward's bounds."""
    found = bounds.layers(net.inference(), states)
    scale, batch = float(net.value_scale), len(targets)
    z, z_error = found[-1].exact[:, 0], found[-1].bound[:, 0]
    t = np.tanh(z)
    t_error = z_error + bounds.TRANSCENDENTAL_ERROR * (np.abs(t) + z_error)
    miss = scale * t - targets
    miss_error = rounded(miss, rounded(scale * t, scale * t_error))
    first = 2 * miss / batch * scale  # 2 x is exact; the division and the scaling round
    first_error = rounded(first, scale * rounded(2 * miss / batch, 2 * miss_error / batch))
    slope = 1 - t * t
    slope_error = rounded(slope, rounded(t * t, (2 * np.abs(t) + t_error) * t_error))
    grad = (first * slope)[:, None]
    grad_error = rounded(grad[:, 0], np.abs(first) * slope_error + first_error * np.abs(slope)
                         + first_error * slope_error)[:, None]
    return backpropagated(net, found, grad, grad_error)


def level_gradients(net: TorchSinrMapNetwork, states: np.ndarray,
                    labels: np.ndarray) -> list[bounds.Bounded]:
    """As ``gradients``, of the batch's mean cross-entropy of the softmax of the logits.

    The softmax is the same whatever its shift, so the exact one is taken at the float32 step's
    own shift (a logit it computed): the step's errors are then each logit's, the shift's
    subtraction, exp, the sum of exps and the quotient, one rounding each."""
    found = bounds.layers(net.inference(), states)
    z, z_error = found[-1].exact, found[-1].bound
    classes, batch = z.shape[1], len(labels)
    shifted = z - z.max(axis=1, keepdims=True)
    shifted_error = z_error + z_error.max(axis=1, keepdims=True)  # the shift read off too
    shifted_error = shifted_error + U * (np.abs(shifted) + shifted_error)
    exp_error = np.expm1(shifted_error) + bounds.TRANSCENDENTAL_ERROR * np.exp(shifted_error)
    total_error = (1 + exp_error.max(axis=1, keepdims=True)) * (1 + bounds.gamma(classes - 1)) - 1
    share = np.exp(shifted) / np.exp(shifted).sum(axis=1, keepdims=True)
    share_error = share * ((1 + exp_error) * (1 + U) / (1 - total_error) - 1)
    one_hot = np.eye(classes)[labels]
    miss = share - one_hot
    miss_error = rounded(miss, share_error)
    grad = miss / batch
    grad_error = rounded(grad, miss_error / batch)
    return backpropagated(net, found, grad, grad_error)


def backpropagated(net: TorchNetwork, found: list[bounds.Bounded], grad: np.ndarray,
                   grad_error: np.ndarray) -> list[bounds.Bounded]:
    """Each parameter's gradient from the output's, ``grad`` (batch, outputs) within
    ``grad_error``, through the layers ``found`` bounds."""
    tensors = {name: t.astype(np.float64) for name, t in net.inference().tensors.items()}
    batch = len(grad)
    found_params: list[bounds.Bounded] = []
    for layer in range(len(found) - 2, -1, -1):
        inputs = found[layer].exact if layer == 0 else np.maximum(found[layer].exact, 0.0)
        in_error = found[layer].bound
        weight = tensors[f"body.{2 * layer}.weight"]  # (outputs, inputs)
        magnitude = np.abs(grad) + grad_error
        padded = -(-batch // 16) * 16
        weight_grad = grad.T @ inputs
        weight_error = (grad_error.T @ (np.abs(inputs) + in_error) + np.abs(grad).T @ in_error
                        + bounds.gamma(padded) * magnitude.T @ (np.abs(inputs) + in_error))
        bias_grad = grad.sum(axis=0)
        bias_error = grad_error.sum(axis=0) + bounds.gamma(padded) * magnitude.sum(axis=0)
        found_params[:0] = [bounds.Bounded(weight_grad, weight_error),
                            bounds.Bounded(bias_grad, bias_error)]
        if layer == 0:
            break
        summed = grad @ weight
        summed_error = (grad_error @ np.abs(weight)
                        + bounds.gamma(weight.shape[0]) * magnitude @ np.abs(weight))
        # The ReLU's gate: the float32 forward may open or shut it where the pre-activation
        # lies within its bound of zero; there the gradient may be all or nothing.
        gate, pre_error = found[layer].exact > 0, found[layer].bound
        certain = np.abs(found[layer].exact) > pre_error
        grad = np.where(gate, summed, 0.0)
        grad_error = np.where(certain, np.where(gate, summed_error, 0.0),
                              np.abs(summed) + summed_error)
    return found_params


def parameters(net: TorchNetwork) -> list[np.ndarray]:
    return [p.detach().numpy().astype(np.float64) for layer in net.body
            if isinstance(layer, torch.nn.Linear) for p in (layer.weight, layer.bias)]


def adam(net: TorchNetwork, settings: dict) -> torch.optim.Adam:
    return torch.optim.Adam(net.parameters(), fused=True, **settings)


def level_network_and_batch(seed: int) -> tuple[TorchSinrMapNetwork, np.ndarray, np.ndarray]:
    """A SINR map as a survey fit starts it, standardized on its inputs, and a batch of
    positions' features with every level among their labels."""
    torch.manual_seed(seed)
    net = TorchSinrMapNetwork(MAP_INPUTS, LEVELS)
    rng = np.random.default_rng(seed)
    states = (rng.standard_normal((BATCH, MAP_INPUTS)) * 20 - 5).astype(np.float32)
    net.standardize.fit(torch.from_numpy(states))
    labels = rng.integers(0, LEVELS, BATCH)
    return net, states, labels


def moves_within_bounds(before: list[np.ndarray], after: list[np.ndarray],
                        expected: list[bounds.Bounded]) -> None:
    """Each parameter moved by REVEALING's step on its gradient, within the gradient's bound."""
    big = REVEALING["lr"]
    for k, (old, new, gradient) in enumerate(zip(before, after, expected, strict=True)):
        moved = old - new
        want = big * gradient.exact / (np.abs(gradient.exact) + big)
        # x -> E x / (|x| + E) is 1-Lipschitz; the step's sqrt, sum and division round (4u of
        # the move), and the parameter's subtraction half a unit in its last place.
        allowed = gradient.bound + 4 * U * np.abs(moved) + U * np.abs(new)
        excess = np.abs(moved - want) - allowed
        assert excess.max() <= 0, (k, float(excess.max()), float(np.abs(want).max()))
    assert max(np.abs(g.exact).max() for g in expected) > 1e-3  # the step had work to do


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_each_parameter_moves_by_its_gradient(seed):
    net, states, targets = network_and_batch(seed)
    expected = gradients(net, states, targets)
    before = parameters(net)
    CompiledStep(net, adam(net, REVEALING))(states, targets)
    moves_within_bounds(before, parameters(net), expected)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_each_map_parameter_moves_by_its_cross_entropy_gradient(seed):
    net, states, labels = level_network_and_batch(seed)
    expected = level_gradients(net, states, labels)
    logits = bounds.last_layer(net.inference(), states)
    before = parameters(net)
    loss = CompiledStep(net, adam(net, REVEALING))(states, labels)
    moves_within_bounds(before, parameters(net), expected)
    # The loss it reports: the batch's mean cross-entropy before the step. Each state's term,
    # log of the sum of exps less the label's logit, strays by its logits' errors, the sum's
    # (within gamma(2) beside each exp's) and log's own.
    z, z_error = logits.exact, logits.bound
    log_total = np.log(np.exp(z).sum(axis=1))
    exact = float(np.mean(log_total - z[np.arange(BATCH), labels]))
    sum_error = np.expm1(2 * z_error.max(axis=1)) + bounds.gamma(LEVELS + 1)
    term_error = (2 * z_error.max(axis=1) + np.log1p(sum_error)
                  + bounds.TRANSCENDENTAL_ERROR * (np.abs(log_total) + 1))
    assert abs(loss - exact) <= term_error.mean()


def test_adam_steps_as_torch_defines_it_on_its_own_moments():
    net, states, targets = network_and_batch(5)
    optimizer = adam(net, PAPER)
    step = CompiledStep(net, optimizer)
    for _ in range(3):  # moments away from zero
        step(states[::-1].copy(), targets[::-1].copy())
    linears = [layer for layer in net.body if isinstance(layer, torch.nn.Linear)]
    params = [p for layer in linears for p in (layer.weight, layer.bias)]
    snapshot = [{key: value.numpy().astype(np.float64).copy() for key, value in
                 optimizer.state[p].items()} | {"param": p.detach().numpy().astype(np.float64)}
                for p in params]
    expected = gradients(net, states, targets)
    step(states, targets)
    beta1, beta2 = PAPER["betas"]
    keep1, beta2_f, keep2 = (float(np.float32(1 - beta1)), float(np.float32(beta2)),
                             float(np.float32(1 - beta2)))
    decay, eps = float(np.float32(PAPER["weight_decay"])), float(np.float32(PAPER["eps"]))
    number = 4
    step_size = float(np.float32(PAPER["lr"] / (1 - beta1**number)))
    correction2_sqrt = float(np.float32(np.sqrt(1 - beta2**number)))
    for p, old, gradient in zip(params, snapshot, expected, strict=True):
        state = optimizer.state[p]
        assert float(state["step"]) == number
        mean, square = state["exp_avg"].numpy(), state["exp_avg_sq"].numpy()
        # The decayed gradient, its moments, as the loop rounds each operation.
        decayed = gradient.exact + decay * old["param"]
        decayed_error = rounded(decayed, gradient.bound + U * np.abs(decay * old["param"]))
        shift = decayed - old["exp_avg"]
        mean_want = old["exp_avg"] + shift * keep1
        mean_error = rounded(mean_want, rounded(shift * keep1,
                                                keep1 * rounded(shift, decayed_error)))
        assert np.all(np.abs(mean - mean_want) <= mean_error)
        square_want = beta2_f * old["exp_avg_sq"] + keep2 * decayed**2
        fresh_error = rounded(keep2 * decayed**2, rounded(
            keep2 * decayed, keep2 * decayed_error) * (np.abs(decayed) + decayed_error)
            + keep2 * np.abs(decayed) * decayed_error)
        square_error = rounded(square_want, U * beta2_f * old["exp_avg_sq"] + fresh_error)
        assert np.all(np.abs(square - square_want) <= square_error)
        # The update from the moments the step kept: a product, a quotient, a sqrt, a sum of
        # positives and a division, each rounding once (6u of it), then the subtraction.
        update = step_size * mean / (np.sqrt(square) / correction2_sqrt + eps)
        new = p.detach().numpy().astype(np.float64)
        allowed = 6 * U * np.abs(update) + U * np.abs(new)
        assert np.all(np.abs((old["param"] - new) - update) <= allowed)


def test_torch_goes_on_where_the_compiled_step_left_off():
    """Both steps keep Adam's state in the one optimizer: a run (or a checkpoint) may change
    hands, and each step keeps the count."""
    net, states, targets = network_and_batch(3)
    optimizer = adam(net, PAPER)
    compiled = CompiledStep(net, optimizer)
    for _ in range(2):
        compiled(states, targets)
    torch_step(net, optimizer)(states, targets)
    compiled(states, targets)
    for p in net.parameters():
        state = optimizer.state[p]
        assert float(state["step"]) == 4 and state["step"].dtype == torch.float32
    loaded = adam(net, PAPER)
    loaded.load_state_dict(optimizer.state_dict())
    CompiledStep(net, loaded)(states, targets)
    assert float(loaded.state[next(net.parameters())]["step"]) == 5


def test_the_environment_chooses_the_step(monkeypatch):
    nets = network_and_batch(0)[0], level_network_and_batch(0)[0]
    monkeypatch.delenv(PLANNER_VARIABLE, raising=False)
    assert all(isinstance(adam_step(net, adam(net, PAPER)), CompiledStep) for net in nets)
    monkeypatch.setenv(PLANNER_VARIABLE, "reference")
    assert not any(isinstance(adam_step(net, adam(net, PAPER)), CompiledStep) for net in nets)


def test_a_bad_batch_is_refused_in_one_line():
    net, states, targets = network_and_batch(0)
    step = CompiledStep(net, adam(net, PAPER))
    with pytest.raises(ValueError, match="targets"):
        step(states, targets[:-1])
    with pytest.raises(ValueError, match="inputs"):
        step(states[:, :-1].copy(), targets)
    net, states, labels = level_network_and_batch(0)
    with pytest.raises(ValueError, match="outside the network's 3 levels"):
        CompiledStep(net, adam(net, PAPER))(states, np.where(labels == 0, LEVELS, labels))
    core = compiled_module("_regression")
    with pytest.raises(ValueError, match="float32"):
        core.ValueRegression([(np.zeros((1, 3)),) * 6], np.zeros(3), np.ones(3), 2.0)


def test_a_step_is_kept_until_the_optimizer_takes_other_moments():
    """Training keeps its step from episode to episode; a checkpoint loaded into the
    optimizer brings moments of its own, and a step made afresh reads those."""
    net, states, targets = network_and_batch(4)
    optimizer = adam(net, PAPER)
    first = adam_step(net, optimizer)
    first(states, targets)
    assert adam_step(net, optimizer, first) is first
    saved = io.BytesIO()
    torch.save(optimizer.state_dict(), saved)
    saved.seek(0)
    optimizer.load_state_dict(torch.load(saved, weights_only=True))
    again = adam_step(net, optimizer, first)
    assert again is not first
    again(states, targets)
    assert float(optimizer.state[next(net.parameters())]["step"]) == 2


def test_a_step_kept_for_batches_of_any_size_steps_as_a_fresh_one():
    """The step's scratch, kept from step to step, grows for a larger batch and serves a
    smaller one after it: each step as a step made for it alone, bit for bit."""
    net, states, targets = network_and_batch(6)
    kept_net, fresh_net = net, copy.deepcopy(net)
    kept_optimizer, fresh_optimizer = adam(kept_net, PAPER), adam(fresh_net, PAPER)
    kept = CompiledStep(kept_net, kept_optimizer)
    for rows in (slice(0, 50), slice(0, 200), slice(100, 117)):
        assert kept(states[rows], targets[rows]) == CompiledStep(
            fresh_net, fresh_optimizer)(states[rows], targets[rows])
    assert all(np.array_equal(a.detach().numpy(), b.detach().numpy())
               for a, b in zip(kept_net.parameters(), fresh_net.parameters(), strict=True))


@pytest.mark.parametrize("steps", [1, 7, 1000])
def test_a_fit_s_learning_rates_are_torch_s_schedule_bit_for_bit(steps):
    """Each fit sets the rate itself (the compiled step calls no optimizer.step, which torch's
    scheduler expects): the same numbers as torch's cosine schedule, so that torch's step still
    fits the maps it fitted before."""
    from cloud_service.sinr_training import FINAL_LR, LEARNING_RATE, cosine_rates

    optimizer = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=LEARNING_RATE)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps, eta_min=FINAL_LR)
    expected = []
    for _ in range(steps):
        expected.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        schedule.step()
    assert list(cosine_rates(steps)) == expected
    assert expected[0] == LEARNING_RATE and (steps == 1 or expected[-1] < LEARNING_RATE / 2)
