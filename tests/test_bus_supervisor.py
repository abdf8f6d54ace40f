"""``jamnav up`` for real: every role a separate OS process behind a router on a free loopback
port. Checks the report against ``jamnav eval``, live control of a running system (jammer,
status), the restart of a killed agent, and that nothing outlives the supervisor."""

from __future__ import annotations

import json
import math
import os
import signal
from pathlib import Path

import pytest

from cloud_service.evaluation import evaluate
from cloud_service.sinr_memory import RUN_DIR_FILE, SinrMemory
from jamnav.cli import main as jamnav
from shared.measurements import MeasurementSpec
from shared.paper import JammerSetting
from shared.scenario import load_scenario, resolve_scenario_path
from shared.shipped import SINR_MAP_NO_JAMMER
from tests.support import free_endpoint, gone, wait_until


def run_json(capsys, *argv: str):
    code = jamnav(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.parametrize("uavs, episodes", [(3, 2), (16, 1)])
def test_up_runs_seeded_episodes_like_eval_and_leaves_nothing_behind(supervisor, capsys,
                                                                     tmp_path, uavs, episodes):
    endpoint = free_endpoint()
    # A step waits up to 10 s for every action: sixteen agents on a busy 2-core machine may
    # need more than the default 2 s, and a missed deadline would be a different flight.
    process = supervisor("--uavs", str(uavs), "--episodes", str(episodes), "--lockstep",
                         "--map", "perfect", "--jammer", "0,0,1", "--seed", "5",
                         "--deadline", "10", "--no-figures", "--endpoint", endpoint,
                         "--run-dir", str(tmp_path / "run"))
    out, err = process.communicate(timeout=150 + 10 * uavs)
    assert process.returncode == 0, err[-2000:]
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert sorted(p["role"] for p in report["processes"]) == [
        *["agent"] * uavs, "cloud", "router", "world"]
    assert all(gone(p["pid"]) for p in report["processes"])
    code, eval_out, _ = run_json(capsys, "eval", "--method", "perfect", "--episodes",
                                 str(episodes), "--uavs", str(uavs), "--seed", "5",
                                 "--jammer", "0,0,1", "--per-episode", "--json")
    expected = json.loads(eval_out)
    assert report["outcomes"] == expected["outcomes"]
    for key in ("success_rate", "disconnection_rate", "collision_rate", "timeout_rate"):
        assert report[key] == pytest.approx(expected[key])
    assert report["steps_per_second"] > 0 and report["missed_deadlines"] == 0
    for agent in report["agents"].values():
        # Each decision's wait for the deciding thread is part of its wall time, so the
        # order statistics keep that order too.
        assert 0 <= agent["decision_wait_p99_us"] <= agent["decision_p99_us"]
        assert 0 < agent["decision_cpu_p99_us"]
    assert report["restarts"] == {"router": 0, "world": 0, "cloud": 0, "agent": 0}
    assert report["dropped_messages"] == {}
    assert [e["type"] for e in report["events"]].count("uav_outcomes") == episodes
    assert all(isinstance(e["t"], float) for e in report["events"])
    assert "success" in out and report["stopped_by"] == "end"
    # 16 UAVs on icc2021's hectare are a crowd: both paths chose the network trained in one.
    assert report["model"] == ("extended-crowd" if uavs == 16 else "extended")


def test_a_running_system_is_controlled_restarts_a_dead_agent_and_stops_on_ctrl_c(
        supervisor, capsys, tmp_path):
    endpoint = free_endpoint()
    run_dir = tmp_path / "run"
    process = supervisor("--uavs", "2", "--map", "perfect", "--endpoint", endpoint,
                         "--run-dir", str(run_dir))

    def status():
        code, out, _ = run_json(capsys, "status", "--json", "--endpoint", endpoint)
        return json.loads(out) if code == 0 else []

    def agent_pid(uav: int):
        return next((p["pid"] for p in status() if p["role"] == "agent" and p["id"] == str(uav)
                     and p.get("details", {}).get("decisions")), None)

    first = wait_until(lambda: agent_pid(1), 90, "agent 1 flying")
    os.kill(first, signal.SIGKILL)
    wait_until(lambda: (pid := agent_pid(1)) and pid != first, 60, "agent 1 restarted")
    world = next(p for p in status() if p["role"] == "world")
    assert world["details"]["live_agents"] == 2
    # Meanwhile the world flew UAV 1 on its last velocity, and counted the steps.
    assert world["details"]["unattended_steps"] > 0

    code, out, err = run_json(capsys, "jammer", "set", "500,0,1",
                              "--endpoint", endpoint)
    assert code == 2 and "outside the area" in err and err.count("\n") == 1
    assert json.loads(out)["accepted"] is False
    code, _, err = run_json(capsys, "jammer", "set", "0,0,nan",
                            "--endpoint", endpoint)
    assert code == 2 and err.count("\n") == 1
    code, out, _ = run_json(capsys, "jammer", "set", "-25,-10,0.5", "--endpoint", endpoint)
    assert code == 0 and [j["x"] for j in json.loads(out)["jammers"]] == [-25.0]
    code, out, _ = run_json(capsys, "jammer", "show", "--endpoint", endpoint)
    assert code == 0 and json.loads(out)["jammers"][0]["power_w"] == 0.5
    wait_until(lambda: any(p["role"] == "cloud" and p["sinr_version"] == 2 for p in status()),
               30, "the true map of the new jammer")
    # A second jammer, moved, then removed; a jammer that is not there is refused in a line.
    code, out, _ = run_json(capsys, "jammer", "add", "20,20,1", "--endpoint", endpoint)
    assert code == 0 and [j["id"] for j in json.loads(out)["jammers"]] == [0, 1]
    code, out, _ = run_json(capsys, "jammer", "move", "1", "10,-5", "--endpoint", endpoint)
    assert code == 0 and json.loads(out)["jammers"][1] == {
        "id": 1, "x": 10.0, "y": -5.0, "power_w": 1.0, "height_m": 30.0, "path": None,
        "schedule": None}
    code, _, err = run_json(capsys, "jammer", "remove", "3", "--endpoint", endpoint)
    assert code == 2 and "no jammer 3 (in force: 0, 1)" in err and err.count("\n") == 1
    code, out, _ = run_json(capsys, "jammer", "remove", "1", "--endpoint", endpoint)
    assert code == 0 and [j["id"] for j in json.loads(out)["jammers"]] == [0]
    code, out, _ = run_json(capsys, "status", "--endpoint", endpoint)
    assert code == 0 and "world-0" in out and "agent-1" in out

    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 0, err[-2000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["stopped_by"] == "signal"
    assert report["restarts"]["agent"] == 1
    assert first in [p["pid"] for p in report["processes"]]
    assert all(gone(p["pid"]) for p in report["processes"])
    changes = [e for e in report["events"] if e["type"] == "jammer_changed"]
    assert [[j["x"] for j in change["jammers"]] for change in changes[-3:]] == [
        [-25.0, 20.0], [-25.0, 10.0], [-25.0]]
    for figure in report["figures"]:
        assert Path(figure).stat().st_size > 10_000
    code, _, err = run_json(capsys, "status", "--endpoint", endpoint)
    assert code == 1 and err.count("\n") == 1


def _reports_in(path: Path, scenario) -> list[tuple]:
    """The measurements of a memory, as a sorted list of (level, features): the same reports
    in any order and with any ids or time stamps compare equal."""
    with SinrMemory(path, MeasurementSpec.of(scenario)) as memory:
        stored = memory.recent(memory.count())
    return sorted(zip(stored.levels.tolist(), map(tuple, stored.features.round(4).tolist()),
                      strict=True))


def test_agents_measure_and_upload_what_the_in_process_evaluation_uploads(supervisor,
                                                                         scenario, tmp_path):
    """One measurement model: same seed, no jammer and a detector that never fires (so the
    map stays the survey map in both and the flights agree step for step; the idealized
    survey map never met receiver noise and would take it for a change), then the same
    outcomes and the very same reports in the cloud's memory, noise and de-duplication
    included."""
    noisy = tmp_path / "noisy.toml"
    noisy.write_text(Path(resolve_scenario_path("icc2021")).read_text().replace(
        "measurement_noise_db = 0.0", "measurement_noise_db = 1.0").replace(
        "change_threshold = 12.0", "change_threshold = 1e9"))
    # The default network, so the whole planner of an agent (route fields swept in numpy,
    # the deeper search, the reciprocal model) flies the in-process planner's paths.
    # No survey map was learned in this world: both fly icc2021's, named.
    process = supervisor("--uavs", "3", "--episodes", "2", "--lockstep", "--map", "online",
                         "--no-jammer", "--seed", "8", "--no-figures", "--scenario", str(noisy),
                         "--sinr-map", str(SINR_MAP_NO_JAMMER),
                         "--endpoint", free_endpoint(), "--run-dir", str(tmp_path / "run"))
    _, err = process.communicate(timeout=150)
    assert process.returncode == 0, err[-2000:]
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    world = load_scenario(noisy)
    expected = evaluate(world, "proposed", 2, 8, None, 3, sinr_map=SINR_MAP_NO_JAMMER,
                        memory_dir=tmp_path / "eval")
    assert report["model"] == "extended"
    assert report["outcomes"] == expected["outcomes"]
    assert not any(e["type"] == "change_detected" for e in report["events"])
    on_the_bus = _reports_in(tmp_path / "run" / RUN_DIR_FILE, world)
    in_process = _reports_in(tmp_path / "eval" / "measurements.sqlite", world)
    assert len(in_process) > 100 and on_the_bus == in_process


def _memory_rows(path: Path, scenario) -> list[tuple]:
    """A memory's measurements in the order they arrived, all but their ids (an agent's and
    the in-process evaluation's differ): source, step, time, level, SINR (None for a level
    report) and features."""
    with SinrMemory(path, MeasurementSpec.of(scenario)) as memory:
        stored = memory.recent(memory.count())
    sinr_db = [None if math.isnan(db) else db for db in stored.sinr_db.tolist()]
    return list(zip(stored.sources, stored.steps.tolist(), stored.times.tolist(),
                    stored.levels.tolist(), sinr_db, map(tuple, stored.features.tolist()),
                    strict=True))


# A driven jammer and a blinking one, beside the convoy's: what the world moves and switches.
MOVING_JAMMERS = """
[[jammers]]
x = 20.0
y = -20.0
power_w = 1.0
height_m = 30.0
efficiency_db = -20.0
[jammers.path]
waypoints = [[20.0, 20.0], [-20.0, 20.0]]
speed_mps = 4.0
loop = true
[[jammers]]
x = -25.0
y = -25.0
power_w = 1.0
height_m = 30.0
efficiency_db = -20.0
[jammers.schedule]
kind = "duty"
on_s = 5.0
off_s = 3.0
"""


@pytest.mark.parametrize(("latency", "reports", "jammers"),
                         [(None, "level", "swapped"), (0.0, "level", "swapped"),
                          (30.0, "db", "swapped"), (None, "level", "moving")],
                         ids=["scenario-latency", "no-latency", "db-reports-30-s-latency",
                              "moving-jammers"])
def test_the_cloud_on_the_lockstep_clock_flies_eval_s_maps_and_outcomes(supervisor, tmp_path,
                                                                       latency, reports,
                                                                       jammers):
    """Lockstep with the online map puts the cloud on the clock: each step's uploads are
    taken, and what they trigger finished, before the world goes on, in simulated time. The
    same seed, jammers (a fresh one every 2 episodes; or three of a scenario file, driving
    and blinking), cloud latency and reports then give what ``jamnav eval --method
    proposed`` gives: the same maps, published at the same flight times (so in service at the
    same steps), the same stored measurements, in order, and the same per-UAV outcomes."""
    run = tmp_path / "run"
    extra = [] if latency is None else ["--cloud-latency", str(latency)]
    scenario = load_scenario()
    if reports == "db":  # a scenario file whose receivers report the SINR, as users write one
        path = tmp_path / "reporting.toml"
        path.write_text(resolve_scenario_path(None).read_text().replace(
            'report = "level"', 'report = "db"', 1))
        scenario = load_scenario(path)
        assert scenario.uav.report == "db"
        extra += ["--scenario", str(path)]
    if jammers == "moving":
        path = tmp_path / "moving.toml"
        path.write_text(resolve_scenario_path("convoy").read_text().replace(
            "[rewards]", MOVING_JAMMERS + "\n[rewards]", 1))
        scenario = load_scenario(path)
        assert len(scenario.jammers) == 3
        extra += ["--scenario", str(path)]
        flown = scenario.flown_jammers
    else:
        extra += ["--jammer", "0,0,1", "--swap-every", "2"]
        flown = JammerSetting(0.0, 0.0, 1.0)
    process = supervisor("--uavs", "3", "--episodes", "4", "--lockstep", "--map", "online",
                         "--seed", "5", "--deadline", "10", "--no-figures", *extra,
                         "--endpoint", free_endpoint(), "--run-dir", str(run))
    _, err = process.communicate(timeout=400)
    assert process.returncode == 0, err[-2000:]
    report = json.loads((run / "report.json").read_text())
    if latency is not None:
        scenario = scenario.changed({"online_map.cloud_latency_s": latency})
    expected = evaluate(scenario, "proposed", 4, 5, flown, 3,
                        swap_every=None if jammers == "moving" else 2,
                        memory_dir=tmp_path / "eval")
    published = [(e["t"], e["sha256"]) for e in expected["events"]
                 if e["type"] == "sinr_weights_published"]
    cards = sorted((json.loads(card.read_text()) for card in
                    (run / "sinr_maps").glob("sinr_map_v*.json")), key=lambda c: c["version"])
    assert len(published) >= 2  # the jammers were met, and the maps followed them
    assert [(card["flown_s"], card["sha256"]) for card in cards] == published
    stored = _memory_rows(run / RUN_DIR_FILE, scenario)
    assert stored == _memory_rows(tmp_path / "eval" / "measurements.sqlite", scenario)
    assert all((row[4] is not None) == (reports == "db") for row in stored)
    assert report["outcomes"] == expected["outcomes"]
    assert report["missed_deadlines"] == 0
