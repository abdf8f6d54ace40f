"""Coordinates are often negative: every command and process that takes a position reads
"-25,15,1" as a value, never as an unknown option (argparse's default)."""

from __future__ import annotations

import json

import pytest

from cloud_service.process import build_parser as cloud_parser
from jamnav.cli import main
from jamnav.supervisor import Child, Supervisor, UpConfig
from shared.jammer_messages import JammerInfo, initial_jammers
from tests.test_radio import reference_sinr_db
from world_sim.process import build_parser as world_parser

JAMMER = "-25,15,1"


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_sinr_takes_a_jammer_and_points_left_and_below_the_origin(capsys, scenario):
    code, out, err = run(capsys, "sinr", "--jammer", JAMMER, "--at", "-10,-5", "-40.5,-0.5")
    assert code == 0, err
    jammer = (-25.0, 15.0, 1.0, scenario.jammer.height_m)
    for row in json.loads(out):
        want_db, want_gbs = reference_sinr_db(scenario, row["x"], row["y"], jammer)
        assert row["x"] < 0 and row["y"] < 0
        assert row["sinr_db"] == pytest.approx(want_db, abs=1e-4)
        assert row["serving_gbs"] == want_gbs


@pytest.mark.parametrize("argv", [
    ["map", "--jammer", JAMMER, "--out", "{tmp}/map.png", "--resolution", "20"],
    ["eval", "--jammer", JAMMER, "--method", "straight", "--episodes", "1", "--json"],
    ["fit-sinr", "--jammer", JAMMER, "--samples", "200", "--steps", "2",
     "--out", "{tmp}/m.safetensors"],
])
def test_commands_taking_a_jammer_accept_a_negative_position(capsys, tmp_path, argv):
    code, _, err = run(capsys, *(a.replace("{tmp}", str(tmp_path)) for a in argv))
    assert code == 0, err


def test_up_checks_and_hands_a_negative_jammer_to_its_children(capsys, tmp_path, scenario):
    # Refused before anything starts when outside the area; accepted when inside.
    code, _, err = run(capsys, "up", "--jammer", "-999,15,1", "--run-dir", str(tmp_path / "r"))
    assert code == 2 and "outside" in err
    code, _, err = run(capsys, "up", "--swap-jammer-at", "1", "--swap-to", "-999,-10,1",
                       "--run-dir", str(tmp_path / "r"))
    assert code == 2 and "outside the area" in err

    config = UpConfig(endpoint="tcp/127.0.0.1:1", run_dir=tmp_path, jammer=JAMMER)
    supervisor = Supervisor(config, scenario)
    want = JammerInfo.parse(JAMMER, scenario.jammer.height_m)
    for role, parser in (("world", world_parser()), ("cloud", cloud_parser())):
        argv = supervisor._argv(Child(role, 0, tmp_path / "log"))
        parsed = parser.parse_args(argv[argv.index("-m") + 2:])
        assert initial_jammers(scenario, parsed.jammer, parsed.jammers, parsed.no_jammer) == (
            want,)
