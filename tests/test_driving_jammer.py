"""A jammer driving at a steady velocity, fitted to every upload at once
(``cloud_service.driving_jammer``): the velocity grid, the frame the path loss reads, and
the fit of a jammer that drives and of one that stands still."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cloud_service.driving_jammer import (
    HEADINGS,
    driving_frames,
    estimate_driving_jammer,
    velocity_hypotheses,
)
from cloud_service.jammer_estimation import estimate_jammer, fit_frames
from cloud_service.jammer_evidence import JammerEvidence, Reports, independence_weights
from cloud_service.no_jammer_belief import sinr_beliefs
from shared.radio import JammerParams, RadioModel
from shared.scenario import load_scenario
from tests.conftest import variant


def test_the_velocities_stand_still_first_then_every_speed_each_way(scenario):
    # The grid is float64: speeds of at most 5 m/s times cos and sin carry about 1e-15 of
    # rounding, so reading speeds to 1e-9 and "due east" as |vy| < 1e-12 is far above it and
    # far below the grid's 1 m/s and 22.5 degrees.
    velocities = velocity_hypotheses(scenario)
    low, high = scenario.training.moving_jammer_speed_range_mps  # 1 and 5 m/s
    speeds = np.hypot(*velocities.T)
    assert not velocities[0].any() and len(velocities) == 1 + 5 * HEADINGS
    assert sorted(set(np.round(speeds[1:], 9))) == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert (low, high) == (1.0, 5.0)
    east = velocities[(np.abs(velocities[:, 1]) < 1e-12) & (velocities[:, 0] > 0)]
    assert sorted(east[:, 0]) == [1.0, 2.0, 3.0, 4.0, 5.0]
    headings = np.round(np.degrees(np.arctan2(velocities[1:, 1], velocities[1:, 0])) % 360, 6)
    assert sorted(set(headings)) == [k * 360 / HEADINGS for k in range(HEADINGS)]


def test_the_path_loss_reads_the_frame_and_the_ground_stations_the_places(scenario):
    """Uploads read in a frame moved by d from where they were taken: a jammer at p weighs on
    them as one at p + d on the uploads where they were, while the ground stations'
    interference and the reports' tables stay those of the places."""
    # Bound: the two ways round differ by float64's rounding of coordinates under 200 m
    # (a few 1e-14 m), which moves r by well under 1e-11 dB.
    radio = RadioModel(scenario, shadowed=False)
    rng = np.random.default_rng(3)
    xy = rng.uniform(-50, 50, size=(200, 2))
    levels = radio.evaluate(xy).level
    shift = np.array([12.5, -4.0])
    placed = JammerEvidence(radio, scenario.jammer.height_m, Reports.of(scenario, xy, levels),
                            independence_weights(xy, 5.0), sinr_beliefs(radio, xy, levels, None,
                                                                        None), 1.0, 0.01, 20.0)
    moved = placed.in_frame(xy - shift)
    jammers = rng.uniform(-40, 40, size=(7, 2))
    np.testing.assert_allclose(moved.ratios_db(jammers, -10.0),
                               placed.ratios_db(jammers + shift, -10.0), rtol=0, atol=1e-9)
    assert moved.interference_db is placed.interference_db and moved.table is placed.table
    assert placed.xy.tolist() == xy.tolist()  # the frame is the moved copy's alone


@pytest.fixture
def three_metres_a_second(scenario):
    """icc2021 whose driving jammers all go at 3 m/s: a grid of 16 headings and standing
    still, which keeps the fits below to a few seconds."""
    return variant(scenario, training={"moving_jammer_speed_range_mps": (3.0, 3.0)})


def reports_of(scenario, jammer_x, rng, seconds=20, per_second=20):
    """Reports anywhere in the area, ``per_second`` a second, as the scenario's world gives
    them (icc2021's exactly; icc2021-shadowed's through its shadowing) under a 1 W jammer at
    (``jammer_x(t)``, -10): their places, times, levels and no-jammer levels."""
    truth = RadioModel(scenario)
    times = np.repeat(np.arange(seconds), per_second) + rng.uniform(0, 1, seconds * per_second)
    xy = rng.uniform(-50, 50, size=(len(times), 2))
    jammers = JammerParams(jammer_x(times), np.full(len(times), -10.0), 1.0,
                           scenario.jammer.height_m)
    return xy, times, truth.evaluate(xy, jammers).level, truth.evaluate(xy).level


def test_a_jammer_driving_a_line_is_placed_where_it_is_and_its_velocity_found(
        three_metres_a_second):
    """A 1 W jammer driving east at 3 m/s from (-30, -10) for 20 s: placed at the last
    second within 3 m of where it is, at the grid's (3, 0) m/s; the still fit of the same
    uploads lies off its path's end by more than twice that, or places nothing."""
    # The bounds are the fit's (20 s of 20 exact reports a second; measured 1.1 m, the still
    # fit 36.8 m; the velocity's sd 0.34 m/s), not arithmetic. The velocity is the grid's
    # node at heading 0, 3 cos 0 and 3 sin 0: exactly (3, 0) in float64.
    scenario = three_metres_a_second
    xy, times, levels, no_jammer = reports_of(scenario, lambda t: -30.0 + 3.0 * t,
                                              np.random.default_rng(5))
    now = float(times.max())
    found = estimate_driving_jammer(scenario, xy, times, levels, now,
                                    no_jammer_levels=no_jammer)
    assert found is not None and found.present
    assert math.hypot(found.x - (-30.0 + 3.0 * now), found.y + 10.0) <= 3.0
    assert (found.vx_mps, found.vy_mps) == (3.0, 0.0)
    assert 0.0 < found.sd_vx_mps < 1.0 and 0.0 < found.sd_vy_mps < 1.0
    still = estimate_jammer(scenario, xy, levels, no_jammer_levels=no_jammer)
    assert still is None or math.hypot(still.x - (-30.0 + 3.0 * now), still.y + 10.0) > 6.0


def test_a_still_jammer_is_fitted_still():
    """icc2021's shadowed world, a jammer standing at (10, -10), 800 reports over 20 s: one
    velocity's frame explains them a little better than standing still, by less than BIC's
    penalty for two parameters more (ln 800, 6.7), so the estimate is the still fit's, with
    no velocity."""
    # The position's bound is the shadowed world's still fit (measured 7.6 m), not
    # arithmetic; the rest is exact.
    shadowed = variant(load_scenario("icc2021-shadowed"),
                       training={"moving_jammer_speed_range_mps": (3.0, 3.0)})
    xy, times, levels, no_jammer = reports_of(shadowed, lambda t: np.full_like(t, 10.0),
                                              np.random.default_rng(15), per_second=40)
    now = float(times.max())
    velocities = velocity_hypotheses(shadowed)
    every = fit_frames(shadowed, xy, levels, driving_frames(xy, times, now, velocities),
                       fitted=len(velocities), no_jammer_levels=no_jammer)
    still = next(fit for fit in every if fit.frame == 0)
    best = max(fit.log_likelihood for fit in every if fit.frame != 0)
    assert 0.0 < best - still.log_likelihood < math.log(len(xy))
    found = estimate_driving_jammer(shadowed, xy, times, levels, now,
                                    no_jammer_levels=no_jammer)
    assert found == still.estimate == estimate_jammer(shadowed, xy, levels,
                                                      no_jammer_levels=no_jammer)
    assert found.present and found.vx_mps is None
    assert math.hypot(found.x - 10.0, found.y + 10.0) <= 10.0



def test_a_velocity_must_beat_standing_still_where_no_still_estimate_converges(scenario,
                                                                                 monkeypatch):
    """Standing still's log-likelihood (its best coarse hypothesis) counts whether or not its
    estimate converged: a converged velocity 0.1 nats short of BIC's penalty (ln 800) over
    it gives no jammer, 0.1 nats beyond it gives that velocity's estimate."""
    import cloud_service.driving_jammer as driving_jammer
    from cloud_service.estimated_jammer import JammerEstimate
    from cloud_service.jammer_estimation import FrameFit

    east = int(np.flatnonzero((velocity_hypotheses(scenario) == (3.0, 0.0)).all(axis=1))[0])
    placed = JammerEstimate(True, 1.0, 2.0, 1.0, 10.0, 1.0, 1.0, 1.0, 800, 20.0)
    xy, times = np.zeros((3, 2)), np.arange(3.0)

    def fitted(gain):
        return [FrameFit(0, None, -100.0), FrameFit(east, placed, -100.0 + gain)]

    for gain, expected in ((math.log(800) - 0.1, None), (math.log(800) + 0.1, (3.0, 0.0))):
        monkeypatch.setattr(driving_jammer, "fit_frames", lambda *a, gain=gain, **k: fitted(gain))
        found = estimate_driving_jammer(scenario, xy, times, np.zeros(3), 2.0)
        assert (None if found is None else (found.vx_mps, found.vy_mps)) == expected
