"""The two networks of the paper, their safetensors format, their forward in numpy, and the
levels a SINR map predicts from its logits.

Value network: standardization, hidden (64, 32, 16) ReLU, tanh output scaled to the reward
range. SINR-mapping network: standardization, hidden (32, 16, 8) ReLU, logits over levels.
The standardization statistics are tensors like the weights, so they travel with them.

Every map, and every decision of the reference lookahead, is computed by the numpy forward
here (the compiled lookahead reads the same layers: ``Network.layers``), so a UAV's agent needs
neither torch nor its memory. Training, in the cloud, builds the same networks as torch
modules and hands their numpy form to the lookahead.

Weights are stored and sent as safetensors (never pickle) with a JSON card. Loading checks
the sha256 digest, the architecture, every tensor's name, shape and dtype, and refuses anything
else with a one-line ``WeightsError``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
from safetensors import SafetensorError
from safetensors.numpy import load as load_bytes
from safetensors.numpy import save as save_bytes

VALUE_HIDDEN = (64, 32, 16)
SINR_HIDDEN = (32, 16, 8)
ROWS_PER_PASS = 1024  # the widest layer of a pass, 1024 x 64 float32, fits a core's L2 cache


class WeightsError(ValueError):
    """Weights that cannot be used: unreadable, tampered, or of the wrong shape."""


def value_architecture(
    input_size: int, value_scale: float, method: dict | None = None
) -> dict[str, Any]:
    """The card of a value network; ``method`` says how its inputs are built and its lookahead
    scored (MethodOptions)."""
    return {"kind": ValueNetwork.kind, "input_size": int(input_size),
            "value_scale": float(value_scale), "method": dict(method or {})}


def sinr_map_architecture(input_size: int, levels: int) -> dict[str, Any]:
    return {"kind": SinrMapNetwork.kind, "input_size": int(input_size), "levels": int(levels)}


def checked_architecture(architecture: Any) -> dict[str, Any]:
    """A card read from elsewhere, in the form the networks are built from."""
    if not isinstance(architecture, dict):
        raise WeightsError(f"architecture description is not a mapping: {architecture!r}")
    kind = architecture.get("kind")
    if kind not in (ValueNetwork.kind, SinrMapNetwork.kind):
        raise WeightsError(f"unknown network kind {kind!r}")
    try:
        if kind == ValueNetwork.kind:
            checked = value_architecture(architecture["input_size"],
                                         architecture["value_scale"], architecture.get("method"))
        else:
            checked = sinr_map_architecture(architecture["input_size"], architecture["levels"])
    except (KeyError, TypeError, ValueError) as exc:
        raise WeightsError(f"architecture description is incomplete: {exc}") from None
    if min(layer_widths(checked)) < 1:
        raise WeightsError(f"architecture {checked} has a layer without units")
    return checked


def layer_widths(architecture: dict[str, Any]) -> tuple[int, ...]:
    """Units from the input through the hidden layers to the output."""
    if architecture["kind"] == ValueNetwork.kind:
        return (architecture["input_size"], *VALUE_HIDDEN, 1)
    return (architecture["input_size"], *SINR_HIDDEN, architecture["levels"])


def tensor_shapes(architecture: dict[str, Any]) -> dict[str, tuple[int, ...]]:
    """Name and shape of every float32 tensor of a network: the names of the torch modules'
    state (``body.<k>``: the k-th module of a sequence alternating Linear and ReLU)."""
    widths = layer_widths(architecture)
    shapes = {"standardize.mean": (widths[0],), "standardize.std": (widths[0],)}
    for layer, (inputs, outputs) in enumerate(pairwise(widths)):
        shapes[f"body.{2 * layer}.weight"] = (outputs, inputs)
        shapes[f"body.{2 * layer}.bias"] = (outputs,)
    return shapes


class Network:
    """A network's forward in numpy, float32, over the tensors of ``tensor_shapes``.

    The layers read the tensors without copying them: tensors that are views of a torch
    module's memory follow that module's training steps. Several threads may run one network
    at once: the forward writes nothing but its own outputs.
    """

    kind: str

    def __init__(self, architecture: dict[str, Any], tensors: Mapping[str, np.ndarray]):
        """``architecture`` in the form of ``checked_architecture``; ``tensors`` as it
        describes them (``from_bytes`` checks both)."""
        self.card = architecture
        self.tensors = dict(tensors)
        self.input_size: int = architecture["input_size"]
        self._mean = self.tensors["standardize.mean"]
        self._std = self.tensors["standardize.std"]
        self._layers = [(self.tensors[f"body.{2 * k}.weight"].T, self.tensors[f"body.{2 * k}.bias"])
                        for k in range(len(layer_widths(architecture)) - 1)]

    def architecture(self) -> dict[str, Any]:
        return dict(self.card)

    def read_subnormals_as_zero(self) -> Network:
        """Let the forward read the subnormal weights as zeros (``tensors`` keep them, so the
        network's bytes stay as they came). Training's weight decay leaves the weights of dead
        ReLU units below float32's normal range: a fifth of every shipped value network's. To
        any output they are zeros, but on some CPUs every multiply-add that touches one costs
        as much as dozens of others (BENCHMARKS.md, "Foundation": subnormal weights). The
        forward then reads
        copies, so a network over a torch module's memory (training) does not call this."""
        self._layers = [(_flushed(weight_t), _flushed(bias)) for weight_t, bias in self._layers]
        return self

    def layers(self) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
        """What the forward reads, for a forward in compiled code: the standardization's mean
        and std, and each layer's weight (outputs, inputs) and bias, float32."""
        return self._mean, self._std, [(weight_t.T, bias) for weight_t, bias in self._layers]

    def outputs(self, inputs: np.ndarray) -> np.ndarray:
        """The last layer's outputs (..., units) for inputs (..., input_size)."""
        inputs = np.asarray(inputs)
        rows = inputs.reshape(-1, self.input_size)
        last_weight_t, last_bias = self._layers[-1]
        out = np.empty((len(rows), len(last_bias)), dtype=np.float32)
        # A pass over a few rows at a time keeps its layers in a core's cache: on the
        # lookahead's batch (256 UAVs x 46 actions) it halves the time of one pass over all.
        for start in range(0, len(rows), ROWS_PER_PASS):
            hidden = np.subtract(rows[start : start + ROWS_PER_PASS], self._mean,
                                 dtype=np.float32)
            hidden /= self._std
            for weight_t, bias in self._layers[:-1]:
                hidden = hidden @ weight_t
                hidden += bias
                np.maximum(hidden, 0.0, out=hidden)
            chunk = out[start : start + ROWS_PER_PASS]
            np.matmul(hidden, last_weight_t, out=chunk)
            chunk += last_bias
        return out.reshape(inputs.shape[:-1] + (len(last_bias),))


class ValueNetwork(Network):
    """The value network V(s^jn): a joint state to the value of its UAV's mission, scaled
    from a tanh output; ``method`` says which method's features it reads."""

    kind = "value"

    def __init__(self, architecture: dict[str, Any], tensors: Mapping[str, np.ndarray]):
        super().__init__(architecture, tensors)
        self.value_scale: float = architecture["value_scale"]
        self.method: dict = architecture["method"]

    def __call__(self, states: np.ndarray) -> np.ndarray:
        """Values (...,) float32 of joint states (..., input_size)."""
        values = np.tanh(self.outputs(states)[..., 0])
        values *= self.value_scale
        return values


class SinrMapNetwork(Network):
    """The SINR-mapping network: a place's features to the logits of its quantized SINR
    level, from which the online map's rasters are sampled."""

    kind = "sinr_map"

    def __init__(self, architecture: dict[str, Any], tensors: Mapping[str, np.ndarray]):
        super().__init__(architecture, tensors)
        self.levels: int = architecture["levels"]

    def __call__(self, features: np.ndarray) -> np.ndarray:
        """Logits (..., levels) float32 of features (..., input_size)."""
        return self.outputs(features)


def predict_probabilities(network: SinrMapNetwork, features: np.ndarray) -> np.ndarray:
    """Probability of each level (softmax of the logits) for features of shape (..., F):
    shape (..., levels), float32."""
    logits = network(features)
    logits -= logits.max(axis=-1, keepdims=True)
    np.exp(logits, out=logits)
    logits /= logits.sum(axis=-1, keepdims=True)
    return logits


def predict_levels(network: SinrMapNetwork, features: np.ndarray) -> np.ndarray:
    """Predicted level (the most probable) for features of shape (..., F)."""
    return predict_probabilities(network, features).argmax(-1).astype(np.int64)


def accuracy_of(network: SinrMapNetwork, features, levels) -> float:
    predicted = predict_levels(network, features)
    return float((predicted == np.asarray(levels)).mean())


def build_network(architecture: dict[str, Any], tensors: Mapping[str, np.ndarray]) -> Network:
    """The network of a card in the form of ``checked_architecture``, over ``tensors``."""
    kind = ValueNetwork if architecture["kind"] == ValueNetwork.kind else SinrMapNetwork
    return kind(architecture, tensors)


def to_bytes(network: Network) -> bytes:
    """safetensors bytes of the network; the architecture rides in the header metadata."""
    tensors = {name: np.ascontiguousarray(t, dtype=np.float32)
               for name, t in network.tensors.items()}
    return save_bytes(tensors, metadata={"architecture": json.dumps(network.architecture())})


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def from_bytes(
    data: bytes, expected_sha256: str | None = None, expected: dict[str, Any] | None = None
) -> Network:
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
    architecture = checked_architecture(architecture)
    if expected is not None:
        mismatched = {k: v for k, v in expected.items() if architecture.get(k) != v}
        if mismatched:
            raise WeightsError(f"architecture {architecture} does not match expected {expected}")
    reference = tensor_shapes(architecture)
    if set(tensors) != set(reference):
        raise WeightsError(
            f"tensor names differ: missing {sorted(set(reference) - set(tensors))}, "
            f"unexpected {sorted(set(tensors) - set(reference))}"
        )
    for name, shape in reference.items():
        tensor = tensors[name]
        if tensor.shape != shape or tensor.dtype != np.float32:
            raise WeightsError(
                f"tensor {name}: {tensor.shape} {tensor.dtype}, expected {shape} float32"
            )
        if not np.isfinite(tensor).all():
            raise WeightsError(f"tensor {name} holds NaN or infinite values")
    return build_network(architecture,
                         {name: tensors[name] for name in reference}).read_subnormals_as_zero()


def _flushed(tensor: np.ndarray) -> np.ndarray:
    return np.where(np.abs(tensor) < np.finfo(np.float32).tiny, np.float32(0.0), tensor)


def _header_metadata(data: bytes) -> dict[str, str]:
    header_size = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + header_size])
    return header.get("__metadata__", {})


def card_path(weights_path: Path) -> Path:
    return weights_path.with_suffix(".json")


def save_network(network: Network, path: Path, card: dict[str, Any]) -> str:
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


def load_network(path: Path, expected: dict[str, Any] | None = None) -> tuple[Network, dict]:
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
