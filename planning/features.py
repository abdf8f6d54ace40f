"""The joint state s^jn the value network reads (paper Sec. III-A), from what a UAV observes
(``shared.observation.Observation``).

The frame is agent-centric and turned so that +x points at the UAV's destination (as CADRL):
translating or rotating the whole world leaves the features unchanged, so the value network
does not depend on the choice of coordinates.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from shared.kinematics import wrap_angle
from shared.observation import Observation
from shared.scenario import Scenario

OWN_FEATURES = ("v_x", "v_y", "dest_x", "dest_y", "dest_distance", "dest_azimuth",
                "radius", "max_speed", "heading")
OTHER_FEATURES = ("p_x", "p_y", "v_x", "v_y", "distance", "azimuth")
# A missing neighbour (fewer than J_n in the air) is shown as a still UAV this far behind,
# where it cannot matter, so the network needs no special input for absence.
ABSENT_DISTANCE = 1000.0


class MethodOptions(NamedTuple):
    """What a value network reads beyond the paper's joint state, and how its lookahead
    scores a lost mission. The defaults are the paper's method; they travel in the network's
    safetensors metadata so a network is always run the way it was trained."""

    disconnection_memory: bool = False  # consecutive steps below T_s, as a feature
    route_distance: bool = False  # distance along the map's cheapest connected route
    disconnection_reward: float = 0.0  # added when a mission ends by disconnection
    # The lookahead treats another UAV closer than r_i + r_j + margin as a collision: the
    # others may turn into the predicted path within the step.
    collision_margin_m: float = 0.0
    # At run time each UAV keeps its move inside its buffered Voronoi cell (the half-planes
    # that stay a radius short of the bisector to every UAV in sight). Two UAVs that both do
    # so cannot touch, whatever they choose at the same instant: the guarantee that a
    # constant-velocity prediction lacks when a hovering UAV starts or another turns.
    # Training flies without it (see LookaheadPolicy): trained inside the cells, the network
    # never met a collision and leaned on the cells, with more timeouts (README, "The
    # extended method").
    safe_cells: bool = False

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> MethodOptions:
        return cls(**(data or {}))


PAPER_METHOD = MethodOptions()
EXTENDED_METHOD = MethodOptions(disconnection_memory=True, route_distance=True,
                                disconnection_reward=-1.0, collision_margin_m=1.5,
                                safe_cells=True)
METHODS = {"paper": PAPER_METHOD, "extended": EXTENDED_METHOD}


def joint_state_size(scenario: Scenario, options: MethodOptions = PAPER_METHOD) -> int:
    extra = int(options.disconnection_memory) + int(options.route_distance)
    return len(OWN_FEATURES) + len(OTHER_FEATURES) * scenario.policy.observed_uavs + 1 + extra


def joint_state(
    position: np.ndarray,
    velocity: np.ndarray,
    heading: np.ndarray,
    destination: np.ndarray,
    radius: np.ndarray,
    max_speed: np.ndarray,
    level: np.ndarray,
    others_position: np.ndarray,
    others_velocity: np.ndarray,
    others_present: np.ndarray,
    observed_uavs: int,
    below_steps: np.ndarray | None = None,
    route_distance: np.ndarray | None = None,
) -> np.ndarray:
    """Joint state features, float32, shape (..., F).

    Own arrays have shape (..., 2) or (...); others (..., K, 2) or (..., K) with K <= J_n,
    already chosen and ordered (``Observation.nearest_neighbours``), broadcastable against
    the own batch (the lookahead passes own (N, A) against others (N, 1, K)).
    """
    if others_present.shape[-1] > observed_uavs:
        raise ValueError("pass at most J_n others: see Observation.nearest_neighbours")
    goal_distance, cos, sin = _goal_frame(position, destination)
    extras = [column for column in (below_steps, route_distance) if column is not None]
    level_column = len(OWN_FEATURES) + len(OTHER_FEATURES) * observed_uavs
    # One contiguous plane per feature, turned into rows of features once at the end: faster
    # on the lookahead's batch than writing each feature down a column of the rows.
    planes = np.empty((level_column + 1 + len(extras),) + goal_distance.shape)
    _write_own(planes[: len(OWN_FEATURES)], velocity, heading, radius, max_speed,
               goal_distance, cos, sin)
    width = len(OTHER_FEATURES)
    for k in range(observed_uavs):
        column = len(OWN_FEATURES) + k * width
        block = planes[column : column + width]
        if k < others_present.shape[-1]:
            _write_other(block, others_position[..., k, :] - position,
                         others_velocity[..., k, :], others_present[..., k], cos, sin)
        else:
            _write_absent(block)
    planes[level_column] = level
    # Extended method: how long the UAV has been disconnected (tells a harmless gap from a
    # fatal one) and how far the destination is along the map's connected route.
    for offset, column in enumerate(extras, start=1):
        planes[level_column + offset] = column
    return np.ascontiguousarray(np.moveaxis(planes, 0, -1), dtype=np.float32)


def _goal_frame(position: np.ndarray,
                destination: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distance to the goal, and the cosine and sine of the frame's turn: its +x axis is
    the unit vector to the goal (any axis at the goal itself)."""
    gx = destination[..., 0] - position[..., 0]
    gy = destination[..., 1] - position[..., 1]
    goal_distance = np.hypot(gx, gy)
    at_goal = goal_distance == 0
    safe = goal_distance.copy()
    np.copyto(safe, 1.0, where=at_goal)
    cos, sin = gx / safe, gy / safe
    np.copyto(cos, 1.0, where=at_goal)
    np.copyto(sin, 0.0, where=at_goal)
    return goal_distance, cos, sin


def _write_own(planes: np.ndarray, velocity: np.ndarray, heading: np.ndarray,
               radius: np.ndarray, max_speed: np.ndarray, goal_distance: np.ndarray,
               cos: np.ndarray, sin: np.ndarray) -> None:
    """The UAV's own features (``OWN_FEATURES``) into their planes."""
    vx, vy = velocity[..., 0], velocity[..., 1]
    planes[0] = vx * cos + vy * sin
    planes[1] = vy * cos - vx * sin
    planes[2] = goal_distance  # destination in the turned frame: (d_d, 0), azimuth 0
    planes[3] = 0.0
    planes[4] = goal_distance
    planes[5] = 0.0
    planes[6] = radius
    planes[7] = max_speed
    planes[8] = wrap_angle(heading - np.arctan2(sin, cos))


def _write_other(block: np.ndarray, offset: np.ndarray, velocity: np.ndarray,
                 present: np.ndarray, cos: np.ndarray, sin: np.ndarray) -> None:
    """One observed UAV's features (``OTHER_FEATURES``) into ``block``: where it is
    (``offset`` from the UAV) and how it moves, turned into the frame; where ``present`` is
    False, the still UAV far behind that stands for a missing one."""
    rx, ry = offset[..., 0], offset[..., 1]
    ovx, ovy = velocity[..., 0], velocity[..., 1]
    px, py = block[0], block[1]
    px[...] = rx * cos + ry * sin
    py[...] = ry * cos - rx * sin
    block[2] = ovx * cos + ovy * sin
    block[3] = ovy * cos - ovx * sin
    absent = ~present
    if absent.any():
        np.copyto(px, -ABSENT_DISTANCE, where=absent)
        np.copyto(block[1:4], 0.0, where=absent)
    np.hypot(px, py, out=block[4])
    np.arctan2(py, px, out=block[5])


def _write_absent(block: np.ndarray) -> None:
    """A neighbour slot no observed UAV fills: a still UAV ``ABSENT_DISTANCE`` behind."""
    block[0] = -ABSENT_DISTANCE
    block[1:4] = 0.0
    block[4] = ABSENT_DISTANCE
    block[5] = np.pi


def observation_state(
    observation: Observation,
    scenario: Scenario,
    options: MethodOptions = PAPER_METHOD,
    radio_map: Any = None,
) -> np.ndarray:
    """Joint state of each UAV as observed now: (N, F). The extended method's route
    distance needs the UAV's radio map."""
    observed_uavs = scenario.policy.observed_uavs
    route = None
    if options.route_distance:
        route = radio_map.route_distance(
            observation.position[:, None, :], observation.destination
        )[:, 0]
    observation = observation.nearest_neighbours(observed_uavs)
    return joint_state(
        observation.position,
        observation.velocity,
        observation.heading,
        observation.destination,
        observation.radius,
        observation.max_speed,
        observation.level,
        observation.others_position,
        observation.others_velocity,
        observation.others_present,
        observed_uavs,
        observation.below_steps if options.disconnection_memory else None,
        route,
    )
