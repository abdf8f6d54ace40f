"""The compiled lookahead: ``planning.reference.LookaheadPolicy``'s decisions, each UAV's taken
whole by the compiled core (``planning._lookahead``) from plain arrays.

The settings, the checks on the value network and every other method stay those of the
reference, which this class extends; only ``decide`` (and ``decide_scored``) run compiled.
The maps it reads are raster maps (``planning.maps.RasterMap``), as agents, evaluation and
training fly."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from planning.compiled import compiled_module, on_two_cores
from planning.features import ABSENT_DISTANCE, joint_state_size
from planning.maps import RasterMap, RouteFields
from planning.networks import ValueNetwork
from planning.reference import (
    CLOSING_TOLERANCE_M,
    DEEP_SEARCH_BEAM,
    GAP_SLACK_M,
    Decision,
    LookaheadPolicy,
    explored,
)
from planning.routes import REACH_FACTOR, REACH_MARGIN_M
from shared.kinematics import wrap_angle
from shared.observation import CELL_CLEARANCE_M, Observation
from shared.scenario import Scenario

_lookahead = compiled_module("_lookahead")

NO_ROUTES = RouteFields([], np.zeros(0, dtype=np.int64), np.zeros(0), 0.0, 0.0, 1.0)


class ScoredDecision(NamedTuple):
    """A decision with the scores and the safe cells' allowed actions it was chosen from."""

    decision: Decision
    score: np.ndarray  # (N, A) as LookaheadPolicy.scored gives it
    allowed: np.ndarray  # (N, A)


class CompiledLookahead(LookaheadPolicy):
    """The lookahead with its decision computed by the compiled core (``_lookahead.pyx``):
    the same choices as ``LookaheadPolicy``, which it is tested against; the planner
    ``planning.chosen`` picks unless ``JAMNAV_PLANNER=reference``."""

    def __init__(self, scenario: Scenario, value_net: ValueNetwork, shield: bool = True,
                 lookahead_depth: int | None = None, others_model: str | None = None):
        super().__init__(scenario, value_net, shield, lookahead_depth, others_model)
        if type(value_net).__call__ is not ValueNetwork.__call__:
            raise TypeError("the compiled planner computes a value network's layers; "
                            f"{type(value_net).__name__} computes its values otherwise")
        turns, turn_of_action = np.unique(self.actions.turns, return_inverse=True)
        rewards = self.rewards
        settings = {
            "speeds": self.actions.speeds, "distinct_turns": turns,
            "turn_of_action": turn_of_action.astype(np.int64),
            "connectivity_by_level": rewards.connectivity_by_level,
            "observed_uavs": self.observed_uavs, "depth": self.depth,
            "others_model": self.others_model,
            "beam": DEEP_SEARCH_BEAM, "safe_cells": self.safe_cells,
            "disconnection_memory": self.options.disconnection_memory,
            "route_distance": self.options.route_distance,
            "dt": self.dt, "gamma": self.gamma, "arrival_tolerance": self.tolerance,
            "top_speed": self.actions.max_speed, "discomfort": rewards.discomfort,
            "collision": rewards.collision, "arrival": rewards.arrival,
            "step_reward": rewards.step,
            "disconnection_reward": self.options.disconnection_reward,
            "collision_margin": self.options.collision_margin_m,
            "closing_tolerance": CLOSING_TOLERANCE_M, "gap_slack": GAP_SLACK_M,
            "cell_clearance": CELL_CLEARANCE_M, "orca_time_horizon": self.orca_time_horizon,
            "absent_distance": ABSENT_DISTANCE,
            "disconnection_limit": self.disconnection_limit,
            "check_every": rewards.check_every, "weak_levels": self.weak_levels,
            "value_scale": value_net.value_scale,
            "features": joint_state_size(scenario, self.options),
        }
        mean, std, layers = value_net.layers()
        self.kernel = _lookahead.Kernel(settings, (_float32(mean), _float32(std), [
            (_float32(weight), _float32(bias)) for weight, bias in layers]))
        # How far from a UAV the search reads the route field: its deepest move's end.
        self.search_reach = self.depth * self.actions.max_speed * self.dt
        self._recent_fields: tuple | None = None

    def decide(self, observation: Observation, radio_map: RasterMap, epsilon: float = 0.0,
               rng: np.random.Generator | None = None) -> Decision:
        if epsilon <= 0:
            return self.decide_scored(observation, radio_map).decision
        decision, _, allowed = self.decide_scored(observation, radio_map)
        action, value = explored(decision.action, decision.value, allowed, epsilon, rng)
        return Decision(self.actions.speeds[action],
                        wrap_angle(observation.heading + self.actions.turns[action]), action,
                        value)

    def decide_scored(self, observation: Observation, radio_map: RasterMap) -> ScoredDecision:
        """The decision, with every action's score and which the safe cells allow."""
        if not isinstance(radio_map, RasterMap):
            raise TypeError("the compiled planner reads raster maps (planning.maps.RasterMap), "
                            f"not {type(radio_map).__name__}")
        n, actions = len(observation), len(self.actions)
        out = (np.empty(n, dtype=np.int64), np.empty(n), np.empty(n), np.empty(n),
               np.empty((n, actions)), np.empty((n, actions), dtype=np.uint8),
               np.zeros(n, dtype=np.uint8))
        state = _plain(observation)
        fields = self._route_fields(observation, radio_map, None)
        self._run(state, radio_map, fields, out)
        missing = out[-1]
        if missing.any():  # a field computed as far as a reach, read beyond it: whole now
            self._run(state, radio_map,
                      self._route_fields(observation, radio_map, missing.astype(bool)), out)
        action, speed, heading, value, score, allowed, _ = out
        return ScoredDecision(Decision(speed, heading, action, value), score,
                              allowed.view(bool))

    def _route_fields(self, observation: Observation, radio_map: RasterMap,
                      whole: np.ndarray | None) -> RouteFields:
        """The route fields of each row. An agent asks for the same map and destination at
        every decision: the answer stays, until the map's routing grids evict a field."""
        if not self.options.route_distance:
            return NO_ROUTES
        destination = np.ascontiguousarray(observation.destination, dtype=np.float64)
        grids = [raster.routes(self.scenario) for raster in radio_map.rasters]
        key = (destination.tobytes(), radio_map.which.tobytes(),
               [(grid.changes, id(grid.store)) for grid in grids])
        recent = self._recent_fields
        if whole is None and recent is not None and recent[0] is radio_map and recent[1] == key:
            return recent[2]
        straight = np.hypot(*(observation.position - destination).T) + self.search_reach
        fields = radio_map.route_fields(destination, REACH_FACTOR * straight + REACH_MARGIN_M,
                                        whole)
        key[2][:] = [(grid.changes, id(grid.store)) for grid in grids]
        self._recent_fields = (radio_map, key, fields)
        return fields

    def _run(self, state: tuple, radio_map: RasterMap, fields: RouteFields,
             out: tuple) -> None:
        first = radio_map.first
        which = np.ascontiguousarray(radio_map.which, dtype=np.int64)
        routed = len(fields.slots) > 0

        def decide(rows: slice) -> None:
            self.kernel.decide(*(part[rows] for part in state), radio_map.stack, which[rows],
                               first.x0, first.y0, first.spacing, fields.stores,
                               fields.slots[rows] if routed else fields.slots,
                               fields.offset[rows] if routed else fields.offset, fields.x0,
                               fields.y0, fields.cell, *(part[rows] for part in out))

        on_two_cores(decide, len(which))


def _float32(array: np.ndarray) -> np.ndarray:
    """The array itself where it is float32 and C-contiguous (the views of a torch module's
    memory that training updates in place), a copy otherwise."""
    return np.ascontiguousarray(array, dtype=np.float32)


def _plain(observation: Observation) -> tuple:
    """The observation's arrays in the types the compiled core reads."""
    def floats(values):
        return np.ascontiguousarray(values, dtype=np.float64)

    def integers(values):
        return np.ascontiguousarray(values, dtype=np.int64)

    return (floats(observation.position), floats(observation.velocity),
            floats(observation.heading), floats(observation.destination),
            floats(observation.radius), floats(observation.max_speed),
            integers(observation.level), integers(observation.below_steps),
            integers(observation.step),
            floats(observation.others_position), floats(observation.others_velocity),
            floats(observation.others_radius),
            np.ascontiguousarray(observation.others_present, dtype=bool).view(np.uint8))
