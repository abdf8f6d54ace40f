"""A jammer that drives at a steady velocity, fitted to every upload since a change at once.

Fitted as if it stood still, such a jammer comes out where its path's middle lies, or not at
all: its hole has moved on under the later uploads. The windows of ``jammer_tracking`` each
read a few seconds of uploads alone, which a fleet of four does not place it from
(BENCHMARKS.md, "Following a moving jammer"). Here every upload counts, read in the frame
that moves with each velocity of a grid (``velocity_hypotheses``): an upload at time t
stands, from a jammer that drives at v and is at p at time T, where it would stand from a
still one at p had it been taken at its place less v (t - T) (``Reports.frame_xy``). Each
velocity's estimate is ``estimate_jammer``'s with those positions; the one that explains the
uploads best is kept when it beats the still jammer's by BIC's penalty for its two
parameters more, or when no still jammer converges.
"""

from __future__ import annotations

import math

import numpy as np

from cloud_service.estimated_jammer import JammerEstimate
from cloud_service.jammer_estimation import estimate_jammer
from shared.scenario import Scenario

HEADINGS = 16  # of the velocity grid, evenly round the circle
SPEED_STEP_MPS = 1.0  # of the velocity grid, over the scenario's driving speeds


def velocity_hypotheses(scenario: Scenario) -> np.ndarray:
    """(V, 2) m/s: standing still first, then every ``SPEED_STEP_MPS`` over the training's
    driving speeds in each of ``HEADINGS`` directions."""
    low, high = scenario.training.moving_jammer_speed_range_mps
    speeds = np.arange(low, high + SPEED_STEP_MPS / 2, SPEED_STEP_MPS)
    angles = 2.0 * math.pi * np.arange(HEADINGS) / HEADINGS
    driving = (speeds[:, None, None]
               * np.stack([np.cos(angles), np.sin(angles)], axis=-1)[None]).reshape(-1, 2)
    return np.concatenate([np.zeros((1, 2)), driving])


def estimate_driving_jammer(scenario: Scenario, xy: np.ndarray, times: np.ndarray,
                            levels: np.ndarray, at_s: float, *,
                            reported_db: np.ndarray | None = None,
                            no_jammer_levels: np.ndarray | None = None) -> JammerEstimate | None:
    """The jammer of uploads at ``xy`` (n, 2) taken at ``times`` (n,) s with ``levels``
    (and SINRs ``reported_db``), placed where it is at ``at_s``, with its velocity and their
    standard deviations when it drives; None when no velocity's estimate converges
    (``estimate_jammer``, which also reads ``no_jammer_levels``).

    The velocity's sd is the spread of the converged velocities weighed by their likelihood,
    with the grid's own: a uniform over a cell of the grid adds its side squared over 12."""
    times = np.asarray(times, dtype=np.float64)
    fits = []
    for velocity in velocity_hypotheses(scenario):
        estimate = estimate_jammer(
            scenario, xy, levels, reported_db=reported_db, no_jammer_levels=no_jammer_levels,
            jammer_frame_xy=xy - (times - at_s)[:, None] * velocity)
        if estimate is not None and estimate.present:
            fits.append((estimate, velocity))
    if not fits:
        return None
    best, velocity = max(fits, key=lambda fit: fit[0].log_likelihood_ratio)
    still = next((estimate for estimate, v in fits if not v.any()), None)
    penalty = math.log(best.measurements)  # BIC: half a log of n for each of vx and vy
    if still is not None and best.log_likelihood_ratio - still.log_likelihood_ratio < penalty:
        return still
    if not velocity.any():
        return best
    llr = np.array([estimate.log_likelihood_ratio for estimate, _ in fits])
    weight = np.exp(llr - llr.max())
    weight /= weight.sum()
    velocities = np.array([v for _, v in fits])
    spread = weight @ (velocities - weight @ velocities) ** 2
    cell_m_s = max(SPEED_STEP_MPS, float(np.hypot(*velocity)) * 2.0 * math.pi / HEADINGS)
    sd = np.sqrt(spread + cell_m_s**2 / 12.0)
    return best._replace(vx_mps=float(velocity[0]), vy_mps=float(velocity[1]),
                         sd_vx_mps=float(sd[0]), sd_vy_mps=float(sd[1]))
