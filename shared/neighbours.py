"""Which others a UAV must see, found with a k-d tree per fleet.

Apart from ``shared.observation`` because only the world and the in-process flights look for
neighbours among many UAVs: an agent is sent its neighbours, and scipy.spatial would cost each
agent process memory for nothing (BENCHMARKS.md, "Fleets of agent processes").
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def nearby_others(position: np.ndarray, active: np.ndarray, count: int,
                  reach: float) -> np.ndarray | None:
    """The others each UAV of E fleets of J (position (E, J, 2), active (E, J)) must see to
    decide as if it saw them all (``decision_relevant``): indices (E, J, M) of its ``count``
    nearest active others and of every active one within ``reach``, nearest first, -1 where a
    row has fewer. None when every other is among the ``count`` nearest anyway. A k-d tree per
    fleet keeps this O(J log J), where the full view of the J - 1 others is O(J^2)."""
    e, j = active.shape
    if j - 1 <= count:
        return None
    rows = np.arange(j)[:, None]
    picked = []
    for env in range(e):
        members = np.flatnonzero(active[env])
        if members.size == 0:
            picked.append(np.empty((j, 0), dtype=np.int64))
            continue
        tree = cKDTree(position[env, members])
        in_reach = tree.query_ball_point(position[env], reach, return_length=True)
        # One more than wanted: an active UAV finds itself first.
        k = min(members.size, max(count, int(in_reach.max())) + 1)
        _, nearest = tree.query(position[env], k=k)
        found = members[nearest.reshape(j, k)]
        kept = np.argsort(found == rows, axis=1, kind="stable")[:, : k - 1]
        picked.append(np.take_along_axis(found, kept, axis=1))
    width = max(p.shape[1] for p in picked)
    out = np.full((e, j, width), -1, dtype=np.int64)
    for env, found in enumerate(picked):
        out[env, :, : found.shape[1]] = found
    return out
