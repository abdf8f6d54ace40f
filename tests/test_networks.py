from __future__ import annotations

import pytest
import torch

from shared.networks import (
    SinrMapNetwork,
    ValueNetwork,
    WeightsError,
    from_bytes,
    load_network,
    save_network,
    sha256,
    to_bytes,
)


def trained_like(network):
    torch.manual_seed(0)
    for parameter in network.parameters():
        parameter.data.normal_()
    network.standardize.fit(torch.randn(50, network.input_size) * 3 + 1)
    return network


@pytest.mark.parametrize("network", [ValueNetwork(34, 2.0), SinrMapNetwork(20, 3)])
def test_round_trip_is_exact(network, tmp_path):
    network = trained_like(network)
    path = tmp_path / "net.safetensors"
    digest = save_network(network, path, {"note": "test"})
    loaded, card = load_network(path)
    assert card["sha256"] == digest == sha256(path.read_bytes())
    for (name, a), (_, b) in zip(network.state_dict().items(), loaded.state_dict().items(),
                                 strict=True):
        assert torch.equal(a, b), name
    x = torch.randn(7, network.input_size)
    assert torch.equal(network.eval()(x), loaded(x))


def test_value_output_is_bounded_by_the_scale():
    network = trained_like(ValueNetwork(34, 2.0))
    values = network(torch.randn(1000, 34) * 100)
    assert values.abs().max() <= 2.0


def test_truncated_and_tampered_files_are_refused(tmp_path):
    path = tmp_path / "net.safetensors"
    save_network(trained_like(ValueNetwork(34, 2.0)), path, {})
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
    data = to_bytes(trained_like(ValueNetwork(34, 2.0)))
    with pytest.raises(WeightsError, match="does not match"):
        from_bytes(data, expected={"kind": "value", "input_size": 40})
    with pytest.raises(WeightsError, match="does not match"):
        from_bytes(data, expected={"kind": "sinr_map"})
