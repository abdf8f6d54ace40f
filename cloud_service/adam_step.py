"""A network's mini-batch step: one Adam step of the value network on the mean squared error of
its values against targets, or of the SINR map on the cross-entropy of its levels against the
levels reported. Two implementations of each: torch's (autograd and its Adam), the reference
and the only one off the CPU, and the compiled core's (``planning/_regression.pyx``), which
spares torch's fixed cost per operation, most of a step on networks this small. Both read and
write the same tensors and the same Adam moments, so a checkpoint is one and the same whichever
made it, and ``JAMNAV_PLANNER=reference`` trains with torch's as it flies the numpy planner."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from cloud_service.torch_networks import TorchNetwork, TorchValueNetwork
from planning.compiled import chosen_planner, compiled_module

# (states, target values or levels) -> the batch's mean loss before the step
AdamStep = Callable[[np.ndarray, np.ndarray], float]


def adam_step(net: TorchNetwork, optimizer: torch.optim.Adam,
              reuse: AdamStep | None = None) -> AdamStep:
    """Steps of ``optimizer`` (torch's Adam over ``net``'s parameters) on ``net``: compiled
    where the network is on the CPU and the planner chosen is the compiled one. ``reuse``: a
    step made before, returned if it still serves them (its set-up is most of a step's cost)."""
    if isinstance(reuse, CompiledStep) and reuse.serves(net, optimizer):
        return reuse
    group = optimizer.param_groups[0]
    on_cpu = all(p.device.type == "cpu" for p in net.parameters())
    plain_adam = not (group["amsgrad"] or group["maximize"]) and len(optimizer.param_groups) == 1
    if on_cpu and plain_adam and chosen_planner() == "compiled":
        return CompiledStep(net, optimizer)
    return torch_step(net, optimizer)


def torch_step(net: TorchNetwork, optimizer: torch.optim.Adam) -> AdamStep:
    device = next(net.parameters()).device
    loss_of = (torch.nn.functional.mse_loss if isinstance(net, TorchValueNetwork)
               else torch.nn.functional.cross_entropy)

    def step(states: np.ndarray, targets: np.ndarray) -> float:
        loss = loss_of(net(torch.from_numpy(states).to(device)),
                       torch.from_numpy(targets).to(device))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return float(loss.detach())

    return step


class CompiledStep:
    """The compiled step over ``net``'s tensors and ``optimizer``'s moments, in place. Adam's
    state starts as torch starts it (zero moments, step 0, float32 as its fused form keeps it)
    and its step count follows every step, so torch's own steps may go on from here. The
    learning rate is read at each step, where a schedule sets it."""

    def __init__(self, net: TorchNetwork, optimizer: torch.optim.Adam):
        self.net, self.optimizer = net, optimizer
        linears = [layer for layer in net.body if isinstance(layer, torch.nn.Linear)]
        self.counters, self.moments = [], []
        layers = []
        for linear in linears:
            arrays = []
            for parameter in (linear.weight, linear.bias):
                state = self._adam_state(parameter)
                self.moments.append((parameter, state["exp_avg"], state["exp_avg_sq"]))
                self.counters.append(state["step"].numpy())
                arrays.append((parameter.detach().numpy(), state["exp_avg"].numpy(),
                               state["exp_avg_sq"].numpy()))
            (weight, weight_mean, weight_square), (bias, bias_mean, bias_square) = arrays
            layers.append((weight, bias, weight_mean, weight_square, bias_mean, bias_square))
        core, standardization = compiled_module("_regression"), (
            layers, net.standardize.mean.numpy(), net.standardize.std.numpy())
        if isinstance(net, TorchValueNetwork):
            self.core = core.ValueRegression(*standardization, float(net.value_scale))
            self.target_type = np.float32
        else:
            self.core = core.LevelRegression(*standardization)
            self.target_type = np.int64

    def serves(self, net: TorchNetwork, optimizer: torch.optim.Adam) -> bool:
        """Whether this step still reads ``net``'s tensors and ``optimizer``'s moments: loading
        a checkpoint into the optimizer gives it new ones."""
        if net is not self.net or optimizer is not self.optimizer:
            return False
        return all(optimizer.state[p].get("exp_avg") is mean
                   and optimizer.state[p].get("exp_avg_sq") is square
                   for p, mean, square in self.moments)

    def _adam_state(self, parameter: torch.nn.Parameter) -> dict:
        state = self.optimizer.state[parameter]
        if not state:
            state["step"] = torch.zeros((), dtype=torch.float32)
            state["exp_avg"] = torch.zeros_like(parameter, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(parameter,
                                                   memory_format=torch.preserve_format)
        return state

    def __call__(self, states: np.ndarray, targets: np.ndarray) -> float:
        step = int(self.counters[0]) + 1
        group = self.optimizer.param_groups[0]
        loss = self.core.step(np.ascontiguousarray(states, dtype=np.float32),
                              np.ascontiguousarray(targets, dtype=self.target_type), step,
                              float(group["lr"]), *map(float, group["betas"]),
                              float(group["eps"]), float(group["weight_decay"]))
        for counter in self.counters:
            counter += 1
        return float(loss)
