"""jamnav eval: rates add up, runs are reproducible, batching does not change results."""

from __future__ import annotations

import json

import numpy as np

from cloud_service.rollout import StraightController, run_episodes
from jamnav.cli import main
from shared.paper import JammerSetting


def run_json(capsys, *argv):
    assert main(["eval", "--json", *argv]) == 0
    return json.loads(capsys.readouterr().out)


def test_rates_add_up_and_per_episode_is_reproducible(capsys):
    argv = ["--method", "straight", "--episodes", "12", "--seed", "3", "--per-episode"]
    first = run_json(capsys, *argv)
    second = run_json(capsys, *argv)
    rates = [first[k] for k in ("success_rate", "disconnection_rate", "collision_rate",
                                "timeout_rate")]
    assert abs(sum(rates) - 1.0) < 1e-9
    assert first["outcomes"] == second["outcomes"]
    assert len(first["outcomes"]) == 12 and {len(row) for row in first["outcomes"]} == {4}
    labels = {label for row in first["outcomes"] for label in row}
    assert labels <= {"success", "disconnection", "collision", "timeout"}
    assert (first["episodes"], first["uavs"], first["seed"]) == (12, 4, 3)


def test_results_do_not_depend_on_how_many_environments_fly_at_once(scenario):
    jammer = JammerSetting(0.0, 0.0, 1.0)
    wide = run_episodes(scenario, StraightController(), 10, 7, jammer, num_envs=10)
    narrow = run_episodes(scenario, StraightController(), 10, 7, jammer, num_envs=3)
    np.testing.assert_array_equal(wide.outcomes, narrow.outcomes)


def test_the_jammer_costs_straight_flights_missions(capsys):
    jammed = run_json(capsys, "--method", "straight", "--episodes", "60", "--jammer", "0,0,1")
    clear = run_json(capsys, "--method", "straight", "--episodes", "60", "--no-jammer")
    assert jammed["success_rate"] < clear["success_rate"]


def test_bad_model_is_a_one_line_error(capsys, tmp_path):
    bogus = tmp_path / "value.safetensors"
    bogus.write_bytes(b"not weights")
    assert main(["eval", "--method", "perfect", "--episodes", "1", "--model", str(bogus)]) == 2
    err = capsys.readouterr().err
    assert "--model" in err and err.count("\n") == 1
