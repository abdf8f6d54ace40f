"""Route distance over a radio map: how far the destination is along the cheapest route that
stays connected, instead of as the crow flies.

The map's levels are read on a coarse grid; moving through an uncovered cell costs
``uncovered_cost`` times its length, so routes bend around jammed zones and cross narrow gaps
only where that is short. One Dijkstra per (map, destination) gives the distance from every
grid node (or every node within reach of the trips asked about: ``REACH_FACTOR``); a lookup
is a bilinear interpolation. This is the map-aware feature of the extended
method: a one-step lookahead that reads it descends the route instead of walking into the
first hole it meets.

Two builders give the same fields, bit for bit: both settle on the one fixpoint of
d[v] = min(d[v], d[u] + w(u, v)) over the same float64 edge weights, whatever the order of the
relaxations (test). The compiled core's Dijkstra (``planning/_routes.pyx``) builds them for
every caller, the batches of destinations of training and the in-process flights and an agent's
one destination alike: faster than scipy's Dijkstra, and without the tens of MiB that importing
scipy's graph module costs an agent (bench_policy's route field rows; BENCHMARKS.md, "Route
fields compiled"). ``JAMNAV_PLANNER=reference`` sweeps them in numpy instead (``SweptFields``),
the reference the compiled one is tested against. An agent told its next destination builds
that field between decisions (``RouteGrid.prepare``).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from functools import partial
from typing import NamedTuple

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from planning.compiled import chosen_planner, compiled_module, on_two_cores
from shared.kinematics import clamp


class EdgeWeights(NamedTuple):
    """Length times mean crossing cost of every edge of the 8-connected grid, by direction:
    ``down[r, c]`` joins (r, c)-(r+1, c), ``right[r, c]`` (r, c)-(r, c+1), ``down_right[r, c]``
    (r, c)-(r+1, c+1) and ``down_left[r, c]`` (r, c+1)-(r+1, c)."""

    down: np.ndarray
    right: np.ndarray
    down_right: np.ndarray
    down_left: np.ndarray

    @classmethod
    def of(cls, cost: np.ndarray, cell: float) -> EdgeWeights:
        straight, diagonal = cell * 1.0, cell * float(np.hypot(1, 1))
        return cls(
            down=straight * (0.5 * (cost[:-1, :] + cost[1:, :])),
            right=straight * (0.5 * (cost[:, :-1] + cost[:, 1:])),
            down_right=diagonal * (0.5 * (cost[:-1, :-1] + cost[1:, 1:])),
            down_left=diagonal * (0.5 * (cost[:-1, 1:] + cost[1:, :-1])),
        )

    def transposed(self) -> EdgeWeights:
        return EdgeWeights(self.right.T, self.down.T, self.down_right.T, self.down_left.T)

    def improvable(self, field: np.ndarray) -> bool:
        """Whether some edge still shortens ``field``: False only at the fixpoint."""
        ends = ((field[:-1, :], field[1:, :], self.down), (field[:, :-1], field[:, 1:], self.right),
                (field[:-1, :-1], field[1:, 1:], self.down_right),
                (field[:-1, 1:], field[1:, :-1], self.down_left))
        return any(bool((a + w < b).any() or (b + w < a).any()) for a, b, w in ends)

    def from_previous_line(self) -> tuple[np.ndarray, np.ndarray]:
        """Weights (lines - 1, columns, 3) of the edges into column c of a line from columns
        c - 1, c, c + 1 of the line before it, sweeping first to last and last to first
        (infinite where the column is off the grid), indexed by the lower line's edge row."""
        beyond = np.full((self.down.shape[0], 1), np.inf)
        forward = np.stack([np.hstack([beyond, self.down_right]), self.down,
                            np.hstack([self.down_left, beyond])], axis=-1)
        backward = np.stack([np.hstack([beyond, self.down_left]), self.down,
                             np.hstack([self.down_right, beyond])], axis=-1)
        return forward, backward


# A builder of route fields: destination nodes (K,) int64 and their limits (K,) -> the fields
# (K, rows, cols) float64, each infinite where the route is longer than its limit.
FieldBuilder = Callable[[np.ndarray, np.ndarray], np.ndarray]


class SweptFields:
    """The reference builder of route fields, in numpy: each field by Gauss-Seidel sweeps until
    no edge shortens it (2-4 rounds: about one per bend of the routes). A round sweeps the rows
    down and up, then the columns right and left, each line relaxed from the one before it. The
    two sweeps along an axis run at once, on two copies of the field stacked together (the
    second upside down, so that it too runs first to last), and each node keeps the shorter of
    the two: one numpy call relaxes a line of each, which makes a field cheaper than sweeping
    them one after the other (BENCHMARKS.md, "Fleets of agent processes")."""

    def __init__(self, weights: EdgeWeights):
        self.weights = weights
        # The weights as the sweeps read them: rows, then columns, the second copy upside down.
        self.lines = tuple(
            np.stack([forward, backward[::-1]]) for forward, backward in
            (weights.from_previous_line(), weights.transposed().from_previous_line()))

    def __call__(self, nodes: np.ndarray, limits: np.ndarray) -> np.ndarray:
        fields = np.stack([self.field(node) for node in nodes.tolist()])
        fields[fields > limits[:, None, None]] = np.inf  # as Dijkstra stopped at the limit
        return fields

    def field(self, node: int) -> np.ndarray:
        """The whole field (rows, cols) to ``node``."""
        # A border of infinity, so that every line reads three neighbours of each column.
        padded = np.full((self.weights.right.shape[0] + 2, self.weights.down.shape[1] + 2),
                         np.inf)
        field = padded[1:-1, 1:-1]
        field.flat[node] = 0.0
        while True:
            for lines, weights in zip((padded, padded.T), self.lines, strict=True):
                both_ways = np.stack([lines, lines[::-1]])
                _sweep_lines(both_ways, weights)
                np.minimum(both_ways[0], both_ways[1][::-1], out=lines)
            if not self.weights.improvable(field):
                return field


def field_builder(weights: EdgeWeights) -> FieldBuilder:
    """The builder of route fields on ``weights`` that ``JAMNAV_PLANNER`` names: the compiled
    core's Dijkstra, or the numpy sweeps of the reference."""
    if chosen_planner() == "reference":
        return SweptFields(weights)
    return partial(_fields_on_two_cores, partial(compiled_module("_routes").route_fields,
                                                 *weights))


def _fields_on_two_cores(build: FieldBuilder, nodes: np.ndarray,
                         limits: np.ndarray) -> np.ndarray:
    """The compiled fields, half of the destinations on a second core (their Dijkstra runs
    without the GIL): each field is computed alone, so the same fields."""
    parts: dict[int, np.ndarray] = {}

    def work(part: slice) -> None:
        parts[part.start] = build(nodes[part], limits[part])

    on_two_cores(work, len(nodes), split_at=2)
    return np.concatenate([parts[start] for start in sorted(parts)])


# Distance fields a route grid keeps by default: every destination of a batch of environments
# (an in-process evaluation's whole fleet, training's environments in flight).
FIELDS_KEPT = 4096
# A field computed for trips stops where the route grows longer than a reach: this many times
# the straight distance from the farthest position asked about to the destination, plus the
# margin, rounded up to REACH_STEP_M. Dijkstra settles nodes in the order of their distance, so
# every node within the reach has its exact distance and every node beyond reads infinity; a
# query that reads one has its field computed whole (a decision that reads one, every field of
# its batch that stops at a reach: rounding up keeps that rare). So the values read are those
# of the whole field, bit for bit, and most fields cover a disc about the trip instead of the
# map: on a large map most of the work is saved.
REACH_FACTOR = 1.5
REACH_MARGIN_M = 30.0
REACH_STEP_M = 50.0


class RouteGrid:
    """The coarse routing graph of one map raster, and a cache of distance fields on it."""

    def __init__(self, covered: np.ndarray, x0: float, y0: float, cell: float,
                 uncovered_cost: float, cache_size: int = FIELDS_KEPT):
        self.rows, self.cols = covered.shape
        self.x0, self.y0, self.cell = x0, y0, cell
        self.weights = EdgeWeights.of(np.where(covered, 1.0, uncovered_cost), cell)
        self._build = field_builder(self.weights)
        # Destination node -> its slot in ``store``, least recently used first. One array of
        # fields read by fancy indexing: stacking them per query would copy every field at
        # every step (43 MB a step with 256 UAVs on a 400 m map).
        self.cache: OrderedDict[int, int] = OrderedDict()
        self.cache_size = cache_size
        self.store = np.empty((0, self.rows, self.cols), dtype=np.float32)
        self._partial: set[int] = set()  # destination nodes whose field stops at a reach
        # Fields evicted so far: a reader that kept a field's slot in ``store`` may read it
        # there for as long as this count and ``store`` stay.
        self.changes = 0

    def node_of(self, xy: np.ndarray) -> np.ndarray:
        col = clamp(np.rint((xy[..., 0] - self.x0) / self.cell), 0, self.cols - 1)
        row = clamp(np.rint((xy[..., 1] - self.y0) / self.cell), 0, self.rows - 1)
        return (row * self.cols + col).astype(np.int64)

    def slots(self, nodes: np.ndarray,
              reach_m: Callable[[], np.ndarray] | None = None) -> np.ndarray:
        """Slots in ``store`` of the distance fields to each destination node, computed on
        first use (once for a node asked for twice); beyond cache_size the least recently
        used field's slot is reused. With ``reach_m`` (giving one route length per node) the
        fields computed may stop beyond it (see REACH_FACTOR)."""
        wanted = nodes.tolist()
        for node in wanted:
            if node in self.cache:
                self.cache.move_to_end(node)
        missing = list(dict.fromkeys(node for node in wanted if node not in self.cache))
        if missing:
            reach = {}
            if reach_m is not None:
                for node, metres in zip(wanted, reach_m().tolist(), strict=True):
                    reach[node] = max(reach.get(node, 0.0), metres)
            self._compute(missing, [reach.get(node, np.inf) for node in missing])
        return np.array([self.cache[node] for node in wanted], dtype=np.int64)

    def _compute(self, nodes: list[int], reach_m: list[float]) -> None:
        """The fields to ``nodes`` into the cache, each stopped at its reach rounded up to
        REACH_STEP_M (infinite: whole)."""
        if not nodes:
            return
        limits = np.ceil(np.asarray(reach_m, dtype=np.float64) / REACH_STEP_M) * REACH_STEP_M
        fields = self._build(np.asarray(nodes, dtype=np.int64), limits)
        for node, field, limit in zip(nodes, fields, limits.tolist(), strict=True):
            self._keep(node, field)
            if np.isfinite(limit):
                self._partial.add(node)

    def prepare(self, destination: np.ndarray) -> None:
        """The whole field to ``destination`` (2,) into the cache, unless one is there: an
        agent told its next mission builds it between decisions, so that the new mission's
        first decision finds it ready."""
        node = int(self.node_of(np.asarray(destination, dtype=np.float64)))
        if node not in self.cache:
            self._compute([node], [np.inf])

    def _keep(self, node: int, field: np.ndarray) -> None:
        slot = self.cache.get(node)
        if slot is None:
            slot = self._free_slot()
        self.store[slot] = field.reshape(self.rows, self.cols)
        self.cache[node] = slot
        self._partial.discard(node)

    def _free_slot(self) -> int:
        if len(self.cache) >= self.cache_size:
            node, slot = self.cache.popitem(last=False)
            self._partial.discard(node)
            self.changes += 1
        else:
            slot = len(self.cache)
            if slot == len(self.store):
                grown = np.empty((max(1, 2 * slot),) + self.store.shape[1:], dtype=np.float32)
                grown[:slot] = self.store
                self.store = grown
        return slot

    def distance(self, xy: np.ndarray, destination: np.ndarray) -> np.ndarray:
        """Route distance from positions ``xy`` (N, ..., 2) to each row's ``destination``
        (N, 2): the field interpolated at ``xy`` plus the last stretch to the exact point."""
        nodes = self.node_of(destination)

        def reach() -> np.ndarray:  # only when a field is computed
            rows = (-1,) + (1,) * (xy.ndim - 2)
            straight = np.hypot(xy[..., 0] - destination[:, 0].reshape(rows),
                                xy[..., 1] - destination[:, 1].reshape(rows))
            return REACH_FACTOR * straight.reshape(len(nodes), -1).max(axis=1) + REACH_MARGIN_M

        value = self._read(self.slots(nodes, reach), xy)
        if self._partial:
            short = ~np.isfinite(value.reshape(len(nodes), -1)).all(axis=1)
            if short.any():  # a position beyond the reach: that field whole, and read again
                beyond = list(dict.fromkeys(nodes[short].tolist()))
                self._compute(beyond, [np.inf] * len(beyond))
                value[short] = self._read(self.slots(nodes[short]), xy[short])
        return value + self._offset(destination, nodes).reshape((-1,) + (1,) * (xy.ndim - 2))

    def _offset(self, destination: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        """The last stretch (N,) from each destination's grid node to the exact point."""
        return np.hypot(destination[:, 0] - (self.x0 + (nodes % self.cols) * self.cell),
                        destination[:, 1] - (self.y0 + (nodes // self.cols) * self.cell))

    def fields(self, destination: np.ndarray, reach_m: np.ndarray,
               whole: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """For a reader of ``store`` that interpolates as ``distance`` does: the slots (N,) of
        the fields to each ``destination`` (N, 2), computed as far as each row's ``reach_m``
        (N,) at least (see REACH_FACTOR; ``whole``: everywhere), and each destination's offset
        from its node (N,), which ``distance`` adds to the field's value."""
        nodes = self.node_of(destination)
        if whole:
            partial = [node for node in dict.fromkeys(nodes.tolist()) if node in self._partial]
            self._compute(partial, [np.inf] * len(partial))
        return self.slots(nodes, lambda: reach_m), self._offset(destination, nodes)

    def _read(self, slot: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """The fields in ``slot`` (N,) interpolated at ``xy`` (N, ..., 2)."""
        fields = self.store
        fx = clamp((xy[..., 0] - self.x0) / self.cell, 0, self.cols - 1)
        fy = clamp((xy[..., 1] - self.y0) / self.cell, 0, self.rows - 1)
        c0 = np.minimum(np.floor(fx).astype(np.int64), self.cols - 2)
        r0 = np.minimum(np.floor(fy).astype(np.int64), self.rows - 2)
        tx, ty = fx - c0, fy - r0
        sx, sy = 1 - tx, 1 - ty
        field = slot.reshape((-1,) + (1,) * (xy.ndim - 2))
        # Corners read through one flat index each: half the cost of three index arrays.
        corner = (field * self.rows + r0) * self.cols + c0
        flat = fields.reshape(-1)
        # Beyond a field's reach a corner is infinite, and infinity times a zero weight is NaN:
        # ``distance`` computes such a field whole and reads it again.
        with np.errstate(invalid="ignore"):
            return (
                flat[corner] * sx * sy
                + flat[corner + 1] * tx * sy
                + flat[corner + self.cols] * sx * ty
                + flat[corner + self.cols + 1] * tx * ty
            )


def _sweep_lines(stacked: np.ndarray, weights: np.ndarray) -> None:
    """Relax every line of each padded field of ``stacked`` (copies, line, column), in place
    and first to last, from the line before it, by that copy's ``weights`` (copies, lines - 1,
    columns, 3) in the form of ``from_previous_line``; the borders stay infinite."""
    lines = stacked.shape[1] - 2
    neighbours = sliding_window_view(stacked, 3, axis=2)  # [copy, line, c] = columns c-1..c+1
    reached = np.empty((stacked.shape[0], *neighbours.shape[2:]))
    best = np.empty(reached.shape[:2])
    for line in range(2, lines + 1):
        np.add(neighbours[:, line - 1], weights[:, line - 2], out=reached)
        np.minimum(reached[..., 0], reached[..., 1], out=best)
        np.minimum(best, reached[..., 2], out=best)
        here = stacked[:, line, 1:-1]
        np.minimum(here, best, out=here)
