"""The radio maps the lookahead reads: the SINR level at a position it has not been to yet
and, for the extended method, the distance along the map's connected route (``planning.routes``).

``TrueMap`` is the simulator's map, exact at every query. ``LevelRaster`` holds levels sampled
on a grid (``sinr_network_raster``: a SINR-mapping network's map), the form agents, evaluation
and training fly; ``RasterMap`` gives each UAV row its own raster.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np

from planning.measuring import scenario_features
from planning.networks import SinrMapNetwork, predict_levels
from planning.routes import FIELDS_KEPT, RouteGrid
from shared.kinematics import clamp
from shared.radio import Jammers, RadioModel
from shared.scenario import Scenario


class RadioMap(Protocol):
    """Where the lookahead gets the SINR level of a position it has not been to yet."""

    def level_at(self, xy: np.ndarray) -> np.ndarray:
        """Levels at positions ``xy`` of shape (N, A, 2), one row per UAV: (N, A)."""

    def route_distance(self, xy: np.ndarray, destination: np.ndarray) -> np.ndarray:
        """Distance along the map's connected route from ``xy`` (N, ..., 2) to each row's
        destination (N, 2); read only by the extended method."""

    def for_rows(self, rows: np.ndarray) -> RadioMap:
        """The map as read by the UAVs of ``rows`` (indices into the UAV rows), one row each:
        how a deeper lookahead queries the UAVs it searches, each several times over."""


MAP_SPACING_M = 0.5  # raster spacing of the lookahead's maps: well below a UAV's radius
# Grid rows whose SINR-map features are computed at once: few, so that an agent's memory peaks
# little above its floor while it samples a map (BENCHMARKS.md, "Fleets of agent processes");
# more rows at once were no faster.
RASTER_BLOCK_ROWS = 16
RASTER_TILE_COLUMNS = 64


class TrueMap:
    """The simulator's map with given jammers, computed exactly at every query."""

    def __init__(self, radio: RadioModel, jammers: Jammers):
        self.radio = radio
        self.jammers = jammers

    def level_at(self, xy: np.ndarray) -> np.ndarray:
        return self.radio.evaluate(xy, self.jammers).level

    def for_rows(self, rows: np.ndarray) -> TrueMap:
        return self  # one map for every row


class LevelRaster:
    """Quantized levels sampled on a square grid over the area plus a margin: the stored form
    of a radio map. A query snaps to the nearest grid node, so it costs an index lookup
    instead of a radio (or network) evaluation; beyond the margin the edge value holds."""

    def __init__(self, levels: np.ndarray, x0: float, y0: float, spacing: float):
        self.levels = np.ascontiguousarray(levels, dtype=np.int8)
        self.x0, self.y0, self.spacing = x0, y0, spacing
        # How many route fields the routing grid keeps (set before its first use): a fleet's
        # destinations in-process, far fewer in an agent.
        self.route_fields_kept = FIELDS_KEPT
        self._routes: RouteGrid | None = None

    @classmethod
    def sample(
        cls,
        scenario: Scenario,
        level_fn: Callable[[np.ndarray], np.ndarray],
        spacing: float,
    ) -> LevelRaster:
        area = scenario.area
        margin = scenario.uav.max_speed_mps * scenario.timing.step_s + spacing
        xs = np.arange(area.x_min - margin, area.x_max + margin + spacing / 2, spacing)
        ys = np.arange(area.y_min - margin, area.y_max + margin + spacing / 2, spacing)
        grid = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1)
        return cls(level_fn(grid), float(xs[0]), float(ys[0]), spacing)

    def indices(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows, cols = self.levels.shape[-2:]
        col = np.rint((xy[..., 0] - self.x0) / self.spacing).astype(np.int64)
        row = np.rint((xy[..., 1] - self.y0) / self.spacing).astype(np.int64)
        return clamp(row, 0, rows - 1), clamp(col, 0, cols - 1)

    def level_at(self, xy: np.ndarray) -> np.ndarray:
        return self.levels[self.indices(xy)]

    def for_rows(self, rows: np.ndarray) -> LevelRaster:
        return self  # one map for every row

    def routes(self, scenario: Scenario) -> RouteGrid:
        """The routing grid of this map (built once): levels read every route_cell_m."""
        if self._routes is None:
            stride = max(1, round(scenario.policy.route_cell_m / self.spacing))
            covered = self.levels[::stride, ::stride] > 0
            self._routes = RouteGrid(covered, self.x0, self.y0, self.spacing * stride,
                                     scenario.policy.route_uncovered_cost,
                                     self.route_fields_kept)
        return self._routes


def sinr_network_raster(
    network: SinrMapNetwork, scenario: Scenario, spacing: float = MAP_SPACING_M
) -> LevelRaster:
    """A SINR-mapping network's map sampled on the lookahead's grid, a block of rows at a time
    (the features of a whole city-sized grid at once would take gigabytes)."""

    def features(rows: np.ndarray) -> np.ndarray:
        # Tile by tile: a compact tile reads only the GBSs near it (the city's ~40 of 192).
        tiles = np.array_split(rows, max(1, rows.shape[1] // RASTER_TILE_COLUMNS), axis=1)
        return np.concatenate([scenario_features(scenario, tile) for tile in tiles], axis=1)

    def levels(grid: np.ndarray) -> np.ndarray:
        blocks = np.array_split(grid, max(1, grid.shape[0] // RASTER_BLOCK_ROWS))
        return np.concatenate([predict_levels(network, features(block)) for block in blocks])

    return LevelRaster.sample(scenario, levels, spacing)


class RouteFields(NamedTuple):
    """Route fields as plain arrays: row n reads field ``slots[n]`` of ``stores[which[n]]``
    (fields (S, rows, cols) float32 on a grid from (x0, y0) at ``cell`` metres), interpolated
    bilinearly, plus ``offset[n]`` (``planning.routes.RouteGrid.distance``)."""

    stores: list[np.ndarray]
    slots: np.ndarray
    offset: np.ndarray
    x0: float
    y0: float
    cell: float


class RasterMap:
    """Several rasters of one shape, each UAV row reading its own (per-environment jammers)."""

    def __init__(self, scenario: Scenario, rasters: list[LevelRaster], which: np.ndarray):
        self.scenario = scenario
        self.rasters = rasters
        self.first = rasters[0]
        self.stack = np.stack([raster.levels for raster in rasters])
        self.which = which

    def level_at(self, xy: np.ndarray) -> np.ndarray:
        row, col = self.first.indices(xy)
        which = self.which.reshape(self.which.shape + (1,) * (xy.ndim - 2))
        _, rows, cols = self.stack.shape
        return self.stack.ravel()[(which * rows + row) * cols + col]  # one index: faster than three

    def for_rows(self, rows: np.ndarray) -> RasterMap:
        subset = copy.copy(self)  # the rasters and their route caches are shared, not copied
        subset.which = self.which[rows]
        return subset

    def prepare_route(self, destination: np.ndarray) -> None:
        """The route field to ``destination`` (2,) on the first raster (an agent's only one),
        built into its cache (``RouteGrid.prepare``)."""
        self.first.routes(self.scenario).prepare(destination)

    def route_fields(self, destination: np.ndarray, reach_m: np.ndarray,
                     whole: np.ndarray | None = None) -> RouteFields:
        """The route fields to each row's ``destination`` (N, 2) as plain arrays, computed as
        far as each row's ``reach_m`` (N,) at least, everywhere for the rows ``whole`` marks
        (N,): what ``route_distance`` interpolates, for a reader in compiled code."""
        slots = np.empty(len(self.which), dtype=np.int64)
        offset = np.empty(len(self.which))
        grids = [raster.routes(self.scenario) for raster in self.rasters]
        for index, grid in enumerate(grids):
            rows = np.flatnonzero(self.which == index)
            if rows.size:
                slots[rows], offset[rows] = grid.fields(
                    destination[rows], reach_m[rows],
                    whole is not None and bool(whole[rows].any()))
        first = grids[0]  # the rasters share one shape, so their routing grids one geometry
        return RouteFields([grid.store for grid in grids], slots, offset, first.x0, first.y0,
                           first.cell)

    def route_distance(self, xy: np.ndarray, destination: np.ndarray) -> np.ndarray:
        """Route distance (N, ...) from ``xy`` (N, ..., 2) to each row's destination."""
        out = np.empty(xy.shape[:-1], dtype=np.float64)
        for index, raster in enumerate(self.rasters):
            rows = np.flatnonzero(self.which == index)
            if rows.size:
                out[rows] = raster.routes(self.scenario).distance(xy[rows], destination[rows])
        return out
