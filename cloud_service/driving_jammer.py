"""A jammer that drives at a steady velocity, fitted to every upload since a change at once.

Fitted as if it stood still, such a jammer comes out where its path's middle lies, or not at
all: its hole has moved on under the later uploads. The windows of ``jammer_tracking`` each
read a few seconds of uploads alone, which a fleet of four does not place it from
(BENCHMARKS.md, "Following a moving jammer"). Here every upload counts, read in the frame
that moves with each velocity of a grid (``velocity_hypotheses``): an upload at time t
stands, from a jammer that drives at v and is at p at time T, where it would stand from a
still one at p had it been taken at its place less v (t - T) (``JammerEvidence.in_frame``).
The velocities the coarse search ranks best are estimated in full as ``estimate_jammer``
would (``fit_frames``); the one that explains the uploads best is kept when it beats the
still jammer by BIC's penalty for its two parameters more."""

from __future__ import annotations

import math

import numpy as np

from cloud_service.estimate_inputs import EstimateInputs
from cloud_service.estimated_jammer import JammerEstimate
from cloud_service.jammer_estimation import fit_frames
from shared.measurements import MeasurementBatch
from shared.scenario import Scenario

HEADINGS = 16  # of the velocity grid, evenly round the circle
SPEED_STEP_MPS = 1.0  # of the velocity grid, over the scenario's driving speeds
# Velocities estimated in full, the best of the grid by their coarse search alone. Over the
# convoy's crossing (bench_tracking's 36 moments, 4 UAVs), wherever the best of all 81 full
# estimates was the convoy's own velocity, it ranked among the coarse search's first six.
FULLY_FITTED = 6
# The cost of a fit grows with the reports it reads: a larger fleet's are thinned to about
# as many as four UAVs bring in 30 s (a fit of which takes about a second on one core).
MOST_REPORTS = 1200


def velocity_hypotheses(scenario: Scenario) -> np.ndarray:
    """(V, 2) m/s: standing still first, then every ``SPEED_STEP_MPS`` over the training's
    driving speeds in each of ``HEADINGS`` directions."""
    low, high = scenario.training.moving_jammer_speed_range_mps
    speeds = np.arange(low, high + SPEED_STEP_MPS / 2, SPEED_STEP_MPS)
    angles = 2.0 * math.pi * np.arange(HEADINGS) / HEADINGS
    driving = (speeds[:, None, None]
               * np.stack([np.cos(angles), np.sin(angles)], axis=-1)[None]).reshape(-1, 2)
    return np.concatenate([np.zeros((1, 2)), driving])


def driving_frames(xy: np.ndarray, times: np.ndarray, at_s: float,
                   velocities: np.ndarray) -> np.ndarray:
    """(V, n, 2): where uploads at ``xy`` (n, 2) taken at ``times`` (n,) stand from a jammer
    at each of ``velocities`` (V, 2), in the frame of its place at ``at_s``."""
    ahead_s = np.asarray(times, dtype=np.float64) - at_s
    return np.asarray(xy, dtype=np.float64)[None] - ahead_s[None, :, None] * velocities[:, None]


def estimate_driving_jammer(scenario: Scenario, xy: np.ndarray, times: np.ndarray,
                            levels: np.ndarray, at_s: float, **inputs) -> JammerEstimate | None:
    """The jammer of uploads at ``xy`` (n, 2) taken at ``times`` (n,) s with ``levels``,
    placed where it is at ``at_s``, with its velocity and their standard deviations when it
    drives; else the still jammer's estimate (``estimate_jammer``'s, None where it does not
    converge). ``inputs``: what ``estimate_jammer`` reads besides (the reported SINRs, the
    no-jammer beliefs, the decision's report spread).

    Each velocity's coarse search ranks it (``fit_frames``); standing still and the
    ``FULLY_FITTED`` best velocities get ``estimate_jammer``'s whole estimate. The best
    velocity whose estimate converges drives the jammer when the reports' log-likelihood
    with its best hypothesis beats standing still's (converged or not) by BIC's penalty for
    two parameters more. The velocity's sd is the spread of those converged, weighed by that
    likelihood, with the grid's own: a uniform over a cell of the grid adds its side squared
    over 12."""
    velocities = velocity_hypotheses(scenario)
    fitted = fit_frames(scenario, xy, levels, driving_frames(xy, times, at_s, velocities),
                        fitted=FULLY_FITTED, **inputs)
    if fitted is None:
        return None
    still, *others = fitted
    converged = [fit for fit in others if fit.estimate is not None]
    if not converged:
        return still.estimate
    best = max(converged, key=lambda fit: fit.log_likelihood)
    penalty = math.log(best.estimate.measurements)  # BIC: half a log of n for each of vx and vy
    if best.log_likelihood - still.log_likelihood < penalty:
        return still.estimate
    if still.estimate is not None:
        converged.append(still)
    log_likelihood = np.array([fit.log_likelihood for fit in converged])
    weight = np.exp(log_likelihood - log_likelihood.max())
    weight /= weight.sum()
    fitted_velocities = velocities[[fit.frame for fit in converged]]
    spread = weight @ (fitted_velocities - weight @ fitted_velocities) ** 2
    velocity = velocities[best.frame]
    cell_m_s = max(SPEED_STEP_MPS, float(np.hypot(*velocity)) * 2.0 * math.pi / HEADINGS)
    sd = np.sqrt(spread + cell_m_s**2 / 12.0)
    return best.estimate._replace(vx_mps=float(velocity[0]), vy_mps=float(velocity[1]),
                                  sd_vx_mps=float(sd[0]), sd_vy_mps=float(sd[1]))


def driving_refit(inputs: EstimateInputs, data: MeasurementBatch) -> JammerEstimate | None:
    """A driving jammer fitted to the latest ``online_map.driving_fit_window_s`` of a
    change's uploads ``data`` (every k-th of them where more than ``MOST_REPORTS``), placed
    where it will be when the map corrected for it flies (the cloud's latency after the
    newest upload); None where it does not drive."""
    scenario = inputs.models.scenario
    newest = float(data.times.max())
    rows = np.flatnonzero(data.times >= newest - scenario.online_map.driving_fit_window_s)
    recent = data.take(rows[:: math.ceil(len(rows) / MOST_REPORTS)])
    xy, levels, keywords = inputs.of(recent)
    driving = estimate_driving_jammer(scenario, xy, recent.times, levels,
                                      newest + scenario.online_map.cloud_latency_s, **keywords)
    return driving if driving is not None and driving.vx_mps is not None else None
