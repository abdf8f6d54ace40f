"""The two networks as torch modules: the form they are trained in.

Their layers, tensor names and shapes are those of ``planning.networks``, whose numpy forward
runs every decision and map; ``inference()`` gives a module in that form. On the CPU it reads
the module's own memory and so follows every in-place training step; on another device it is
a copy of the moment.
"""

from __future__ import annotations

from itertools import pairwise
from typing import Any

import torch
from torch import nn

from planning.networks import (
    Network,
    build_network,
    layer_widths,
    sinr_map_architecture,
    value_architecture,
)


class Standardize(nn.Module):
    def __init__(self, size: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(size))
        self.register_buffer("std", torch.ones(size))

    def fit(self, samples: torch.Tensor) -> None:
        """Set the statistics from data; constant inputs keep a unit scale."""
        self.mean.copy_(samples.mean(dim=0))
        std = samples.std(dim=0)
        self.std.copy_(torch.where(std > 1e-6, std, torch.ones_like(std)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


class TorchNetwork(nn.Module):
    """Standardization and the ReLU layers of ``layer_widths``; subclasses add the output."""

    def __init__(self, architecture: dict[str, Any]):
        super().__init__()
        self.card = architecture
        self.input_size: int = architecture["input_size"]
        widths = layer_widths(architecture)
        self.standardize = Standardize(widths[0])
        layers: list[nn.Module] = []
        for inputs, outputs in pairwise(widths):
            layers += [nn.Linear(inputs, outputs), nn.ReLU()]
        self.body = nn.Sequential(*layers[:-1])  # the output layer is linear

    def inference(self) -> Network:
        """This module in the numpy form that decides and maps (see above)."""
        return build_network(self.card, {name: tensor.detach().cpu().numpy()
                                         for name, tensor in self.state_dict().items()})

    def assign(self, network: Network) -> None:
        """Take over the tensors of ``network``, of this module's architecture, in place."""
        self.load_state_dict({name: torch.tensor(array) for name, array in
                              network.tensors.items()})


class TorchValueNetwork(TorchNetwork):
    def __init__(self, input_size: int, value_scale: float, method: dict | None = None):
        super().__init__(value_architecture(input_size, value_scale, method))
        self.value_scale = self.card["value_scale"]

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.value_scale * torch.tanh(self.body(self.standardize(state))).squeeze(-1)


class TorchSinrMapNetwork(TorchNetwork):
    def __init__(self, input_size: int, levels: int):
        super().__init__(sinr_map_architecture(input_size, levels))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.body(self.standardize(features))
