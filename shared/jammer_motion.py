"""Where each jammer of a world stands, and whether it transmits, at a time into an episode.

A jammer's drive and its schedule both start afresh with each episode (``shared.scenario``'s
``JammerPath`` and schedules), so every episode of a run meets its jammers alike, and a world
process and an in-process evaluation place them at the same steps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from shared.radio import JammerParams
from shared.scenario import DutyCycle, Jammer


def position_at(jammer: Jammer, t: float) -> tuple[float, float]:
    """Where ``jammer`` is ``t`` seconds into an episode: on its path, at its speed."""
    if jammer.path is None:
        return jammer.x, jammer.y
    corners = [(jammer.x, jammer.y), *jammer.path.waypoints]
    if jammer.path.loop:
        corners.append((jammer.x, jammer.y))
    corners_xy = np.asarray(corners, dtype=np.float64)
    legs = np.hypot(*np.diff(corners_xy, axis=0).T)
    along = np.concatenate([[0.0], np.cumsum(legs)])
    total = float(along[-1])
    if total == 0.0:
        return jammer.x, jammer.y
    travelled = jammer.path.speed_mps * t
    travelled = math.fmod(travelled, total) if jammer.path.loop else min(travelled, total)
    # The last leg of positive length that starts at or before the distance travelled.
    leg = int(np.flatnonzero((along[:-1] <= travelled) & (legs > 0))[-1])
    share = min((travelled - along[leg]) / legs[leg], 1.0)
    x, y = corners_xy[leg] + share * (corners_xy[leg + 1] - corners_xy[leg])
    return float(x), float(y)


def transmits_at(jammer: Jammer, t: float, flying_xy: np.ndarray) -> bool:
    """Whether ``jammer`` transmits ``t`` seconds into an episode, with UAVs in flight at
    ``flying_xy`` (n, 2): a reactive jammer hears them, a duty cycle keeps its own time."""
    if not jammer.enabled or jammer.power_w == 0:
        return False
    schedule = jammer.schedule
    if schedule is None:
        return True
    if isinstance(schedule, DutyCycle):
        return math.fmod(t + schedule.offset_s, schedule.on_s + schedule.off_s) < schedule.on_s
    x, y = position_at(jammer, t)
    flying_xy = np.asarray(flying_xy, dtype=np.float64).reshape(-1, 2)
    return bool((np.hypot(flying_xy[:, 0] - x, flying_xy[:, 1] - y) <= schedule.radius_m).any())


def params_at(jammers: Sequence[Jammer], t: float,
              flying_xy: np.ndarray) -> tuple[JammerParams, ...]:
    """The radio model's jammers ``t`` seconds into an episode: those transmitting, where they
    are then."""
    return tuple(JammerParams(*position_at(jammer, t), jammer.power_w, jammer.height_m)
                 for jammer in jammers if transmits_at(jammer, t, flying_xy))
