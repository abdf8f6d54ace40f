"""The summary `jamnav up` prints is for people: rounded figures, words where a number is
missing, success before and after a jammer swap, and the value network named."""

from __future__ import annotations

import inspect
import json
import logging
import threading

import pytest

from cloud_service.evaluation import evaluate, load_policy
from jamnav.run_report import map_delays, summary_table, swap_rates
from shared.scenario import load_scenario
from shared.shipped import (
    DEFAULT_VALUE_NET,
    EXTENDED_CROWD_VALUE_NET,
    EXTENDED_MANY_VALUE_NET,
    EXTENDED_VALUE_NET,
    VALUE_NET,
    best_value_net,
    value_net_for,
    value_net_name,
    value_net_path,
)


def _report(**changes) -> dict:
    report = {
        "episodes": 0, "uavs": 4, "clock": "realtime", "map": "online", "model": "extended",
        "stopped_by": "signal", "steps_per_second": None, "missed_deadlines": None,
        "success_rate": None, "disconnection_rate": None, "collision_rate": None,
        "timeout_rate": None, "swap": None, "restarts": {"router": 0, "world": 0, "cloud": 0,
                                                          "agent": 0},
        "dropped_messages": {}, "events": [],
        "measurements": {"taken": 0, "acknowledged": 0, "buffered": 0, "overflowed": 0,
                         "refused": 0, "duplicates": 0, "upload_failures": 0,
                         "in_memory": None, "memory_of_earlier_runs": False},
    }
    return {**report, **changes}


def test_an_early_ctrl_c_prints_words_not_none():
    text = summary_table(_report())
    assert "None" not in text
    assert "no episode finished" in text
    assert "the cloud's memory was not reached" in text
    assert "restarts       none" in text and "value network extended" in text


def test_restarts_name_the_processes_that_restarted():
    text = summary_table(_report(restarted={"agent-2": 1, "cloud": 3}))
    assert "restarts       agent-2 once, cloud 3 times" in text


def test_rates_are_rounded_and_a_swap_splits_success_by_hand():
    outcomes = {0: ["success"] * 4, 1: ["success", "success", "success", "disconnection"],
                2: ["success", "collision", "timeout", "disconnection"],
                3: ["success"] * 4}
    events = [{"type": "uav_outcomes", "episode": 0},
              {"type": "jammer_changed", "episode": 2, "step": 7,
               "jammers": [{"x": 25.0, "y": -10.0, "power_w": 1.0, "height_m": 30.0}]},
              # as a report written when a world had one jammer names it
              {"type": "jammer_changed", "episode": 3, "step": 1, "jammer": None}]
    swap = swap_rates(events, outcomes)
    # Before: episodes 0 and 1, 7 of 8 UAVs; from episode 2 on: 5 of 8.
    assert swap == {"episode": 2, "before": {"episodes": 2, "success_rate": 7 / 8},
                    "after": {"episodes": 2, "success_rate": 5 / 8}}
    assert swap_rates(events[:1], outcomes) is None
    text = summary_table(_report(
        episodes=4, success_rate=12 / 16, disconnection_rate=2 / 16, collision_rate=1 / 16,
        timeout_rate=1 / 16, swap=swap, steps_per_second=19.98765, missed_deadlines=0,
        events=events, restarts={"router": 0, "world": 0, "cloud": 0, "agent": 2},
        restarted={"agent-3": 2}))
    assert "success 75.0%, disconnection 12.5%, collision 6.2%, timeout 6.2%" in text
    assert ("87.5% before the jammer changed (2 episodes), 62.5% from episode 2 on "
            "(2 episodes)") in text
    assert "20 steps/s, 0 missed deadlines" in text and "restarts       agent-3 2 times" in text
    assert "without a live agent" not in text
    assert "20 steps/s, 0 missed deadlines, 7 UAV-steps without a live agent" in summary_table(
        _report(steps_per_second=20.0, missed_deadlines=0, unattended_steps=7))
    assert "jammer moved to (25, -10), 1 W (episode 2, step 7)" in text
    assert "jammer switched off (episode 3, step 1)" in text
    assert "None" not in text


def test_the_value_network_is_named_by_its_shipped_name_or_its_path(tmp_path):
    assert value_net_name(None) == "extended"
    assert value_net_name(EXTENDED_VALUE_NET) == "extended"
    assert value_net_name(VALUE_NET) == "paper"
    assert value_net_name(tmp_path / "mine.safetensors") == str(tmp_path / "mine.safetensors")
    assert value_net_name(value_net_path("paper-tt6")) == "paper-tt6"


def test_the_default_network_is_the_one_for_the_fleets_density_and_the_worlds_jammers():
    icc2021, city = load_scenario("icc2021"), load_scenario("city")  # 1 ha and 16 ha
    assert best_value_net(icc2021, 4) == best_value_net(icc2021, 7) == EXTENDED_VALUE_NET
    assert best_value_net(icc2021, 8) == best_value_net(icc2021, 16) == EXTENDED_CROWD_VALUE_NET
    assert best_value_net(city, 64) == EXTENDED_VALUE_NET  # the paper's density on 16 ha
    assert best_value_net(city, 128) == EXTENDED_CROWD_VALUE_NET
    assert value_net_for(None, icc2021, 16) == EXTENDED_CROWD_VALUE_NET
    assert value_net_for("paper", icc2021, 16) == VALUE_NET  # asked for, whatever the fleet
    assert value_net_name(EXTENDED_CROWD_VALUE_NET) == "extended-crowd"
    # Two still jammers, or one that drives: the network trained with both.
    for several_or_driving in ("two-jammers", "two-jammers-shadowed", "convoy"):
        assert best_value_net(load_scenario(several_or_driving), 4) == EXTENDED_MANY_VALUE_NET
    assert best_value_net(load_scenario("convoy"), 16) == EXTENDED_CROWD_VALUE_NET  # dense first
    assert best_value_net(load_scenario("two-jammers").without_jammer(), 4) == EXTENDED_VALUE_NET
    # The jammers flown, when they are given: a jammer of no power flies as none.
    first, second = load_scenario("two-jammers").jammers
    assert best_value_net(icc2021, 4, (first, second)) == EXTENDED_MANY_VALUE_NET
    silent = second.model_copy(update={"power_w": 0.0})
    assert best_value_net(icc2021, 4, (first, silent)) == EXTENDED_VALUE_NET
    assert value_net_name(EXTENDED_MANY_VALUE_NET) == "extended-many"


def test_the_library_flies_the_best_network_by_default_too(scenario, monkeypatch):
    """A benchmark or a notebook calling evaluate() gets what `jamnav eval` gets."""
    import cloud_service.evaluation as evaluation

    assert inspect.signature(evaluate).parameters["value_net"].default is None
    flown = []
    monkeypatch.setattr(evaluation, "load_policy", lambda scenario, path: flown.append(path)
                        or load_policy(scenario, path))
    for uavs in (None, 16):
        evaluate(scenario, "perfect", 1, 0, None, uavs)
    assert flown == [EXTENDED_VALUE_NET, EXTENDED_CROWD_VALUE_NET]
    assert DEFAULT_VALUE_NET == "extended"
    # The jammers flown choose, not those the scenario lists: icc2021 given two jammers flies
    # the network trained with several, two-jammers given none the one-jammer network.
    two = load_scenario("two-jammers")
    assert evaluate(scenario, "perfect", 1, 0, two.flown_jammers)["model"] == "extended-many"
    assert evaluate(two, "perfect", 1, 0, None)["model"] == "extended"
    assert flown[2:] == [EXTENDED_MANY_VALUE_NET, EXTENDED_VALUE_NET]


@pytest.mark.parametrize(("argv", "served"), [
    ([], EXTENDED_VALUE_NET),
    (["--scenario", "convoy"], EXTENDED_MANY_VALUE_NET),
    (["--scenario", "two-jammers", "--no-jammer"], EXTENDED_VALUE_NET),
    (["--jammers", json.dumps([{"id": 0, "x": 0.0, "y": 0.0, "power_w": 1.0, "height_m": 30.0},
                               {"id": 1, "x": 20.0, "y": 5.0, "power_w": 0.5, "height_m": 30.0}])],
     EXTENDED_MANY_VALUE_NET),
    (["--scenario", "convoy", "--value-net", "paper"], VALUE_NET),
])
def test_a_cloud_started_alone_serves_the_network_for_the_jammers_it_starts_with(
        capsys, argv, served, monkeypatch):
    """``python -m cloud_service.process`` without --value-net serves what `jamnav eval` would
    fly under the same jammers."""
    import cloud_service.process as cloud_process

    given = []

    def recorded(*args, value_net, **kwargs):
        given.append(value_net)
        raise ValueError("recorded")

    monkeypatch.setattr(cloud_process, "CloudService", recorded)
    setup = cloud_process.cloud_setup(cloud_process.build_parser().parse_args(argv))
    assert setup.run(None, threading.Event(), logging.getLogger("test")) == 2
    assert given == [served] and "recorded" in capsys.readouterr().err


def test_the_clouds_latency_is_told_in_wall_seconds_and_in_flight():
    """Real time at 20 steps of 1 s a second: a map 1.5 s after its change was detected cost
    30 s of flight; maps before any detection are no answer to a change."""
    events = [{"type": "sinr_weights_published", "t": 90.0, "version": 1},
              {"type": "change_detected", "t": 100.0, "version": 1},
              {"type": "sinr_weights_published", "t": 101.5, "version": 2},
              {"type": "sinr_weights_published", "t": 103.0, "version": 3}]
    delays = map_delays(events, 20.0)
    assert delays == [{"version": 2, "after_detection_s": 1.5, "flight_s": 30.0},
                      {"version": 3, "after_detection_s": 3.0, "flight_s": 60.0}]
    wall = summary_table(_report(cloud_latency={"clock": "wall", "maps": delays}))
    assert "cloud latency  first map 1.5 s after the detection (wall), 30 s of flight" in wall
    lockstep = summary_table(_report(cloud_latency={"clock": "lockstep", "latency_s": 2.0}))
    assert "maps fly 2 s of flight after their uploads (lockstep)" in lockstep
