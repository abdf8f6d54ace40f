"""What a UAV observes, and which of the others it must be shown to decide as if it saw them
all.

The world (and the in-process flights that stand in for it) builds observations; the planners
of ``planning`` read them. They meet here, so the world needs no planner. Which others can
matter follows from the planners' safe cells, whose clearance is therefore set here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.scenario import Scenario

# The lookahead's safe cells (planning.reference.inside_safe_cells) keep this far from a cell's
# edge, so two UAVs at their edges do not touch; which others an observation must carry follows.
CELL_CLEARANCE_M = 0.005
REACH_SLACK_M = 1.0  # added to decision_reach against rounding at its edge


def decision_reach(scenario: Scenario, radius: np.ndarray) -> np.ndarray:
    """How near another UAV must be to matter to a decision beyond the J_n nearest: the safe
    cell (``planning.reference.inside_safe_cells``) stops a move at half the distance to each other
    less the UAV's ``radius`` and clearance, and no move is longer than v_max * dt, so only an
    other closer than twice their sum can bound it."""
    longest_move = scenario.uav.max_speed_mps * scenario.timing.step_s
    return 2 * (longest_move + radius + CELL_CLEARANCE_M) + REACH_SLACK_M


@dataclass
class Observation:
    """What N UAVs know, batched: their own state and the observable state of the others.

    Own fields have shape (N, ...); others have shape (N, M, ...) with ``others_present``
    marking the real ones (M may exceed J_n; the nearest J_n are used).
    """

    position: np.ndarray  # (N, 2)
    velocity: np.ndarray  # (N, 2)
    heading: np.ndarray  # (N,)
    destination: np.ndarray  # (N, 2)
    radius: np.ndarray  # (N,)
    max_speed: np.ndarray  # (N,)
    level: np.ndarray  # (N,) quantized SINR level measured now
    below_steps: np.ndarray  # (N,) consecutive measurements below T_s up to now
    step: np.ndarray  # (N,) step index of the episode (R_s is checked when n_t divides it)
    others_position: np.ndarray  # (N, M, 2)
    others_velocity: np.ndarray  # (N, M, 2)
    others_radius: np.ndarray  # (N, M)
    others_present: np.ndarray  # (N, M) bool

    def __len__(self) -> int:
        return self.position.shape[0]

    @classmethod
    def of_fleet(
        cls,
        position: np.ndarray,
        velocity: np.ndarray,
        heading: np.ndarray,
        destination: np.ndarray,
        radius: np.ndarray,
        max_speed: np.ndarray,
        level: np.ndarray,
        below_steps: np.ndarray,
        active: np.ndarray,
        step: np.ndarray,
        others: np.ndarray | None = None,
    ) -> Observation:
        """Observations of every UAV of E fleets of J (arrays (E, J, ...), step (E,)), each
        seeing the others of its own fleet that ``others`` (E, J, M) lists
        (``shared.neighbours.nearby_others``: indices, -1 for none), or all J - 1 of them;
        rows are ordered env-major."""
        e, j = active.shape
        if others is None:
            column = np.arange(max(j - 1, 0))
            everyone = column[None, :] + (column[None, :] >= np.arange(j)[:, None])
            others = np.broadcast_to(everyone, (e, j, column.size))
        width = others.shape[2]
        fleet = np.arange(e)[:, None, None]
        listed = np.maximum(others, 0)

        def gather(values: np.ndarray) -> np.ndarray:
            picked = values[fleet, listed]  # (E, J, M, ...)
            return picked.reshape((e * j, width) + values.shape[2:])

        return cls(
            position=position.reshape(e * j, 2),
            velocity=velocity.reshape(e * j, 2),
            heading=heading.reshape(e * j),
            destination=destination.reshape(e * j, 2),
            radius=radius.reshape(e * j),
            max_speed=max_speed.reshape(e * j),
            level=level.reshape(e * j),
            below_steps=below_steps.reshape(e * j),
            step=np.repeat(step, j),
            others_position=gather(position),
            others_velocity=gather(velocity),
            others_radius=gather(radius),
            others_present=gather(active) & (others >= 0).reshape(e * j, width),
        )

    def select(self, rows: np.ndarray) -> Observation:
        return Observation(**{name: value[rows] for name, value in vars(self).items()})

    def nearest_neighbours(self, count: int) -> Observation:
        """The same observation keeping only the ``count`` nearest present others, nearest
        first (absent ones last): the J_n UAVs a UAV watches, chosen once per decision."""
        relative = self.others_position - self.position[:, None, :]
        distance = np.where(self.others_present, np.hypot(relative[..., 0], relative[..., 1]),
                            np.inf)
        order = np.argsort(distance, axis=1, kind="stable")[:, :count]
        rows = np.arange(len(self))[:, None]
        fields = dict(vars(self))
        for name in ("others_position", "others_velocity", "others_radius", "others_present"):
            fields[name] = fields[name][rows, order]
        return Observation(**fields)


def decision_relevant(observation: Observation, count: int, reach: np.ndarray) -> np.ndarray:
    """Which others (N, M) can change a UAV's decision: the ``count`` nearest present ones
    (ranked as ``Observation.nearest_neighbours`` ranks them, ties included) and every present
    one closer than the UAV's ``reach`` (N,). Removing the rest, in order, leaves the same
    nearest neighbours, and absent others count as nothing anywhere."""
    relative = observation.others_position - observation.position[:, None, :]
    distance = np.where(observation.others_present,
                        np.hypot(relative[..., 0], relative[..., 1]), np.inf)
    nearest = np.argsort(distance, axis=1, kind="stable")[:, :count]
    ranked = np.zeros(distance.shape, dtype=bool)
    np.put_along_axis(ranked, nearest, True, axis=1)
    return observation.others_present & (ranked | (distance <= reach[:, None]))
