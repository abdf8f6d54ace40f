"""Per-UAV mission outcomes, exclusive and final once set, and the rules that end a mission in
a step: written once for the world (``world_sim.core.VectorWorld.step``) and for the lookahead
that predicts it (``planning.reference.LookaheadPolicy.expand``; the compiled core,
``planning/_lookahead.pyx``, repeats them in C).

A collision (a smallest gap over the step, distance less both radii, of zero or less) comes
first, then an arrival, then a disconnection. The lookahead lets a move that collides arrive
too, as either ends it; only the world bars it (``arrivals``' ``may_arrive``). Only the world
times a mission out: the lookahead does not count a mission's steps.
"""

from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

import numpy as np

from shared.kinematics import closest_approach


class Outcome(IntEnum):
    """How a UAV's mission stands: active, or the one way it ended."""

    ACTIVE = 0
    SUCCESS = 1
    DISCONNECTION = 2
    COLLISION = 3
    TIMEOUT = 4

    @property
    def label(self) -> str:
        return self.name.lower()


FINAL_OUTCOMES = (Outcome.SUCCESS, Outcome.DISCONNECTION, Outcome.COLLISION, Outcome.TIMEOUT)
OUTCOME_LABELS = [outcome.label for outcome in Outcome]


class Arrivals(NamedTuple):
    arrived: np.ndarray  # (...) bool
    position: np.ndarray  # (..., 2) where the step leaves each UAV: its destination if arrived


def arrivals(position: np.ndarray, velocity: np.ndarray, destination: np.ndarray, dt: float,
             tolerance: float, may_arrive: np.ndarray | None = None) -> Arrivals:
    """Which UAVs flying ``velocity`` from ``position`` for ``dt`` arrive, and where the step
    leaves each. A UAV arrives when it passes within ``tolerance`` of its ``destination`` at
    any instant of the step (a fast one may fly through it), and then ends the step there.
    Without ``may_arrive`` (bool, as ``arrived``) every UAV may."""
    arrived = closest_approach(position - destination, velocity, dt) <= tolerance
    if may_arrive is not None:
        arrived &= may_arrive
    return Arrivals(arrived, np.where(arrived[..., None], destination, position + velocity * dt))


class Disconnections(NamedTuple):
    below_steps: np.ndarray  # consecutive steps below T_s (level 0), the step's included
    disconnected: np.ndarray  # bool


def disconnections(level: np.ndarray, below_steps: np.ndarray, limit: int,
                   still_flying: np.ndarray) -> Disconnections:
    """The count of consecutive steps below T_s after a step that ends on ``level``, from
    ``below_steps`` before it, and which UAVs the step disconnects: those beyond ``limit``
    steps, of the ones ``still_flying`` after the step's collisions and arrivals."""
    below = np.where(level == 0, below_steps + 1, 0)
    return Disconnections(below, still_flying & (below > limit))
