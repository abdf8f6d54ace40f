"""Every ``jamnav`` command refuses bad arguments with one line on stderr and exit 2 (1 for a
system that cannot be reached), never a traceback, and before any heavy work: the heavy entry
points are replaced by a trap, so a case that slips through fails instead of training."""

from __future__ import annotations

import json
import re
import socket

import pytest

from jamnav.cli import main
from shared.scenario import SCENARIO_DIR
from shared.shipped import SINR_MAP_NO_JAMMER, VALUE_NET

VALUE = str(VALUE_NET)
SINR_MAP = str(SINR_MAP_NO_JAMMER)

HEAVY = [
    ("cloud_service.value_training", "train"),
    ("cloud_service.evaluation", "run_episodes"),  # eval, table and figures fly with it
    ("cloud_service.sinr_training", "fit_sinr_map"),
    ("cloud_service.online_map_sim", "simulate_online_map"),
    ("shared.plots", "save_coverage_map"),
    ("shared.plots", "plot_reward_curve"),
    ("jamnav.supervisor", "up"),
    ("cloud_service.scenario_tables", "jammer_table_runs"),
]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


# {tmp}: the test's directory; {file}: a regular file; {dir}, {tmp}/dir.png and
# {tmp}/dir.safetensors: directories; {binary}: a file that is not UTF-8; {dangling}: a link
# to a file in a directory that does not exist; {header_only}: a training log of no episodes;
# {bools}: points given as JSON booleans; {extended_run}, {broken_run}, {older_run}:
# checkpoints train --resume cannot use; {port}: a free loopback port (no router behind it);
# {other_world}: a scenario in a radio world no shipped survey map was learned in; {broken}: a
# TOML file that does not parse.
CASES = [
    # scenario show
    (["scenario", "show", "--scenario", "nope"], 2),
    (["scenario", "show", "--scenario", "{binary}"], 2),
    (["scenario", "show", "--scenario", "{dir}"], 2),
    (["scenario"], 2),
    # the system's commands, on a scenario that does not parse
    (["up", "--scenario", "{broken}"], 2),
    (["console", "--scenario", "{broken}"], 2),
    # sinr
    (["sinr", "--at", "1,1", "--jammer", "1,2"], 2),
    (["sinr", "--at", "1,1", "--jammer", "a,b,c"], 2),
    (["sinr", "--at", "1,1", "--jammer", "nan,0,1"], 2),
    (["sinr", "--at", "1,1", "--jammer", "0,0,inf"], 2),
    (["sinr", "--at", "1,1", "--jammer", "0,0,-1"], 2),
    (["sinr", "--at", "1,1", "--jammer", "1000,0,1"], 2),
    (["sinr", "--at", "1,1", "--jammer", "0,0,1", "--no-jammer"], 2),
    (["sinr", "--at", "nan,1"], 2),
    (["sinr"], 2),
    (["sinr", "--points-json", "{binary}"], 2),
    (["sinr", "--points-json", "{dir}"], 2),
    (["sinr", "--points-json", "{bools}"], 2),
    (["sinr", "--at", "1,1", "--model", "{tmp}/missing.safetensors"], 2),
    (["sinr", "--at", "1,1", "--model", "{binary}"], 2),
    (["sinr", "--at", "1,1", "--model", VALUE], 2),
    (["sinr", "--at", "1,1", "--model", SINR_MAP, "--jammer", "0,0,1"], 2),
    # map
    (["map", "--out", "{tmp}/map.jpg"], 2),
    (["map", "--out", "{file}/map.png"], 2),
    (["map", "--out", "{tmp}/dir.png"], 2),
    (["map", "--out", "{tmp}/map.png", "--resolution", "0"], 2),
    (["map", "--out", "{tmp}/map.png", "--resolution", "5000"], 2),
    (["map", "--out", "{tmp}/map.png", "--jammer", "0,0,-1"], 2),
    (["map", "--out", "{tmp}/map.png", "--jammer", "0,0,2000"], 2),
    (["map", "--out", "{tmp}/map.png", "--jammer", "0,0,1,5000"], 2),
    (["map", "--out", "{tmp}/map.png", "--jammer", ""], 2),
    (["map", "--out", "{dangling}"], 2),
    (["map", "--out", "/proc/map.png"], 2),  # writable by its mode, to root; not in fact
    # eval
    (["eval", "--episodes", "0"], 2),
    (["eval", "--episodes", "-3"], 2),
    (["eval", "--episodes", "nan"], 2),
    (["eval", "--uavs", "0"], 2),
    (["eval", "--uavs", "1025"], 2),
    (["eval", "--seed", "-1"], 2),
    (["eval", "--seed", str(2**64)], 2),
    (["eval", "--method", "magic"], 2),
    (["eval", "--jammer", "0,0,1", "--no-jammer"], 2),
    (["eval", "--jammer", "nan,0,1"], 2),
    (["eval", "--model", "{tmp}/missing.safetensors", "--episodes", "1"], 2),
    (["eval", "--model", SINR_MAP, "--episodes", "1"], 2),
    (["eval", "--sinr-map", VALUE, "--episodes", "1"], 2),
    (["eval", "--scenario", "nope"], 2),
    (["eval", "--scenario", "{dir}"], 2),
    (["eval", "--uavs", "200", "--method", "straight", "--episodes", "1"], 2),
    (["eval", "--method", "orca", "--model", "paper", "--episodes", "1"], 2),
    (["eval", "--method", "perfect", "--sinr-map", SINR_MAP, "--episodes", "1"], 2),
    # table
    (["table", "--episodes", "0"], 2),
    (["table", "--seed", "-1"], 2),
    (["table", "--out", "{file}"], 2),
    (["table", "--out", "{file}/sub", "--episodes", "1"], 2),
    (["table", "--model", "{tmp}/missing.safetensors", "--out", "{tmp}/t"], 2),
    (["table", "--extended-model", "{binary}", "--out", "{tmp}/t"], 2),
    # figures
    (["figures", "--seed", "-1", "--out", "{tmp}/f"], 2),
    (["figures", "--out", "{file}"], 2),
    (["figures", "--train-log", "{tmp}/missing.csv", "--out", "{tmp}/f"], 2),
    (["figures", "--train-log", "{binary}", "--out", "{tmp}/f"], 2),
    (["figures", "--train-log", "{file}", "--out", "{tmp}/f"], 2),
    (["figures", "--train-log", "{header_only}", "--out", "{tmp}/f"], 2),
    (["figures", "--train-log", "{dir}", "--out", "{tmp}/f"], 2),
    (["figures", "--model", "{tmp}/missing.safetensors", "--out", "{tmp}/f"], 2),
    # train
    (["train", "--episodes", "0", "--out", "{tmp}/r"], 2),
    (["train", "--envs", "0", "--out", "{tmp}/r"], 2),
    (["train", "--uavs", "0", "--out", "{tmp}/r"], 2),
    (["train", "--uavs", "99", "--out", "{tmp}/r"], 2),
    (["train", "--seed", "-1", "--out", "{tmp}/r"], 2),
    (["train", "--device", "foo", "--out", "{tmp}/r"], 2),
    (["train", "--device", "mps", "--out", "{tmp}/r"], 2),
    (["train", "--device", "cuda:abc", "--out", "{tmp}/r"], 2),
    (["train", "--device", "cuda:99", "--out", "{tmp}/r"], 2),
    (["train", "--method", "magic"], 2),
    (["train", "--final-lr", "0", "--out", "{tmp}/r"], 2),
    (["train", "--final-lr", "0.01", "--out", "{tmp}/r"], 2),
    (["train", "--final-lr", "nan", "--out", "{tmp}/r"], 2),
    (["train", "--final-lr", "falling", "--out", "{tmp}/r"], 2),
    (["train", "--out", "{file}"], 2),
    (["train", "--out", "{file}/sub"], 2),
    (["train", "--resume", "--out", "{tmp}/r"], 2),
    (["train", "--resume", "--out", "{extended_run}"], 2),
    (["train", "--resume", "--out", "{broken_run}"], 2),
    (["train", "--resume", "--out", "{older_run}"], 2),
    (["train", "--scenario", "nope"], 2),
    # fit-sinr
    (["fit-sinr", "--out", "{tmp}/m.pt"], 2),
    (["fit-sinr", "--out", "{tmp}/m.safetensors", "--samples", "0"], 2),
    (["fit-sinr", "--out", "{tmp}/m.safetensors", "--samples", str(10**12)], 2),
    (["fit-sinr", "--out", "{tmp}/m.safetensors", "--steps", "0"], 2),
    (["fit-sinr", "--out", "{tmp}/m.safetensors", "--seed", "-1"], 2),
    (["fit-sinr", "--out", "{tmp}/m.safetensors", "--jammer", "a,b,c"], 2),
    (["fit-sinr", "--out", "{file}/m.safetensors"], 2),
    (["fit-sinr", "--out", "{tmp}/dir.safetensors"], 2),
    (["fit-sinr"], 2),
    # the cloud's latency
    (["eval", "--cloud-latency", "-1"], 2),
    (["eval", "--cloud-latency", "nan"], 2),
    (["eval", "--cloud-latency", "1e9"], 2),
    (["eval", "--method", "perfect", "--cloud-latency", "1"], 2),
    (["eval", "--method", "outdated", "--reports", "db"], 2),
    (["eval", "--reports", "decibel"], 2),
    (["table", "--cloud-latency", "inf", "--out", "{tmp}/t"], 2),
    (["cloud-latency", "--latencies", "0,x", "--out", "{tmp}/c"], 2),
    (["cloud-latency", "--latencies", "-1", "--out", "{tmp}/c"], 2),
    (["cloud-latency", "--latencies", "", "--out", "{tmp}/c"], 2),
    (["cloud-latency", "--seeds", "0", "--out", "{tmp}/c"], 2),
    (["cloud-latency", "--episodes", "0", "--out", "{tmp}/c"], 2),
    (["cloud-latency", "--swap-every", "0", "--out", "{tmp}/c"], 2),
    (["cloud-latency", "--uavs", "500", "--out", "{tmp}/c"], 2),
    (["cloud-latency", "--out", "{file}/c"], 2),
    # online-map
    (["online-map", "--out", "{tmp}/o.jpg"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--uavs", "0"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--period", "0"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--period", "nan"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--period", "inf"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--period", "0.001"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--period", "1e300"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--uavs", "10000"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--seed", "-1"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--model", "{tmp}/missing.safetensors"], 2),
    (["online-map", "--out", "{tmp}/o.png", "--model", VALUE], 2),
    (["online-map", "--out", "{file}/o.png"], 2),
    (["online-map", "--out", "{tmp}/dir.png"], 2),
    # the system's commands (jamnav/cli_up.py, jamnav/cli_runtime.py)
    (["up", "--uavs", "0"], 2),
    (["up", "--episodes", "0"], 2),
    (["up", "--rate", "nan"], 2),
    (["up", "--duration", "inf"], 2),
    (["up", "--episodes", "1", "--duration", "5"], 2),
    (["up", "--jammer", "1,2"], 2),
    (["up", "--jammer", "999,0,1"], 2),
    (["up", "--uavs", "300"], 2),
    (["up", "--swap-to", "0,0,-1"], 2),
    (["up", "--model", "{tmp}/missing.safetensors"], 2),
    (["up", "--retrain-samples", "1"], 2),
    (["up", "--prefix", "bad prefix"], 2),
    (["up", "--endpoint", "nonsense"], 2),
    (["up", "--run-dir", "{file}"], 2),
    (["up", "--report", "{dir}"], 2),
    (["up", "--seed", "-1"], 2),
    (["up", "--model", "{binary}"], 2),
    (["up", "--model", SINR_MAP], 2),
    (["up", "--swap-to", "0,0,1"], 2),
    (["up", "--scenario", "{other_world}"], 2),
    (["up", "--map", "perfect", "--sinr-map", SINR_MAP], 2),
    (["up", "--sinr-map", VALUE], 2),
    (["eval", "--scenario", "{other_world}", "--method", "proposed"], 2),
    (["up", "--rate", "20"], 2),
    (["status", "--endpoint", "tcp/127.0.0.1:notaport"], 2),
    (["status", "--endpoint", "foo/bar"], 2),
    (["router", "--endpoint", "tcp/127.0.0.1:70000"], 2),
    (["router", "--id", "a/b", "--endpoint", "tcp/127.0.0.1:{port}"], 2),
    (["router", "--id", "*", "--endpoint", "tcp/127.0.0.1:{port}"], 2),
    (["jammer", "set", "0,0,nan"], 2),
    (["jammer", "set", "0,0,-1"], 2),
    (["jammer", "set", "0,0,1,-1"], 2),
    (["jammer", "set", "0,0,1e300"], 2),
    (["jammer", "set", "0,0,1,1e9"], 2),
    (["jammer", "set", "0,0"], 2),
    (["jammer", "set", "a,0,1"], 2),
    (["jammer", "set", "--x", "0", "--y", "0"], 2),
    (["jammer", "off", "--endpoint", "nonsense"], 2),
    (["jammer"], 2),
    (["jammer", "add", "0,0"], 2),
    (["jammer", "move", "7", "0,0"], 2),
    (["jammer", "move", "1", "0"], 2),
    (["jammer", "move", "one", "0,0"], 2),
    (["jammer", "remove"], 2),
    (["jammer", "remove", "-1"], 2),
    (["jammer", "off", "9"], 2),
    (["up", "--scenario", "convoy", "--map", "perfect"], 2),
    (["fit-sinr", "--scenario", "two-jammers", "--out", "{tmp}/m.safetensors"], 2),
    (["jammers-table"], 2),
    (["jammers-table", "two-jammers", "--episodes", "0"], 2),
    (["jammers-table", "two-jammers", "--jobs", "0"], 2),
    (["jammers-table", "two-jammers", "--out", "{file}"], 2),
    (["jammers-table", "{other_world}", "--seeds", "1", "--episodes", "1"], 2),
    (["status", "--endpoint", "nonsense"], 2),
    (["status", "--prefix", ""], 2),
    (["status", "--endpoint", "tcp/127.0.0.1:{port}"], 1),
    (["router", "--endpoint", "nonsense"], 2),
    (["router", "--connect", "nonsense", "--endpoint", "tcp/127.0.0.1:{port}"], 2),
]


@pytest.fixture
def places(tmp_path, monkeypatch):
    """Files for the cases, the test's directory as working directory (where default outputs
    would go) and every heavy entry point trapped."""
    for module, name in HEAVY:
        def trap(*_args, _name=name, **_kwargs):
            raise AssertionError(f"{_name} was reached: the arguments were not refused first")

        monkeypatch.setattr(f"{module}.{name}", trap)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file").write_text("not a directory\n")
    for name in ("dir", "dir.png", "dir.safetensors"):
        (tmp_path / name).mkdir()
    (tmp_path / "binary").write_bytes(b"\xff\xfe\x00\x81 not text")
    (tmp_path / "dangling.png").symlink_to(tmp_path / "missing" / "map.png")
    (tmp_path / "header_only.csv").write_text("episode,mean_return,straight_bound\n")
    (tmp_path / "bools.json").write_text(json.dumps([[True, False]]))
    extended = tmp_path / "extended_run" / "checkpoint"
    extended.mkdir(parents=True)
    (extended / "progress.json").write_text(json.dumps({"config": {"method": "extended"}}))
    broken = tmp_path / "broken_run" / "checkpoint"
    broken.mkdir(parents=True)
    (broken / "progress.json").write_text(json.dumps({"config": {"method": "paper"},
                                                      "checkpoint_scores": []}))
    (broken / "value.safetensors").write_bytes(b"truncated")
    older = tmp_path / "older_run" / "checkpoint"  # from before checkpoints were scored
    older.mkdir(parents=True)
    (older / "progress.json").write_text(json.dumps({"config": {"method": "paper"}}))
    shadowed = (SCENARIO_DIR / "icc2021-shadowed.toml").read_text(encoding="utf-8")
    assert "gbs_sigma_db = 3.0" in shadowed
    (tmp_path / "other_world.toml").write_text(
        shadowed.replace("gbs_sigma_db = 3.0", "gbs_sigma_db = 4.0"), encoding="utf-8")
    (tmp_path / "broken.toml").write_text('name = "broken"\n[area\n', encoding="utf-8")
    return {
        "other_world": str(tmp_path / "other_world.toml"),
        "broken": str(tmp_path / "broken.toml"),
        "tmp": str(tmp_path), "file": str(tmp_path / "file"), "dir": str(tmp_path / "dir"),
        "binary": str(tmp_path / "binary"), "bools": str(tmp_path / "bools.json"),
        "dangling": str(tmp_path / "dangling.png"),
        "header_only": str(tmp_path / "header_only.csv"),
        "extended_run": str(tmp_path / "extended_run"),
        "broken_run": str(tmp_path / "broken_run"), "older_run": str(tmp_path / "older_run"),
        "port": str(_free_port()),
    }


USAGE_ERROR = re.compile(r"^jamnav( [\w-]+)*: error: \S")


@pytest.mark.parametrize(("argv", "code"), CASES, ids=[" ".join(a) for a, _ in CASES])
def test_bad_arguments_are_refused_in_one_line(capsys, places, argv, code):
    argv = [part.format(**places) for part in argv]
    try:
        got = main(argv)
    except SystemExit as exc:  # argparse's own usage errors
        got = exc.code
    out, err = capsys.readouterr()
    assert got == code, err
    assert "Traceback" not in err and out == ""
    lines = err.splitlines()
    assert lines, "no message"
    if lines[0].startswith("usage:"):
        assert USAGE_ERROR.match(lines[-1]), err
        assert all(line.startswith(("usage:", " ")) for line in lines[:-1]), err
    else:
        assert len(lines) == 1 and lines[0].startswith("jamnav: error: "), err


def test_an_environment_endpoint_is_checked_too(capsys, monkeypatch):
    monkeypatch.setenv("JAMNAV_ENDPOINT", "nonsense")
    assert main(["status"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jamnav: error: endpoint 'nonsense'") and err.count("\n") == 1


@pytest.mark.parametrize("command", [["scenario", "show"], ["up"], ["console"]])
def test_a_scenario_that_cannot_be_read_is_one_line(capsys, places, monkeypatch, command):
    """Permissions cannot be taken away from root, so the read itself is made to fail."""
    import shared.scenario

    def unreadable(*_args, **_kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(shared.scenario.Path, "read_text", unreadable)
    assert main(command) == 2
    err = capsys.readouterr().err
    assert err.startswith("jamnav: error: ") and err.endswith("icc2021.toml: Permission denied\n")
