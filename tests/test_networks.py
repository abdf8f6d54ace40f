from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.numpy import save as save_bytes

from cloud_service.torch_networks import TorchNetwork, TorchSinrMapNetwork, TorchValueNetwork
from planning.networks import (
    Network,
    ValueNetwork,
    WeightsError,
    from_bytes,
    load_network,
    predict_probabilities,
    save_network,
    sha256,
    to_bytes,
)
from shared.shipped import (
    EXTENDED_CROWD_VALUE_NET,
    EXTENDED_VALUE_NET,
    SINR_MAP_NO_JAMMER,
    SINR_MAP_NO_JAMMER_SHADOWED,
    VALUE_NET,
)
from tests import float32_bounds as bounds


def trained_like(module: TorchNetwork, seed: int = 0, std: float = 1.0) -> TorchNetwork:
    torch.manual_seed(seed)
    for parameter in module.parameters():
        parameter.data.normal_(0.0, std)
    module.standardize.fit(torch.randn(50, module.input_size) * 3 + 1)
    return module


def torch_forward(module: TorchNetwork, inputs: np.ndarray) -> np.ndarray:
    with torch.inference_mode():
        return module(torch.from_numpy(inputs)).numpy()


def module_of(network: Network) -> TorchNetwork:
    if isinstance(network, ValueNetwork):
        module = TorchValueNetwork(network.input_size, network.value_scale, network.method)
    else:
        module = TorchSinrMapNetwork(network.input_size, network.levels)
    module.assign(network)
    return module


def inputs_like(network: Network, rows: int, seed: int) -> np.ndarray:
    """Inputs spread as the network's standardization says its training inputs were."""
    noise = np.random.default_rng(seed).standard_normal((rows, network.input_size))
    tensors = network.tensors
    return (tensors["standardize.mean"] + tensors["standardize.std"] * noise).astype(np.float32)


def assert_agree(network: Network, inputs: np.ndarray, *forwards: np.ndarray) -> None:
    """Each float32 forward's outputs within float32's bound of the exact ones (float32_bounds:
    the bound follows the network's depth, widths, weights and inputs, not one CPU's kernels)."""
    exact = (bounds.values(network, inputs) if isinstance(network, ValueNetwork)
             else bounds.last_layer(network, inputs))
    for outputs in forwards:
        bounds.assert_within(outputs, exact)


@pytest.mark.parametrize("module", [TorchValueNetwork(34, 2.0), TorchSinrMapNetwork(20, 3)])
def test_round_trip_is_exact(module, tmp_path):
    module = trained_like(module)
    path = tmp_path / "net.safetensors"
    digest = save_network(module.inference(), path, {"note": "test"})
    loaded, card = load_network(path)
    assert card["sha256"] == digest == sha256(path.read_bytes())
    assert card["architecture"] == loaded.architecture() == module.card
    state = module.state_dict()
    assert loaded.tensors.keys() == state.keys()
    for name, tensor in state.items():
        np.testing.assert_array_equal(loaded.tensors[name], tensor.numpy(), err_msg=name)
    assert to_bytes(loaded) == path.read_bytes()


@pytest.mark.parametrize("path", [VALUE_NET, EXTENDED_VALUE_NET, EXTENDED_CROWD_VALUE_NET,
                                  SINR_MAP_NO_JAMMER, SINR_MAP_NO_JAMMER_SHADOWED],
                         ids=lambda path: path.stem)
def test_the_numpy_forward_agrees_with_torch_on_the_shipped_models(path):
    network, _ = load_network(path)
    assert to_bytes(network) == path.read_bytes()
    inputs = inputs_like(network, 5000, seed=1)
    expected = torch_forward(module_of(network), inputs)
    got = network(inputs)
    assert_agree(network, inputs, got, expected)
    if isinstance(network, ValueNetwork):
        exact = bounds.values(network, inputs)
        assert np.ptp(exact.exact) > 0.5  # the states span values, not one saturated end
        # The bound is far inside the outputs' spread: a forward off by a layer is caught.
        assert exact.bound.max() < 1e-3 * np.ptp(exact.exact)
        return
    logits = bounds.last_layer(network, inputs)
    assert logits.bound.max() < 1e-3 * np.ptp(logits.exact)
    chances = bounds.probabilities(logits)
    bounds.assert_within(predict_probabilities(network, inputs), chances)
    bounds.assert_within(torch.softmax(torch.from_numpy(expected), -1).numpy(), chances)
    # The level a map serves: the same from both forwards and the exact one, wherever no
    # forward within the bounds could pick another (logits closer than their bounds: a tie).
    clear = bounds.decided(logits)
    assert clear.mean() > 0.99
    for forward in (got, expected):
        np.testing.assert_array_equal(forward.argmax(-1)[clear], logits.exact.argmax(-1)[clear])


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("build", [lambda: TorchValueNetwork(34, 2.0),
                                   lambda: TorchSinrMapNetwork(60, 3)], ids=["value", "sinr_map"])
def test_the_numpy_forward_agrees_with_torch_on_random_weights(build, seed):
    # Torch's initialization, and weights spread like the shipped networks' (std 0.07-0.5).
    for module in (build(), trained_like(build(), seed, std=0.2)):
        network = module.inference()
        inputs = inputs_like(network, 2000, seed)
        assert_agree(network, inputs, network(inputs), torch_forward(module, inputs))


def test_the_numpy_form_follows_the_modules_training_steps():
    module = TorchValueNetwork(34, 2.0)
    network = module.inference()
    states = torch.randn(64, 34)
    before = network(states.numpy()).copy()
    optimizer = torch.optim.Adam(module.parameters(), lr=0.05)
    for _ in range(3):
        optimizer.zero_grad()
        (module(states) - 1.0).square().mean().backward()
        optimizer.step()
    module.standardize.fit(states)
    after = network(states.numpy())
    assert np.abs(after - before).max() > 0.01
    assert_agree(network, states.numpy(), after, torch_forward(module, states.numpy()))


def test_value_output_is_bounded_by_the_scale():
    network = trained_like(TorchValueNetwork(34, 2.0)).inference()
    values = network(np.random.default_rng(0).normal(0, 100, (1000, 34)).astype(np.float32))
    assert np.abs(values).max() <= 2.0


def test_truncated_and_tampered_files_are_refused(tmp_path):
    path = tmp_path / "net.safetensors"
    save_network(trained_like(TorchValueNetwork(34, 2.0)).inference(), path, {})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(WeightsError, match="digest"):
        load_network(path)
    tampered = bytearray(data)
    tampered[-5] ^= 0xFF
    path.write_bytes(bytes(tampered))
    with pytest.raises(WeightsError, match="digest"):
        load_network(path)
    # Without a digest to compare, a truncated payload still fails to parse, cleanly.
    with pytest.raises(WeightsError, match="safetensors"):
        from_bytes(data[: len(data) // 2])


def test_wrong_architecture_is_refused():
    data = to_bytes(trained_like(TorchValueNetwork(34, 2.0)).inference())
    with pytest.raises(WeightsError, match="does not match"):
        from_bytes(data, expected={"kind": "value", "input_size": 40})
    with pytest.raises(WeightsError, match="does not match"):
        from_bytes(data, expected={"kind": "sinr_map"})


def test_tensors_of_another_name_shape_dtype_or_value_are_refused():
    network = trained_like(TorchValueNetwork(34, 2.0)).inference()
    metadata = {"architecture": json.dumps(network.architecture())}
    good = network.tensors
    bias = good["body.0.bias"]
    refused = {
        "tensor names differ: missing ['body.0.bias']":
            {name: t for name, t in good.items() if name != "body.0.bias"},
        "tensor body.0.bias: (65,) float32, expected (64,) float32":
            {**good, "body.0.bias": np.concatenate([bias, bias[:1]])},
        "tensor body.0.bias: (64,) float64": {**good, "body.0.bias": bias.astype(np.float64)},
        "tensor body.0.bias holds NaN": {**good, "body.0.bias": np.full(64, np.nan, np.float32)},
    }
    for message, tensors in refused.items():
        with pytest.raises(WeightsError, match=re.escape(message)):
            from_bytes(save_bytes(tensors, metadata=metadata))


@pytest.mark.parametrize(("architecture", "message"), [
    ({"kind": "policy", "input_size": 34}, "unknown network kind 'policy'"),
    ({"kind": "value", "input_size": 34}, "incomplete"),
    ({"kind": "sinr_map", "input_size": 0, "levels": 3}, "without units"),
    (["value", 34], "not a mapping"),
])
def test_unusable_architecture_cards_are_refused(architecture, message):
    tensors = trained_like(TorchSinrMapNetwork(20, 3)).inference().tensors
    data = save_bytes(tensors, metadata={"architecture": json.dumps(architecture)})
    with pytest.raises(WeightsError, match=re.escape(message)):
        from_bytes(data)


def test_a_network_read_from_bytes_computes_without_its_subnormal_weights():
    """Weight decay leaves dead units' weights subnormal, which some CPUs multiply dozens of
    times slower. Read from bytes, the forward sees them as zeros and gives the same outputs;
    the network's bytes keep them."""
    module = trained_like(TorchValueNetwork(34, 2.0), seed=3, std=0.2)
    with torch.no_grad():
        weight = module.body[0].weight
        weight[:8] = 1e-40  # eight dead units' incoming weights, decayed below normal
    exact = module.inference()
    data = to_bytes(exact)
    read = from_bytes(data)
    tiny = np.finfo(np.float32).tiny
    assert not any(((np.abs(w) < tiny) & (w != 0)).any() for w, _ in read._layers)
    assert ((np.abs(exact._layers[0][0]) < tiny) & (exact._layers[0][0] != 0)).sum() == 8 * 34
    assert to_bytes(read) == data
    inputs = inputs_like(read, 2000, seed=3)
    np.testing.assert_array_equal(read(inputs), exact(inputs))


def test_torchs_plain_kernels_give_the_same_agreement():
    """torch's plain kernels (ATEN_CPU_CAPABILITY=default) stand in for an older CPU than this
    one: the forwards agree with the exact ones within the same derived bounds there too, and
    decide as they do."""
    plain = dict(os.environ, ATEN_CPU_CAPABILITY="default")
    capability = subprocess.run(
        [sys.executable, "-c", "import torch; print(torch.backends.cpu.get_cpu_capability())"],
        env=plain, capture_output=True, text=True, check=True)
    assert capability.stdout.strip() == "DEFAULT"
    tests = Path(__file__).parent
    run = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", __file__,
                          str(tests / "test_policy.py"), "-k",
                          "agrees_with_torch or decide_as_the_exact_values"],
                         env=plain, cwd=tests.parent, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-3000:]
    assert re.search(r"\b12 passed\b", run.stdout), run.stdout[-500:]
