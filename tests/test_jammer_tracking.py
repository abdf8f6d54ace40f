"""A moving jammer followed by a track of window estimates (``cloud_service.jammer_tracking``):
the filter against hand-worked numbers, and the track of a jammer driving a straight line."""

from __future__ import annotations

import numpy as np
import pytest

from cloud_service.estimated_jammer import JammerEstimate
from cloud_service.jammer_tracking import (
    MOST_WINDOWS_BEHIND,
    JammerTrack,
    WindowedTracker,
    track_jammer,
)
from shared.radio import JammerParams, RadioModel


def seen(x: float, y: float, sd: float = 1.0) -> JammerEstimate:
    return JammerEstimate(True, x, y, 1.0, 0.0, sd, sd, 0.5, 100, 20.0, 0.0)


def test_exact_positions_on_a_line_give_its_velocity():
    """Nearly exact positions (0.5 m, the floor) a second apart along x at 3 m/s: the filter
    ends within a few centimetres a second of 3 m/s, and predicts ahead on the line."""
    # The bounds are the filter's (its noise floor, its lag), not arithmetic: float64 leaves
    # ~1e-15 of them.
    track = JammerTrack(acceleration_sd=0.01)
    for t in range(12):
        now = track.update(float(t), seen(-20.0 + 3.0 * t, 5.0, sd=0.0))
    assert now.vx == pytest.approx(3.0, abs=0.05) and now.vy == pytest.approx(0.0, abs=0.05)
    assert now.x == pytest.approx(13.0, abs=0.3) and now.sd_vx_mps < 0.2
    assert track.at(14.0) == pytest.approx((22.0, 5.0), abs=0.5)  # 3 s on at 3 m/s


def test_the_first_estimate_is_the_position_and_the_velocity_unknown():
    first = JammerTrack().update(2.0, seen(4.0, -3.0, sd=2.0))
    assert (first.x, first.y, first.vx, first.vy) == (4.0, -3.0, 0.0, 0.0)
    assert (first.sd_x_m, first.sd_vx_mps) == (2.0, 10.0)


def test_a_jammer_that_jumps_starts_its_track_again():
    """A convoy's drive restarted: 3 m/s east for six windows, then seen back at the west edge.
    That estimate lies far outside the prediction (about 55 m off, its spread a few metres),
    so the track starts from it, its velocity unknown again, and the tracker publishes none
    until the next window places the jammer. (The straight-line tests above are the windows
    taken in: a restart among them would lose the velocity they converge to.)"""
    # The velocity's bound is the filter's (its lag after five windows), not arithmetic; the
    # restarted track's values are copied, exact.
    tracker = WindowedTracker(0.0, 5.0)
    places = [(-40.0 + 15.0 * k, 5.0) for k in range(6)] + [(-47.5, 5.0)]
    for k, (x, y) in enumerate(places):
        tracker.follow(5.0 * (k + 1), lambda start, end, x=x, y=y: seen(x, y))
        if k == 4:
            assert tracker.velocity()["vx_mps"] == pytest.approx(3.0, abs=0.5)
    restarted = tracker.track.now()
    assert (restarted.x, restarted.y, restarted.vx, restarted.vy) == (-47.5, 5.0, 0.0, 0.0)
    assert restarted.sd_vx_mps == 10.0 and tracker.velocity() is None
    tracker.follow(40.0, lambda start, end: seen(-32.5, 5.0))
    assert tracker.track.updates == 2 and tracker.velocity()["vx_mps"] > 0.0


def test_a_jammer_driving_a_straight_line_is_tracked(scenario):
    """icc2021's exact receivers; a jammer drives from (-30, -10) east at 2 m/s for 40 s while
    300 reports a second fall anywhere in the area (their no-jammer levels known), read in
    windows of 5 s. Measured: each window's estimate within 2 m of where the jammer was
    halfway through it; the track's last position 0.1 m off, its velocity 0.16 m/s off (its
    sd 0.33 m/s)."""
    truth = RadioModel(scenario)
    rng = np.random.default_rng(4)
    seconds = np.arange(40)
    times = np.repeat(seconds, 300) + rng.uniform(0.0, 1.0, 300 * len(seconds))
    xy = rng.uniform(-50, 50, size=(len(times), 2))
    jammer_x = -30.0 + 2.0 * times
    jammers = JammerParams(jammer_x, np.full(len(times), -10.0), 1.0, scenario.jammer.height_m)
    levels = truth.evaluate(xy, jammers).level
    track = track_jammer(scenario, xy, levels, times, truth.evaluate(xy).level)
    assert len(track) >= 6
    last = track[-1]
    assert np.hypot(last.x - (-30.0 + 2.0 * last.t), last.y + 10.0) <= 3.0
    assert np.hypot(last.vx - 2.0, last.vy) <= 0.5


def test_a_tracker_that_fell_behind_takes_up_only_the_latest_windows():
    """Uploads 60 s past the tracker's next window (a restarted cloud, a busy one): the
    cloud's tracker estimates the last ``MOST_WINDOWS_BEHIND`` complete windows, in order, not
    all twelve; without the limit (``track_jammer``'s) it takes up all of them."""
    asked = []
    tracker = WindowedTracker(0.0, 5.0)
    tracker.follow(61.0, lambda start, end: asked.append((start, end)), MOST_WINDOWS_BEHIND)
    assert asked == [(40.0, 45.0), (45.0, 50.0), (50.0, 55.0), (55.0, 60.0)]
    assert MOST_WINDOWS_BEHIND == len(asked)
    tracker.follow(64.9, lambda start, end: asked.append((start, end)), MOST_WINDOWS_BEHIND)
    assert len(asked) == 4 and tracker.due(65.0)  # the next window ends at 65 s
    every = []
    WindowedTracker(0.0, 5.0).follow(61.0, lambda start, end: every.append((start, end)))
    assert len(every) == 12 and every[0] == (0.0, 5.0)
