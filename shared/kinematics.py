"""UAV kinematics: the permissible action set under (P1.d) and (P1.e), propagation, and the
closest approach of two straight motions within one step (used for collisions and R_c)."""

from __future__ import annotations

import math

import numpy as np

from shared.scenario import Scenario


def clamp(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """``np.clip(values, low, high)`` (NaN stays NaN) without its wrapper's checks, which cost
    more than the clipping on the lookahead's small arrays."""
    return np.minimum(np.maximum(values, low), high)


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(angle) + math.pi) % (2.0 * math.pi) - math.pi


class ActionSet:
    """The sampled action space A_t: speeds x heading changes, plus hovering.

    Speeds are spaced exponentially in (0, v_max] (fine control near the destination, as in
    CADRL); heading changes are spread evenly over [-dt*T_r, +dt*T_r]. Action 0 is hovering
    (speed 0, heading kept), so the set is never empty and always permissible.
    """

    def __init__(self, scenario: Scenario):
        uav = scenario.uav
        self.max_speed = uav.max_speed_mps
        self.max_turn = math.radians(uav.turn_rate_deg_s) * scenario.timing.step_s
        n = uav.speed_choices
        fractions = (np.exp(np.arange(1, n + 1) / n) - 1.0) / (math.e - 1.0)
        turns = (
            np.linspace(-self.max_turn, self.max_turn, uav.heading_choices)
            if uav.heading_choices > 1
            else np.zeros(1)
        )
        speed_grid, turn_grid = np.meshgrid(fractions * self.max_speed, turns, indexing="ij")
        self.speeds = np.concatenate([[0.0], speed_grid.ravel()])
        self.turns = np.concatenate([[0.0], turn_grid.ravel()])
        # The actions share a few heading changes (hovering's among them): turning and its
        # trigonometry are done once per distinct change, then spread over the speeds.
        self._distinct_turns, self._turn_of_action = np.unique(self.turns, return_inverse=True)

    def __len__(self) -> int:
        return self.speeds.shape[0]

    def candidates(self, heading: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Speeds and headings of every action for UAVs at ``heading`` (...,): shape (..., A)."""
        speeds, distinct = self._distinct_headings(heading)
        return speeds, distinct[..., self._turn_of_action]

    def moves(self, heading: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``candidates`` and the velocity (..., A, 2) of each: ``velocity_of`` them, to the
        bit, at a fraction of its cost."""
        speeds, distinct = self._distinct_headings(heading)
        direction = direction_of(distinct)[..., self._turn_of_action, :]
        return speeds, distinct[..., self._turn_of_action], speeds[..., None] * direction

    def _distinct_headings(self, heading: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        heading = np.asarray(heading, dtype=np.float64)[..., None]
        speeds = np.broadcast_to(self.speeds, heading.shape[:-1] + self.speeds.shape)
        return speeds, wrap_angle(heading + self._distinct_turns)

    def clip(
        self, speed: np.ndarray, heading: np.ndarray, current_heading: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The nearest permissible command: speed in [0, v_max], turn within +-dt*T_r."""
        speed = np.clip(np.nan_to_num(speed, nan=0.0), 0.0, self.max_speed)
        turn = np.clip(
            wrap_angle(np.nan_to_num(heading, nan=0.0) - current_heading),
            -self.max_turn,
            self.max_turn,
        )
        # Hovering keeps the heading: a stopped UAV has no direction of travel to turn from.
        new_heading = np.where(speed > 0, wrap_angle(current_heading + turn), current_heading)
        return speed, new_heading


def direction_of(heading: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 2) along ``heading`` (...,)."""
    return np.stack([np.cos(heading), np.sin(heading)], axis=-1)


def velocity_of(speed: np.ndarray, heading: np.ndarray) -> np.ndarray:
    return np.asarray(speed)[..., None] * direction_of(heading)


def closest_approach(
    relative_position: np.ndarray, relative_velocity: np.ndarray, duration: float
) -> np.ndarray:
    """Minimum distance over [0, duration] of two points moving straight at constant velocity.

    ``relative_position`` and ``relative_velocity`` have shape (..., 2); returns shape (...).
    """
    px, py = relative_position[..., 0], relative_position[..., 1]
    vx, vy = relative_velocity[..., 0], relative_velocity[..., 1]
    speed_sq = vx * vx + vy * vy
    toward = -(px * vx + py * vy)
    time = clamp(
        np.divide(toward, speed_sq, out=np.zeros_like(toward), where=speed_sq > 0), 0.0, duration
    )
    return np.hypot(px + vx * time, py + vy * time)
