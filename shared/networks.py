"""The two networks of the paper and their safetensors format.

Value network: standardization, hidden (64, 32, 16) ReLU, tanh output scaled to the reward
range. SINR-mapping network: standardization, hidden (32, 16, 8) ReLU, logits over levels.
The standardization statistics are buffers, so they travel with the weights.

Weights are stored and sent as safetensors (never pickle) with a JSON card. Loading checks
the sha256 digest, every tensor's name, shape and dtype, and refuses anything else with a
one-line ``WeightsError``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_bytes
from safetensors.torch import save as save_bytes
from torch import nn

VALUE_HIDDEN = (64, 32, 16)
SINR_HIDDEN = (32, 16, 8)


class WeightsError(ValueError):
    """Weights that cannot be used: unreadable, tampered, or of the wrong shape."""


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


def _mlp(inputs: int, hidden: tuple[int, ...], outputs: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(inputs, width), nn.ReLU()]
        inputs = width
    layers.append(nn.Linear(inputs, outputs))
    return nn.Sequential(*layers)


class ValueNetwork(nn.Module):
    kind = "value"

    def __init__(self, input_size: int, value_scale: float, method: dict | None = None):
        super().__init__()
        self.input_size = input_size
        self.value_scale = value_scale
        # How the network's inputs are built and its lookahead scored (MethodOptions).
        self.method = dict(method or {})
        self.standardize = Standardize(input_size)
        self.body = _mlp(input_size, VALUE_HIDDEN, 1)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.value_scale * torch.tanh(self.body(self.standardize(state))).squeeze(-1)

    def architecture(self) -> dict[str, Any]:
        return {"kind": self.kind, "input_size": self.input_size,
                "value_scale": self.value_scale, "method": self.method}


class SinrMapNetwork(nn.Module):
    kind = "sinr_map"

    def __init__(self, input_size: int, levels: int):
        super().__init__()
        self.input_size = input_size
        self.levels = levels
        self.standardize = Standardize(input_size)
        self.body = _mlp(input_size, SINR_HIDDEN, levels)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.body(self.standardize(features))

    def architecture(self) -> dict[str, Any]:
        return {"kind": self.kind, "input_size": self.input_size, "levels": self.levels}


def build_network(architecture: dict[str, Any]) -> nn.Module:
    try:
        if architecture["kind"] == ValueNetwork.kind:
            return ValueNetwork(int(architecture["input_size"]),
                                float(architecture["value_scale"]), architecture.get("method"))
        if architecture["kind"] == SinrMapNetwork.kind:
            return SinrMapNetwork(int(architecture["input_size"]), int(architecture["levels"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise WeightsError(f"architecture description is incomplete: {exc}") from None
    raise WeightsError(f"unknown network kind {architecture.get('kind')!r}")


def to_bytes(network: nn.Module) -> bytes:
    """safetensors bytes of the network; the architecture rides in the header metadata."""
    tensors = {name: t.detach().to("cpu", torch.float32).contiguous()
               for name, t in network.state_dict().items()}
    return save_bytes(tensors, metadata={"architecture": json.dumps(network.architecture())})


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def from_bytes(
    data: bytes, expected_sha256: str | None = None, expected: dict[str, Any] | None = None
) -> nn.Module:
    """A network from safetensors bytes, after checking digest, names, shapes and dtypes.

    ``expected`` pins the architecture (e.g. the input size an agent's features have).
    """
    if expected_sha256 is not None and sha256(data) != expected_sha256:
        raise WeightsError("sha256 digest does not match: the weights were altered or truncated")
    try:
        tensors = load_bytes(data)
        metadata = _header_metadata(data)
        architecture = json.loads(metadata["architecture"])
    except (SafetensorError, ValueError, KeyError, TypeError) as exc:
        raise WeightsError(f"not a readable safetensors network: {exc}") from None
    if expected is not None:
        mismatched = {k: v for k, v in expected.items() if architecture.get(k) != v}
        if mismatched:
            raise WeightsError(f"architecture {architecture} does not match expected {expected}")
    network = build_network(architecture)
    reference = network.state_dict()
    if set(tensors) != set(reference):
        raise WeightsError(
            f"tensor names differ: missing {sorted(set(reference) - set(tensors))}, "
            f"unexpected {sorted(set(tensors) - set(reference))}"
        )
    for name, tensor in tensors.items():
        want = reference[name]
        if tensor.shape != want.shape or tensor.dtype != torch.float32:
            raise WeightsError(
                f"tensor {name}: {tuple(tensor.shape)} {tensor.dtype}, expected "
                f"{tuple(want.shape)} torch.float32"
            )
        if not torch.isfinite(tensor).all():
            raise WeightsError(f"tensor {name} holds NaN or infinite values")
    network.load_state_dict(tensors)
    network.eval()
    return network


def _header_metadata(data: bytes) -> dict[str, str]:
    header_size = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + header_size])
    return header.get("__metadata__", {})


def card_path(weights_path: Path) -> Path:
    return weights_path.with_suffix(".json")


def save_network(network: nn.Module, path: Path, card: dict[str, Any]) -> str:
    """Write ``path`` (safetensors) and its JSON card beside it; returns the sha256."""
    data = to_bytes(network)
    digest = sha256(data)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(data)
    tmp.replace(path)
    full_card = {**card, "architecture": network.architecture(), "sha256": digest}
    card_path(path).write_text(json.dumps(full_card, indent=2) + "\n", encoding="utf-8")
    return digest


def load_network(path: Path, expected: dict[str, Any] | None = None) -> tuple[nn.Module, dict]:
    """Load a network and its card; the card's digest must match the file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise WeightsError(f"{path}: {exc.strerror}") from None
    card_file = card_path(path)
    try:
        card = json.loads(card_file.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise WeightsError(f"{card_file}: card missing or unreadable ({exc})") from None
    try:
        network = from_bytes(data, card.get("sha256"), expected)
    except WeightsError as exc:
        raise WeightsError(f"{path}: {exc}") from None
    return network, card
