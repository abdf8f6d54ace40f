from __future__ import annotations

import json
import subprocess
import sys

import pytest

from jamnav.cli import main
from tests.test_radio import reference_sinr_db


def run(capsys, *argv):
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_scenario_show_json_has_the_acceptance_keys(capsys):
    code, out, _ = run(capsys, "scenario", "show", "--json")
    data = json.loads(out)
    assert code == 0
    assert {"x_min", "x_max", "y_min", "y_max"} <= data["area"].keys()
    assert {"positions", "height_m", "power_w", "tilt_deg", "beamwidth_3db_deg",
            "max_attenuation_db"} <= data["gbs"].keys()
    assert len(data["gbs"]["positions"]) == 12
    assert "altitude_m" in data["uav"]
    assert {"path_loss_exponent", "noise_w", "sinr_threshold_db"} <= data["channel"].keys()
    assert {"x", "y", "power_w", "height_m"} <= data["jammers"][0].keys()


def test_sinr_at_points_matches_the_reference(capsys, scenario):
    code, out, _ = run(capsys, "sinr", "--jammer", "25,-10,0.5", "--at", "0,0", "-12.5,-33")
    rows = json.loads(out)
    assert code == 0 and [set(r) for r in rows] == [{"x", "y", "sinr_db", "level",
                                                       "serving_gbs"}] * 2
    jammer = (25.0, -10.0, 0.5, scenario.jammer.height_m)
    for row in rows:
        want_db, want_k = reference_sinr_db(scenario, row["x"], row["y"], jammer)
        assert row["sinr_db"] == pytest.approx(want_db, abs=1e-5)
        assert row["serving_gbs"] == want_k
    assert rows[1]["level"] == 2 and rows[0]["level"] == 0


def test_sinr_points_json_and_no_jammer(capsys, tmp_path, scenario):
    path = tmp_path / "points.json"
    path.write_text(json.dumps([[12.5, 0], {"x": -37.5, "y": 33}]))
    code, out, _ = run(capsys, "sinr", "--no-jammer", "--points-json", str(path))
    rows = json.loads(out)
    assert code == 0 and len(rows) == 2
    assert rows[0]["sinr_db"] == pytest.approx(reference_sinr_db(scenario, 12.5, 0)[0], abs=1e-5)


def test_map_writes_a_png(capsys, tmp_path):
    out = tmp_path / "map.png"
    code, _, err = run(capsys, "map", "--jammer", "0,0,1", "--out", str(out), "--resolution", "60")
    assert code == 0 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "covered" in err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["sinr", "--jammer", "0,0", "--at", "1,1"], "expected X,Y,P"),
        (["sinr", "--jammer", "0,0,-1", "--at", "1,1"], "power"),
        (["sinr", "--jammer", "99,0,1", "--at", "1,1"], "outside the area"),
        (["sinr", "--at", "1,x"], "expected 2"),
        (["sinr", "--points-json", "/nonexistent/points.json"], "points-json"),
        (["scenario", "show", "--scenario", "nope"], "no such file"),
        (["map", "--out", "map.jpg"], "PNG"),
    ],
)
def test_bad_arguments_give_one_line_and_exit_2(capsys, argv, message):
    code, out, err = run(capsys, *argv)
    assert code == 2 and out == ""
    assert message in err and "Traceback" not in err and err.count("\n") == 1


def test_console_script_reports_errors_without_traceback():
    result = subprocess.run(
        [sys.executable, "-m", "jamnav.cli", "sinr", "--jammer", "nan,0,1", "--at", "1,1"],
        capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 2
    assert "Traceback" not in result.stderr and "jamnav: error" in result.stderr


def test_a_reader_that_goes_away_ends_the_output_without_a_traceback():
    """``jamnav scenario show | head -1``: the pipe is closed before the command writes."""
    process = subprocess.Popen([sys.executable, "-m", "jamnav.cli", "scenario", "show"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()
    err = process.stderr.read().decode()
    assert process.wait(60) == 141 and err == ""
