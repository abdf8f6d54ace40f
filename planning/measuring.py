"""What a UAV's reports become on their way to the cloud: the SINR map's input features at
each report's place (``scenario_features``, the one feature function: training, the agents, the
cloud and the evaluation all call it, so a map learned anywhere reads the same inputs
everywhere) and the spot filter that picks the reports a UAV uploads.

An agent runs both on its few reports at every step, where numpy's cost per call is the whole
cost: ``JAMNAV_PLANNER`` chooses the compiled core (planning/_measuring.pyx, the default) or
the numpy functions here, its reference. Both choose the same GBSs and keep the same reports; a
feature may differ by one float32 rounding step (the angles, see the core)."""

from __future__ import annotations

from functools import cache
from types import ModuleType

import numpy as np

from planning.compiled import chosen_planner, compiled_module
from shared.measurements import PER_GBS_FEATURES
from shared.scenario import Scenario


@cache
def _core() -> ModuleType:
    return compiled_module("_measuring")


def scenario_features(scenario: Scenario, xy: np.ndarray) -> np.ndarray:
    """``gbs_features`` with the scenario's GBS layout, K_n, UAV altitude, GBS height and
    channels, then the nearest GBS's position if the scenario asks for it."""
    gbs = scenario.gbs
    return _features(xy, gbs.xy, scenario.policy.nearby_gbs, scenario.uav.altitude_m,
                     gbs.height_m, gbs.channel_of, scenario.policy.nearest_gbs_position)


def gbs_features(
    xy: np.ndarray, gbs_xy: np.ndarray, nearby: int, altitude: float, gbs_height: float,
    gbs_channels: np.ndarray | None = None,
) -> np.ndarray:
    """Input of the SINR-mapping network at UAV positions ``xy`` (shape (..., 2)).

    For the ``nearby`` GBSs closest to the UAV, nearest first (ties keep the scenario's
    order): [dx, dy, horizontal distance, elevation angle, azimuth] of the GBS seen from the
    UAV, in metres and radians. The frame is north-up (+x east, +y north) and only translated
    to the UAV, never turned with its heading: the SINR map depends on where the UAV is, not on
    where it points, so two UAVs at one spot must get one input. Elevation is negative when
    the GBS is below the UAV; azimuth is counter-clockwise from +x in (-pi, pi]. With
    ``gbs_channels``, a sixth: 1 if the GBS shares the nearest GBS's channel, else 0.

    Returns float32 of shape (..., 5 * nearby), or (..., 6 * nearby) with channels.
    """
    return _features(xy, gbs_xy, nearby, altitude, gbs_height, gbs_channels, False)


def _features(xy: np.ndarray, gbs_xy: np.ndarray, nearby: int, altitude: float,
              gbs_height: float, gbs_channels: np.ndarray | None,
              nearest_position: bool) -> np.ndarray:
    """``gbs_features``, then the nearest GBS's position with ``nearest_position``, by the
    core ``JAMNAV_PLANNER`` names."""
    xy = np.asarray(xy, dtype=np.float64)
    gbs_xy = np.ascontiguousarray(gbs_xy, dtype=np.float64)
    if chosen_planner() == "reference":
        features, nearest = _nearby_gbs_features(xy, gbs_xy, nearby, altitude, gbs_height,
                                                 gbs_channels)
        if not nearest_position:
            return features
        return np.concatenate([features, gbs_xy[nearest].astype(np.float32)], axis=-1)
    points = np.ascontiguousarray(xy.reshape(-1, 2))
    channels = (np.empty(0, dtype=np.int64) if gbs_channels is None
                else np.ascontiguousarray(gbs_channels, dtype=np.int64))
    size = ((len(PER_GBS_FEATURES) + int(gbs_channels is not None)) * nearby
            + 2 * int(nearest_position))
    features = np.empty((len(points), size), dtype=np.float32)
    _core().nearby_gbs_features(points, gbs_xy, channels, nearby, float(altitude),
                                float(gbs_height), nearest_position, features)
    return features.reshape(xy.shape[:-1] + (size,))


def _nearby_gbs_features(
    xy: np.ndarray, gbs_xy: np.ndarray, nearby: int, altitude: float, gbs_height: float,
    gbs_channels: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """``gbs_features`` by numpy, the reference, and the index of each point's nearest GBS."""
    xy = np.asarray(xy, dtype=np.float64)
    gbs_xy = np.asarray(gbs_xy, dtype=np.float64)
    within = _candidates(xy, gbs_xy, nearby)
    gbs_x, gbs_y = gbs_xy[within].T
    x, y = xy[..., 0, None], xy[..., 1, None]
    distance = np.hypot(gbs_x - x, gbs_y - y)
    order = _nearest_first(distance, nearby)
    distance = _take_along_last_axis(distance, order)
    # dx and dy again, for the chosen GBSs only: the same subtractions, so the same values,
    # and cheaper than gathering both along the points' rows.
    dx, dy = gbs_x[order] - x, gbs_y[order] - y
    elevation = np.arctan2(gbs_height - altitude, distance)
    azimuth = np.arctan2(dy, dx)
    columns = [dx, dy, distance, elevation, azimuth]
    nearest = within[order]
    if gbs_channels is not None:
        channel = np.asarray(gbs_channels)[nearest]
        columns.append(channel == channel[..., :1])
    # Column by column into float32: for an agent's few points, np.stack and a float64 copy
    # cost several times more.
    features = np.empty(distance.shape + (len(columns),), dtype=np.float32)
    for i, column in enumerate(columns):
        features[..., i] = column
    return features.reshape(xy.shape[:-1] + (len(columns) * nearby,)), nearest[..., 0]


def _take_along_last_axis(values: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """``np.take_along_axis(values, indices, axis=-1)`` for arrays of equal leading shape, in a
    fraction of its time on small arrays."""
    rows = np.arange(0, values.size, values.shape[-1]).reshape(indices.shape[:-1] + (1,))
    return values.reshape(-1)[rows + indices]


def _candidates(xy: np.ndarray, gbs_xy: np.ndarray, nearby: int) -> np.ndarray:
    """Indices, ascending, of the GBSs that can be among the ``nearby`` nearest of some point
    of ``xy``: all of them, but for a compact block of points on a large layout (a raster
    tile in the city) only those within the centre's ``nearby``-th distance plus the block's
    diameter. A point p within r of the centre c has its ``nearby`` nearest within
    d_k(c) + r of p, so within d_k(c) + 2 r of c: the features are the same as from all."""
    every = np.arange(len(gbs_xy))
    flat = xy.reshape(-1, 2)
    if len(gbs_xy) <= 2 * nearby or len(flat) == 0:
        return every
    low, high = flat.min(axis=0), flat.max(axis=0)
    centre, reach = (low + high) / 2, float(np.hypot(*(high - low))) / 2
    distance = np.hypot(*(gbs_xy - centre).T)
    kth = np.partition(distance, nearby - 1)[nearby - 1]
    # A millimetre of slack: rounding must not drop a GBS on the boundary.
    return np.flatnonzero(distance <= kth + 2 * reach + 1e-3)


def _nearest_first(distance: np.ndarray, nearby: int) -> np.ndarray:
    """Indices of the ``nearby`` smallest distances along the last axis, nearest first, ties
    in index order: ``np.argsort(distance, kind="stable")[..., :nearby]``, but O(n) in the
    number of GBSs when only a few of many are wanted (the city's 12 of 192)."""
    count = distance.shape[-1]
    if nearby >= count:
        return np.argsort(distance, axis=-1, kind="stable")
    flat = distance.reshape(-1, count)
    # The nearby-th smallest distance: all below it are in, and of those equal to it the
    # lowest indices until there are ``nearby`` (rows with such ties are rare).
    edge = np.partition(flat, nearby - 1, axis=-1)[:, nearby - 1 : nearby]
    below = flat < edge
    chosen = below | (flat == edge)
    tied = np.flatnonzero(chosen.sum(axis=-1) > nearby)
    if tied.size:
        room = nearby - below[tied].sum(axis=-1, keepdims=True)
        at_edge = chosen[tied] & ~below[tied]
        chosen[tied] = below[tied] | (at_edge & (np.cumsum(at_edge, axis=-1) <= room))
    # Exactly ``nearby`` chosen per row: their column indices, row by row, in index order.
    picked = np.nonzero(chosen)[1].reshape(-1, nearby)
    ranked = np.argsort(np.take_along_axis(flat, picked, axis=-1), axis=-1, kind="stable")
    return np.take_along_axis(picked, ranked, axis=-1).reshape(distance.shape[:-1] + (nearby,))


class SpotFilter:
    """Which of its receiver's reports each UAV of a fleet keeps and uploads.

    A UAV hovering (or crawling) measures the same spot again and again: one report per spot
    and level is all the cloud needs, and repeats would let one UAV's spot fill the
    detector's windows. A report is kept when it lies at least ``uav.measurement_spacing_m``
    from the UAV's last kept one, or shows another level. Agents (one UAV each) and the
    in-process evaluation (a whole fleet) keep reports through this one rule.
    """

    def __init__(self, scenario: Scenario, uavs: int):
        # A 0-d array: numpy compares an array with it faster than with a float.
        self.spacing = np.array(scenario.uav.measurement_spacing_m)
        self.last_xy = np.full((uavs, 2), np.inf)
        self.last_level = np.full(uavs, -1, dtype=np.int64)

    def keep(self, uavs: np.ndarray, xy: np.ndarray, levels: np.ndarray) -> np.ndarray:
        """Mask (n, S) of the reports to keep, for UAVs ``uavs`` (n,) that reported at ``xy``
        (n, S, 2) with ``levels`` (n, S), in the order they were taken along the path."""
        uavs = np.ascontiguousarray(uavs, dtype=np.int64)
        if chosen_planner() == "reference":
            return self._keep_by_numpy(uavs, xy, levels)
        levels = np.ascontiguousarray(levels, dtype=np.int64)
        kept = np.empty(levels.shape, dtype=np.uint8)
        _core().keep_spots(self.last_xy, self.last_level, uavs,
                           np.ascontiguousarray(xy, dtype=np.float64), levels,
                           float(self.spacing), kept)
        return kept.view(bool)

    def _keep_by_numpy(self, uavs: np.ndarray, xy: np.ndarray, levels: np.ndarray
                       ) -> np.ndarray:
        """``keep`` by numpy, the reference."""
        # A report is dropped only at the level of the last one kept, so that level is always
        # the previous report's: where the level changes needs no scan.
        levels = np.concatenate([self.last_level[uavs, None], np.asarray(levels)], axis=1)
        changed = (levels[:, 1:] != levels[:, :-1]).T.copy()
        # Where the UAV moved far enough does: report by report, each in a few numpy calls on
        # all n UAVs at once. For one UAV (an agent's every step) the calls' overhead is the
        # whole cost, hence contiguous rows read in turn and ufuncs writing in place.
        along_xy = np.asarray(xy, dtype=np.float64).transpose(1, 2, 0).copy()
        last_xy = self.last_xy[uavs].T.copy()
        kept = np.empty(changed.shape, dtype=bool)
        for here, level_changed, keep in zip(along_xy, changed, kept, strict=True):
            apart = here - last_xy
            np.logical_or(np.hypot(apart[0], apart[1]) >= self.spacing, level_changed, out=keep)
            np.copyto(last_xy, here, where=keep)
        self.last_xy[uavs], self.last_level[uavs] = last_xy.T, levels[:, -1]
        return kept.T.copy()
