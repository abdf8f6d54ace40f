"""Several jammers, moving jammers, switched jammers: Eq. (3) sums their interference, and the
world places each where its path and schedule say, at the right steps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cloud_service.rollout import RasterMaps
from shared.jammer_motion import params_at, position_at, transmits_at
from shared.radio import JammerParams, RadioModel
from shared.scenario import Jammer, ScenarioError, load_scenario
from tests.test_radio import reference_sinr_db
from world_sim.core import VectorWorld

coordinate = st.floats(-50, 50, allow_nan=False)
a_jammer = st.tuples(coordinate, coordinate, st.floats(0.0, 5.0), st.floats(0.0, 40.0))


def a_scenario_jammer(scenario, **fields) -> Jammer:
    return scenario.jammer.model_validate({**scenario.jammer.model_dump(), **fields})


@settings(max_examples=40, deadline=None)
@given(x=coordinate, y=coordinate, jammers=st.lists(a_jammer, min_size=2, max_size=4))
def test_several_jammers_add_up_in_eq_3(scenario, x, y, jammers):
    want_db, want_k = reference_sinr_db(scenario, x, y, jammers[0], jammers[1:])
    reading = RadioModel(scenario).evaluate(np.array([x, y]),
                                            [JammerParams(*jammer) for jammer in jammers])
    # Both sides in float64 (a few terms, each a few ulps of 1e-16 relative off): 1e-9 dB is
    # the bound, a million times what the arithmetic leaves.
    assert float(reading.sinr_db) == pytest.approx(want_db, abs=1e-9)
    assert int(reading.serving_gbs) == want_k


def test_a_jammer_of_no_power_and_no_jammer_read_the_same(scenario):
    radio = RadioModel(scenario)
    points = np.random.default_rng(3).uniform(-50, 50, size=(200, 2))
    one = JammerParams(25.0, -10.0, 1.0, 30.0)
    silent = JammerParams(-10.0, 5.0, 0.0, 30.0)
    np.testing.assert_array_equal(radio.evaluate(points, [one, silent]).sinr_db,
                                  radio.evaluate(points, one).sinr_db)
    np.testing.assert_array_equal(radio.evaluate(points, []).sinr_db,
                                  radio.evaluate(points, None).sinr_db)


def test_a_path_is_driven_leg_by_leg_by_hand(scenario):
    # Legs (0,0)->(10,0)->(10,10): 10 m each, at 2 m/s; a loop adds the 14.14 m leg home
    # (12 s in: 4 m down it).
    path = {"waypoints": [[10.0, 0.0], [10.0, 10.0]], "speed_mps": 2.0}
    one_way = a_scenario_jammer(scenario, x=0.0, y=0.0, path=path)
    looped = a_scenario_jammer(scenario, x=0.0, y=0.0, path={**path, "loop": True})
    assert position_at(one_way, 0.0) == (0.0, 0.0)
    assert position_at(one_way, 3.0) == pytest.approx((6.0, 0.0))
    assert position_at(one_way, 7.0) == pytest.approx((10.0, 4.0))
    assert position_at(one_way, 60.0) == pytest.approx((10.0, 10.0))  # stopped at the end
    home = 20.0 + 10.0 * math.sqrt(2.0)
    assert position_at(looped, 12.0) == pytest.approx((10.0 - 4.0 / math.sqrt(2.0),
                                                       10.0 - 4.0 / math.sqrt(2.0)))
    assert position_at(looped, (home + 4.0) / 2.0) == pytest.approx((4.0, 0.0))


def test_a_duty_cycle_and_a_reactive_jammer_switch_by_hand(scenario):
    duty = a_scenario_jammer(scenario, schedule={"kind": "duty", "on_s": 2.0, "off_s": 3.0,
                                                 "offset_s": 1.0})
    nobody = np.empty((0, 2))
    # On while (t + 1) mod 5 < 2: t in [0, 1) and [4, 6), [9, 11) ...
    assert [transmits_at(duty, t, nobody) for t in range(12)] == [
        True, False, False, False, True, True, False, False, False, True, True, False]
    reactive = a_scenario_jammer(scenario, x=0.0, y=0.0,
                                 schedule={"kind": "reactive", "radius_m": 10.0})
    assert not transmits_at(reactive, 0.0, nobody)
    assert not transmits_at(reactive, 0.0, np.array([[8.0, 6.01], [30.0, 0.0]]))
    assert transmits_at(reactive, 0.0, np.array([[30.0, 0.0], [8.0, 6.0]]))
    off = a_scenario_jammer(scenario, enabled=False)
    assert params_at([off, duty], 0.0, nobody) == (JammerParams(duty.x, duty.y, duty.power_w,
                                                                duty.height_m),)


def test_the_world_moves_and_switches_its_jammers_at_the_right_steps(scenario):
    convoy = a_scenario_jammer(scenario, x=-40.0, y=0.0, path={"waypoints": [[40.0, 0.0]],
                                                                 "speed_mps": 3.0})
    blinking = a_scenario_jammer(scenario, x=20.0, y=20.0, power_w=0.5,
                                 schedule={"kind": "duty", "on_s": 2.0, "off_s": 2.0})
    world = VectorWorld(scenario, 2, 3)
    world.set_jammers([1], (convoy, blinking))
    world.reset([0, 1], [5, 6])
    dt = scenario.timing.step_s
    hover = np.zeros((2, 3))
    for step in range(1, 9):
        world.step(hover, world.heading)
        t = step * dt
        # float64: the leg's share times its length, within ulps of 40 m (1e-14 m).
        assert world.jammer_x[1, 0] == pytest.approx(min(-40.0 + 3.0 * t, 40.0), abs=1e-9)
        assert world.jammer_power[1, 1] == (0.5 if math.fmod(t, 4.0) < 2.0 else 0.0)
        # The other environment keeps the scenario's still jammer.
        assert world.jammers_now(0) == ((scenario.jammer.x, scenario.jammer.y,
                                        scenario.jammer.power_w, scenario.jammer.height_m),)
    # What each UAV measures is the radio under the jammers where they are now.
    truth = RadioModel(scenario).evaluate(
        world.position[1], [JammerParams(*jammer) for jammer in world.jammers_now(1)])
    # The same float64 radio at the same points: equal but for summation order (1e-14 dB).
    np.testing.assert_allclose(world.sinr_db[1], truth.sinr_db, rtol=0, atol=1e-9)
    world.reset([1], [7])  # a new episode starts each drive afresh
    assert world.jammer_x[1, 0] == -40.0 and world.jammer_power[1, 1] == 0.5


def test_a_late_map_shows_a_driving_jammer_where_it_was_by_hand(scenario):
    convoy = a_scenario_jammer(scenario, x=-40.0, y=0.0, path={"waypoints": [[40.0, 0.0]],
                                                                 "speed_mps": 3.0})
    world = VectorWorld(scenario, 1, 2)
    world.set_jammers([0], (convoy,))
    world.reset([0], [5])
    late = RasterMaps(scenario, late_steps=2)
    hover = np.zeros((1, 2))
    for step in range(6):
        # 2 s late at 3 m/s: 6 m behind, and at the drive's start for the episode's first 2 s
        # (float64 along one leg: approx's default 1e-6 relative is far above its ulps).
        seen_x = -40.0 + 3.0 * max(0, step - 2)
        assert world.jammers_as_of(0, late_steps=2)[0][:2] == pytest.approx((seen_x, 0.0))
        assert world.jammers_as_of(0, late_steps=-1)[0][0] == pytest.approx(
            -40.0 + 3.0 * (step + 1))  # a step ahead
        assert world.jammers_now(0)[0][0] == pytest.approx(-40.0 + 3.0 * step)
        late(world, np.arange(2))
        world.step(hover, world.heading)
    # One raster per place shown: at the start for steps 0-2, then one a step.
    assert len(late.cache) == 4
    still = VectorWorld(scenario, 1, 2)
    still.reset([0], [5])
    still.step(hover, still.heading)
    assert still.jammers_as_of(0, late_steps=2) == still.jammers_now(0)


def test_a_scenario_file_lists_jammers_or_names_the_one(tmp_path):
    text = (load_scenario.__globals__["SCENARIO_DIR"] / "icc2021.toml").read_text()
    section = text[text.index("[jammer]"):text.index("[rewards]")]
    body = section.removeprefix("[jammer]")
    listed = text.replace(section, "[[jammers]]" + body + "[[jammers]]" + body.replace(
        "x = 0.0", "x = 20.0"))
    (tmp_path / "two.toml").write_text(listed)
    two = load_scenario(tmp_path / "two.toml")
    assert [jammer.x for jammer in two.jammers] == [0.0, 20.0]
    assert load_scenario("icc2021").jammers == (two.jammers[0],)
    five = text.replace(section, ("[[jammers]]" + body) * 5)
    (tmp_path / "five.toml").write_text(five)
    with pytest.raises(ScenarioError, match="jammers: .*at most 4") as caught:
        load_scenario(tmp_path / "five.toml")
    assert "\n" not in str(caught.value)
    both = text.replace("[rewards]", "[[jammers]]" + body + "[rewards]")
    (tmp_path / "both.toml").write_text(both)
    with pytest.raises(ScenarioError, match="not both"):
        load_scenario(tmp_path / "both.toml")
