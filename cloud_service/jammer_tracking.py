"""Following a jammer that moves: each window of recent uploads gives an estimate of where it
is (``estimate_jammer``), and a constant-velocity Kalman filter joins them into a track, its
position and velocity with their uncertainty (``JammerTrack``); ``track_jammer`` runs one over
time-stamped uploads, and ``WindowedTracker`` one over the uploads of a change as they come
in, for the online mapper."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from cloud_service.estimated_jammer import JammerEstimate
from cloud_service.jammer_estimation import estimate_jammer
from shared.scenario import Scenario

# How fast a vehicle may change its velocity, the filter's process noise (m/s^2, standard
# deviation of a white-noise acceleration): a convoy keeping its pace. Larger, the track
# follows each window's error; a vehicle that turns is followed a few windows late.
ACCELERATION_SD_MPS2 = 0.2
# A window's estimate is never trusted to better than this (m): the search's fine grid.
MIN_POSITION_SD_M = 0.5
# A window's estimate this far from where the track predicts the jammer, as a squared
# Mahalanobis distance over the two of them (chi-square, 2 degrees of freedom: 1 in 1,000 of a
# tracked jammer's windows lie farther), is another jammer or the same one moved at a jump (a
# convoy's drive restarted): the track starts again from it instead of averaging the two.
RESTART_DISTANCE_SQ = 13.8
WINDOW_S = 5.0  # the uploads each estimate reads: a jammer at 5 m/s moves 25 m in it
# Windows far behind the newest upload say where the jammer was, not where it is: the cloud's
# tracker, fallen behind (restarted, or busy with its estimates and fits), takes up at most
# this many of the latest and skips the older.
MOST_WINDOWS_BEHIND = 4


class TrackedJammer(NamedTuple):
    t: float
    x: float
    y: float
    vx: float
    vy: float
    sd_x_m: float
    sd_y_m: float
    sd_vx_mps: float
    sd_vy_mps: float
    power_w: float  # the latest window's


class JammerTrack:
    """A constant-velocity Kalman filter on (x, y, vx, vy): a window's estimate is a measurement
    of the position at the window's middle (where the jammer was, on average, while the
    window's uploads were taken), with the estimate's own posterior covariance; between two,
    the velocity may drift by ``acceleration_sd`` (white-noise acceleration)."""

    def __init__(self, acceleration_sd: float = ACCELERATION_SD_MPS2):
        self.acceleration_sd = acceleration_sd
        self.t: float | None = None
        self.state = np.zeros(4)
        self.covariance = np.zeros((4, 4))
        self.power_w = 0.0
        self.updates = 0  # estimates taken since the track (re)started

    def update(self, t: float, estimate: JammerEstimate) -> TrackedJammer:
        """Take a present ``estimate`` of the jammer's position at time ``t``; one too far
        from the prediction (``RESTART_DISTANCE_SQ``) starts the track again."""
        measured = np.array([estimate.x, estimate.y])
        cov_xy = estimate.cov_xy_m2 or 0.0
        noise = np.array([[max(estimate.sd_x_m, MIN_POSITION_SD_M) ** 2, cov_xy],
                          [cov_xy, max(estimate.sd_y_m, MIN_POSITION_SD_M) ** 2]])
        if self.t is not None:
            self._predict(t - self.t)
            innovation = measured - self.state[:2]
            spread = self.covariance[:2, :2] + noise
            if innovation @ np.linalg.solve(spread, innovation) > RESTART_DISTANCE_SQ:
                self.t = None
        if self.t is None:  # the first: where it is; its velocity, any a vehicle may have
            self.state = np.concatenate([measured, [0.0, 0.0]])
            self.covariance = np.zeros((4, 4))
            self.covariance[:2, :2] = noise
            self.covariance[2:, 2:] = np.eye(2) * _UNKNOWN_SPEED_MPS**2
            self.updates = 0
        else:
            gain = self.covariance[:, :2] @ np.linalg.inv(spread)
            self.state = self.state + gain @ innovation
            self.covariance = self.covariance - gain @ self.covariance[:2, :]
        self.t, self.power_w = t, float(estimate.power_w)
        self.updates += 1
        return self.now()

    def _predict(self, dt: float) -> None:
        move = np.eye(4)
        move[0, 2] = move[1, 3] = dt
        # White-noise acceleration over dt, on each axis: [[dt^3/3, dt^2/2], [dt^2/2, dt]] q.
        per_axis = self.acceleration_sd**2 * np.array([[dt**3 / 3.0, dt**2 / 2.0],
                                                       [dt**2 / 2.0, dt]])
        drift = np.zeros((4, 4))
        drift[np.ix_([0, 2], [0, 2])] = per_axis
        drift[np.ix_([1, 3], [1, 3])] = per_axis
        self.state = move @ self.state
        self.covariance = move @ self.covariance @ move.T + drift

    def now(self) -> TrackedJammer:
        sd = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return TrackedJammer(self.t, *map(float, self.state), *map(float, sd), self.power_w)

    def at(self, t: float) -> tuple[float, float]:
        """Where the track puts the jammer at a later time ``t``."""
        ahead = t - self.t
        return (float(self.state[0] + ahead * self.state[2]),
                float(self.state[1] + ahead * self.state[3]))


_UNKNOWN_SPEED_MPS = 10.0  # the first estimate's velocity: anything a vehicle on a road does


def track_jammer(scenario: Scenario, xy: np.ndarray, levels: np.ndarray, times: np.ndarray,
                 no_jammer_levels: np.ndarray, *, window_s: float = WINDOW_S,
                 reported_db: np.ndarray | None = None) -> list[TrackedJammer]:
    """The track of one moving jammer through uploads at ``xy`` with ``levels`` (and SINRs
    ``reported_db``) taken at ``times``: the uploads of each ``window_s`` seconds in turn are
    estimated (``estimate_jammer``), and each estimate that converges updates the track at
    the window's middle; one entry per update. The windows do not overlap: the filter takes
    each estimate's error as its own, which overlapping windows would share."""
    def estimate_window(start: float, end: float) -> JammerEstimate | None:
        rows = (times > start) & (times <= end)
        return estimate_jammer(
            scenario, xy[rows], levels[rows], no_jammer_levels=no_jammer_levels[rows],
            reported_db=None if reported_db is None else reported_db[rows])

    return WindowedTracker(float(times.min()), window_s).follow(float(times.max()) + 1e-9,
                                                                estimate_window)


class WindowedTracker:
    """Follows the jammer of a change the cloud handles: the uploads since the change began,
    cut into windows of ``window_s`` (``online_map.tracking_window_s``), each estimated on its
    own once it is complete and joined into a ``JammerTrack``. Which estimate a window gets
    is the caller's (the mapper's, with its no-jammer beliefs)."""

    def __init__(self, start: float, window_s: float):
        self.window_s = window_s
        self.next_start = start  # of the first window not estimated yet
        self.track = JammerTrack()

    def due(self, latest: float) -> bool:
        """Whether uploads up to ``latest`` complete a window not estimated yet."""
        return latest >= self.next_start + self.window_s

    def follow(self, latest: float,
               estimate_window: Callable[[float, float], JammerEstimate | None],
               most_behind: int | None = None) -> list[TrackedJammer]:
        """Estimate every window that uploads up to ``latest`` complete
        (``estimate_window(start, end)``), in order, or only the latest ``most_behind`` of
        them; the track after each that places the jammer."""
        skipped = math.floor((latest - self.next_start) / self.window_s) - (
            math.inf if most_behind is None else most_behind)
        if skipped > 0:
            self.next_start += skipped * self.window_s
        out = []
        while self.due(latest):
            start, end = self.next_start, self.next_start + self.window_s
            self.next_start = end
            estimate = estimate_window(start, end)
            if estimate is not None and estimate.present and not estimate.others:
                out.append(self.track.update((start + end) / 2.0, estimate))
        return out

    def velocity(self) -> dict[str, float] | None:
        """The velocity and its sds as an estimate carries them, once two windows placed
        the jammer since the track (re)started (one alone says nothing of its motion)."""
        if self.track.updates < 2:
            return None
        now = self.track.now()
        return {"vx_mps": now.vx, "vy_mps": now.vy, "sd_vx_mps": now.sd_vx_mps,
                "sd_vy_mps": now.sd_vy_mps}
