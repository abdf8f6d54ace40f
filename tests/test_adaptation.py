"""The measurement model shared by agents and evaluation, the change detector's rule, the
jammer estimate on the wire, and the resilience evaluation's schedule."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cloud_service.change_detection import ChangeDetector
from cloud_service.evaluation import transient_episodes
from planning.measuring import SpotFilter
from shared.events import JammerEstimated, decode_event
from shared.jammer_messages import JammerEstimate, describe_estimate
from shared.paper import JammerSetting
from shared.scenario import load_scenario
from shared.topics import Topics
from shared.wire import MessageError, decode, encode
from shared.zenoh_cli_codec import zenoh_cli_decoder
from tests.conftest import variant
from world_sim.core import VectorWorld, episode_seed
from world_sim.jammers import jammer_set, swapping_jammers


# -- what a UAV keeps -------------------------------------------------------------------------
def test_spot_filter_keeps_a_report_per_spacing_or_new_level(scenario):
    spots = SpotFilter(variant(scenario, uav={"measurement_spacing_m": 1.0}), 2)
    xy = np.array([[[0.0, 0.0], [0.4, 0.0], [0.9, 0.0], [1.0, 0.0], [1.2, 0.0]],
                   [[5.0, 5.0], [5.0, 5.0], [5.0, 5.0], [5.0, 5.0], [5.0, 5.0]]])
    levels = np.array([[2, 2, 2, 2, 1], [0, 0, 0, 2, 2]])
    kept = spots.keep(np.array([0, 1]), xy, levels)
    # UAV 0: first kept; 0.4 and 0.9 m from it dropped; 1.0 m kept; a new level kept.
    # UAV 1 hovers: the first report, then only the change of level.
    np.testing.assert_array_equal(kept, [[1, 0, 0, 1, 1], [1, 0, 0, 1, 0]])
    # The rule carries over from one call (step) to the next.
    again = spots.keep(np.array([1]), np.array([[[5.0, 5.0], [5.0, 6.0]]]), np.array([[2, 2]]))
    np.testing.assert_array_equal(again, [[0, 1]])


def keep_one_by_one(spacing: float, last: list, uavs, xy, levels) -> np.ndarray:
    """SpotFilter's rule as its docstring states it, one UAV and one report at a time; ``last``
    holds each UAV's last kept (position, level) and is updated."""
    kept = np.zeros(np.shape(levels), dtype=bool)
    for row, uav in enumerate(uavs):
        last_xy, last_level = last[uav]
        for sample, (here, level) in enumerate(zip(xy[row], levels[row], strict=True)):
            if np.hypot(*(here - last_xy)) >= spacing or level != last_level:
                kept[row, sample] = True
                last_xy, last_level = here, level
        last[uav] = (last_xy, last_level)
    return kept


# Coordinates on a 5 cm lattice meet the spacing exactly (hypot == spacing) now and then.
coordinates = st.one_of(st.integers(-40, 40).map(lambda k: k * 0.05),
                        st.floats(-1e4, 1e4, allow_nan=False))


@settings(max_examples=150, deadline=None)
@given(data=st.data(), fleet=st.integers(1, 6), samples=st.integers(1, 12),
       spacing=st.sampled_from([0.0, 0.05, 0.25, 1.0, 0.3]))
def test_spot_filter_keeps_what_the_rule_keeps_report_by_report(data, fleet, samples, spacing,
                                                                 scenario):
    """The vectorized filter (any subset of the fleet a call, several calls) against the rule
    applied one report at a time: the same masks, bit for bit."""
    spots = SpotFilter(variant(scenario, uav={"measurement_spacing_m": spacing}), fleet)
    last = [(np.array([np.inf, np.inf]), -1)] * fleet
    for _ in range(data.draw(st.integers(1, 4))):
        uavs = np.array(data.draw(st.lists(st.integers(0, fleet - 1), min_size=1,
                                           max_size=fleet, unique=True)))
        xy = np.array(data.draw(st.lists(coordinates, min_size=len(uavs) * samples * 2,
                                         max_size=len(uavs) * samples * 2))
                      ).reshape(len(uavs), samples, 2)
        levels = np.array(data.draw(st.lists(st.integers(0, 3), min_size=len(uavs) * samples,
                                             max_size=len(uavs) * samples))
                          ).reshape(len(uavs), samples)
        np.testing.assert_array_equal(spots.keep(uavs, xy, levels),
                                      keep_one_by_one(spacing, last, uavs, xy, levels))


def test_the_world_reports_along_the_path_with_seeded_noise(scenario):
    noisy = variant(scenario, uav={"measurement_noise_db": 1.0})
    reports = []
    for envs in (1, 3):
        world = VectorWorld(noisy, envs, 4, record_measurements=True)
        world.reset(np.arange(envs), [episode_seed(5, k) for k in range(envs)])
        start = world.position.copy()
        world.step(np.full((envs, 4), 5.0), world.heading)
        samples = noisy.uav.measurements_per_step
        # Evenly along the step, the last at the new position, exactly: the world reads its
        # truth there from the same evaluation as the reports (noise off: the same SINR).
        np.testing.assert_array_equal(world.measured_xy[:, :, -1], world.position)
        exact = VectorWorld(scenario, envs, 4, record_measurements=True)
        exact.reset(np.arange(envs), [episode_seed(5, k) for k in range(envs)])
        exact.step(np.full((envs, 4), 5.0), exact.heading)
        np.testing.assert_array_equal(
            exact.measured_level[:, :, -1],
            exact.radio.evaluate(exact.position, exact.jammer()).level)
        np.testing.assert_array_equal(exact.level, exact.measured_level[:, :, -1])
        np.testing.assert_allclose(world.measured_xy[:, :, 0],
                                   start + (world.position - start) / samples)
        reports.append(world.measured_level[0].copy())
    # Episode 0's noise comes from its own seed, however many environments fly.
    np.testing.assert_array_equal(reports[0], reports[1])
    radio = world.radio
    sinr_db = np.zeros(20_000) - 3.0 + 1e-9  # on the threshold: noise decides the level
    below = radio.measured_reports(sinr_db, np.random.default_rng(0)).level == 0
    assert abs(below.mean() - 0.5) < 0.02  # symmetric noise


# -- the detector -----------------------------------------------------------------------------
def test_detector_fires_on_one_uavs_run_of_contradictions_not_on_scattered_ones():
    detector = ChangeDetector(levels=3, threshold=12.0, floor=0.05)
    up, down = math.log((1 / 3) / 0.05), math.log((1 / 3) / 0.9)
    # Scattered: one report in twenty that the map ruled out (p = 0.01, counted as the floor)
    # among reports it expected (p = 0.9) never adds up, for any UAV.
    probability = np.tile([0.01] + [0.9] * 19, 40)
    sources = [f"uav-{i // 20 % 4}" for i in range(probability.size)]
    check = detector.update(probability, sources, np.arange(probability.size, dtype=float))
    assert not check.fired and detector.armed and check.statistic <= up
    # A run by one UAV fires once its sum reaches 12, i.e. on its seventh contradiction
    # (6 * 1.90 = 11.4), whatever the other UAVs report in between.
    detector.reset()
    probability = np.array([0.9, 0.01, 0.01, 0.9, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01])
    run_sources = ["uav-2", "uav-1", "uav-1", "uav-3", "uav-1", "uav-1", "uav-1", "uav-1",
                   "uav-1", "uav-1"]
    check = detector.update(probability, run_sources, np.arange(10.0, 20.0))
    assert check.fired and check.source == "uav-1" and not detector.armed
    assert check.t == 18.0 and check.statistic == pytest.approx(7 * up)
    assert detector.change_start == 11.0  # where uav-1's excursion began
    assert detector.update(probability, run_sources, np.arange(10.0)) is None  # disarmed
    # An expected report takes log(u / p) off; an unsure map (p = 1/3) neither adds nor takes.
    detector.reset()
    check = detector.update(np.array([0.01, 0.9, 1 / 3]), ["a", "a", "a"], np.zeros(3))
    assert check.statistic == pytest.approx(up + down)


def test_the_scenario_sets_the_detector(scenario):
    assert ChangeDetector.of(scenario) == ChangeDetector(3, 12.0, 0.002)
    shadowed = ChangeDetector.of(load_scenario("icc2021-shadowed"))
    assert (shadowed.threshold, shadowed.floor) == (24.0, 0.05)


# -- the estimate on the wire -----------------------------------------------------------------
def _estimate(**change) -> JammerEstimate:
    fields = dict(map_version=3, t=12.5, present=True, x=24.0, y=-9.5, power_w=0.9,
                  effective_power_dbm=9.5, sd_x_m=1.5, sd_y_m=2.0, sd_power_db=0.8,
                  measurements=420, change_time=10.0)
    return JammerEstimate(**{**fields, **change})


def test_estimate_round_trips_and_decodes_for_zenoh_cli():
    estimate = _estimate()
    assert decode(JammerEstimate, encode(estimate)) == estimate
    event = JammerEstimated(t=1.0, source="cloud", estimate=estimate)
    assert decode_event(encode(event)) == event
    assert '"x": 24.0' in zenoh_cli_decoder("k", encode(estimate))
    assert describe_estimate(estimate) == (
        "(24.0 +- 1.5, -9.5 +- 2.0) m, 0.90 W +- 0.8 dB (420 measurements)")
    absent = JammerEstimate(map_version=4, t=1.0, present=False, measurements=80)
    assert decode(JammerEstimate, encode(absent)) == absent
    assert Topics("p").jammer_estimate == "p/cloud/jammer_estimate"


@pytest.mark.parametrize("damage", [
    {"x": None}, {"power_w": -1.0}, {"sd_x_m": -0.1}, {"x": float("nan")},
    {"present": False}, {"measurements": -3},
])
def test_a_malformed_estimate_is_refused(damage):
    data = _estimate().model_dump()
    data.update(damage)
    with pytest.raises(MessageError):
        decode(JammerEstimate, msgpack.packb(data))


# -- the resilience evaluation ----------------------------------------------------------------
def test_swapped_jammers_are_seeded_and_inside_the_area(scenario):
    first = jammer_set(scenario, JammerSetting(0.0, 0.0, 1.0))
    assert [(j.x, j.y, j.power_w, j.height_m) for j in first] == [(0.0, 0.0, 1.0, 30.0)]
    schedule = swapping_jammers(scenario, first, 10, seed=4)
    again = swapping_jammers(scenario, first, 10, seed=4)
    settings = [schedule(k) for k in range(0, 100, 10)]
    assert settings[0] == first and schedule(9) == first and schedule(10) != first
    assert settings == [again(k) for k in range(0, 100, 10)]
    assert len(set(settings)) == 10
    low, high = scenario.training.jammer_power_range_w
    for (setting,) in settings[1:]:  # one still jammer each
        assert scenario.area.contains(setting.x, setting.y) and setting.still
        assert low <= setting.power_w <= high
    assert swapping_jammers(scenario, first, None, 4)(500) == first


def test_transient_runs_from_each_change_to_the_first_newer_map():
    a, b = JammerSetting(0, 0, 1), JammerSetting(9, 9, 1)

    def schedule(episode):
        return a if episode < 5 else b

    # Map versions at each episode's start: v1 arrives during episode 1, v2 during 6.
    versions = np.array([0, 0, 1, 1, 1, 1, 1, 2, 2, 2])
    np.testing.assert_array_equal(transient_episodes(schedule, versions),
                                  [1, 1, 0, 0, 0, 1, 1, 0, 0, 0])
    # No jammer at the start: the no-jammer map is right, nothing is transient.
    np.testing.assert_array_equal(transient_episodes(lambda k: None, np.zeros(4, int)),
                                  [0, 0, 0, 0])


def test_the_report_shows_a_run_of_refinements_as_its_first_and_last_map():
    from jamnav.run_report import map_history

    def estimated(version: int, x: float) -> dict:
        return {"type": "jammer_estimated", "estimate": _estimate(map_version=version, x=x)
                .model_dump()}

    published = [{"type": "sinr_weights_published", "version": v, "accuracy": 0.9}
                 for v in range(1, 5)]
    events = [{"type": "jammer_changed",
               "jammers": [{"x": -25.0, "y": 15.0, "power_w": 1.0, "height_m": 30.0}],
               "episode": 3, "step": 40},
              {"type": "change_detected", "version": 0, "accuracy": 0.8123456789}]
    for version, x in ((1, 20.0), (2, 22.0), (3, 23.5), (4, 24.0)):
        events += [estimated(version, x), published[version - 1]]
    lines = map_history(events)
    assert lines[:2] == ["jammer moved to (-25, 15), 1 W (episode 3, step 40)",
                         "change detected: map v0 right on 81% of recent uploads"]
    assert len(lines) == 5
    assert lines[2].startswith("map v1, jammer at") and "(20.0 +- 1.5" in lines[2]
    assert "2 refinements" in lines[3] and lines[4].startswith("map v4") and "(24.0" in lines[4]
    # A map published without an estimate (the DNN alone) is listed as such.
    assert map_history([{"type": "sinr_weights_published", "version": 7, "accuracy": None}]
                       ) == ["SINR map v7 published"]
    # Provisional maps while the estimate converges: a run of their own, before the first map
    # an estimate stands behind.
    provisional = [{"type": "sinr_weights_published", "version": v, "accuracy": None,
                    "provisional": True} for v in (1, 2, 3, 4)]
    lines = map_history([*provisional, estimated(5, 20.0),
                         {"type": "sinr_weights_published", "version": 5, "accuracy": 0.9}])
    assert lines == ["provisional SINR map v1 published", "  ... 2 provisional maps ...",
                     "provisional SINR map v4 published", lines[3]]
    assert lines[3].startswith("map v5, jammer at")
    # One between the first and the last: singular.
    assert map_history(provisional[1:])[1] == "  ... 1 provisional map ..."
    # A provisional map says how many jammers the cloud counted before placing them.
    counted = {**provisional[0], "jammers_counted": 1, "accuracy": 0.9}
    assert map_history([counted]) == [
        "provisional SINR map v1 published, 1 jammer counted, not placed yet "
        "(held-out accuracy 90.0%)"]


def test_the_mapper_summary_says_when_the_map_in_service_is_provisional():
    from shared.process_status import ProcessStatus, mapper_summary

    def cloud(**details) -> ProcessStatus:
        return ProcessStatus(role="cloud", ident="0", pid=1, t=0.0, sinr_version=5,
                             details={"recent_accuracy": 0.93, **details})

    assert mapper_summary(cloud(map_phase="estimating", since_change=120,
                                map_provisional=True, jammers_counted=2)) == (
        "map v5 (provisional) 93% on recent, estimating (120 since change, 2 jammers counted)")
    assert mapper_summary(cloud(map_phase="estimating", since_change=40,
                                map_provisional=False, jammers_counted=None)) == (
        "map v5 93% on recent, estimating (40 since change, no count yet)")
    assert mapper_summary(cloud(map_phase="watching", since_change=None,
                                map_provisional=False)) == "map v5 93% on recent"
