"""Optimal Reciprocal Collision Avoidance (ORCA) for disc-shaped agents in the plane.

Implements J. van den Berg, S. J. Guy, M. Lin and D. Manocha, "Reciprocal n-body collision
avoidance", Robotics Research (ISRR 2009), Springer Tracts in Advanced Robotics 70, 2011,
pp. 3-19, for agent-agent avoidance only (no static obstacles):

* for every pair (A, B), the velocity obstacle VO^tau_{A|B} truncated by the time horizon tau,
  the vector u from the relative velocity to the closest point of its boundary and the outward
  normal n there; A takes half of the responsibility, ORCA^tau_{A|B} = {v | (v - (v_A + u/2)) . n
  >= 0};
* the 2-D linear program: the velocity closest to the preferred one inside the max-speed disc
  and all half-planes, solved incrementally (constraints in a fixed order, so the result is
  deterministic);
* when that program is infeasible, the 3-D program: the velocity in the speed disc minimising
  the largest signed distance by which it violates a half-plane.

Every world of the batch is independent; the work is vectorised over all agents of all worlds,
with Python loops only over the (few) constraints of an agent.
"""

from __future__ import annotations

import numpy as np

# Below this, two constraint lines are treated as parallel (their normals are unit vectors).
_PARALLEL_EPS = 1e-12


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _det(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _perp(a: np.ndarray) -> np.ndarray:
    """``a`` rotated by +90 degrees."""
    return np.stack([-a[..., 1], a[..., 0]], axis=-1)


def _safe_unit(a: np.ndarray, length: np.ndarray) -> np.ndarray:
    return a / np.where(length > 0.0, length, 1.0)[..., None]


def _half_planes(
    positions: np.ndarray,
    velocities: np.ndarray,
    radii: np.ndarray,
    time_horizon: float,
    time_step: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Points and unit normals (E, J, J, 2) of ORCA^tau_{a|b}: (v - point) . normal >= 0."""
    rel_pos = positions[:, None, :, :] - positions[:, :, None, :]  # p_b - p_a
    rel_vel = velocities[:, :, None, :] - velocities[:, None, :, :]  # v_a - v_b
    combined = radii[:, :, None] + radii[:, None, :]
    dist_sq = _dot(rel_pos, rel_pos)
    apart = dist_sq > combined**2

    # Separated agents: the obstacle is the cone of the disc D(p, r) cut off by D(p/tau, r/tau).
    w = rel_vel - rel_pos / time_horizon
    w_len = np.sqrt(_dot(w, w))
    w_dot_p = _dot(w, rel_pos)
    # w lies within the angle that the cut-off arc subtends at its centre exactly when the
    # angle between w and -p is below arccos(r/|p|), i.e. -w.p > r|w|.
    on_cutoff = (w_dot_p < 0.0) & (w_dot_p**2 > combined**2 * w_len**2)
    w_unit = _safe_unit(w, w_len)
    cutoff_u = ((combined / time_horizon - w_len)[..., None]) * w_unit

    # Legs: tangents from the origin to D(p, r), rotated from p by +-asin(r/|p|).
    leg = np.sqrt(np.maximum(dist_sq - combined**2, 0.0))
    safe_dist_sq = np.where(apart, dist_sq, 1.0)[..., None]
    px, py = rel_pos[..., 0], rel_pos[..., 1]
    left = _det(rel_pos, w) > 0.0
    left_dir = np.stack([px * leg - py * combined, px * combined + py * leg], axis=-1)
    right_dir = np.stack([px * leg + py * combined, -px * combined + py * leg], axis=-1)
    leg_dir = np.where(left[..., None], left_dir, right_dir) / safe_dist_sq
    # The obstacle lies clockwise of the left leg and counter-clockwise of the right one.
    leg_normal = np.where(left[..., None], _perp(leg_dir), -_perp(leg_dir))
    leg_u = _dot(rel_vel, leg_dir)[..., None] * leg_dir - rel_vel

    # Overlapping agents: the obstacle for the next time step alone, D(p/dt, r/dt), so that the
    # pair is pushed apart as fast as possible.
    wc = rel_vel - rel_pos / time_step
    wc_len = np.sqrt(_dot(wc, wc))
    dist = np.sqrt(dist_sq)
    # Ties (relative velocity at the disc centre, or coincident agents) still need a normal
    # that is opposite for the two agents of the pair: away from the other agent, and for
    # coincident agents, opposite directions chosen by agent index.
    count = positions.shape[1]
    by_index = np.where(np.arange(count)[:, None] < np.arange(count)[None, :], -1.0, 1.0)
    index_dir = np.stack([by_index, np.zeros_like(by_index)], axis=-1)
    fallback = np.where(
        (dist > 0.0)[..., None], -_safe_unit(rel_pos, dist), np.broadcast_to(index_dir, w.shape)
    )
    overlap_normal = np.where((wc_len > 0.0)[..., None], _safe_unit(wc, wc_len), fallback)
    overlap_u = ((combined / time_step - wc_len)[..., None]) * overlap_normal

    normal = np.where(
        apart[..., None],
        np.where(on_cutoff[..., None], w_unit, leg_normal),
        overlap_normal,
    )
    u = np.where(apart[..., None], np.where(on_cutoff[..., None], cutoff_u, leg_u), overlap_u)
    point = velocities[:, :, None, :] + 0.5 * u
    return point, normal


def _line_interval(
    point: np.ndarray,
    normal: np.ndarray,
    prev_points: np.ndarray,
    prev_normals: np.ndarray,
    radius: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The segment of the line through ``point`` (R, 2) with ``normal`` that lies in the disc
    and in the earlier half-planes (R, i, 2): direction, t_low, t_high and feasibility."""
    direction = _perp(normal)
    t_mid = -_dot(point, direction)
    disc = t_mid**2 - _dot(point, point) + radius**2
    half = np.sqrt(np.maximum(disc, 0.0))
    denom = _dot(prev_normals, direction[:, None, :])
    num = _dot(prev_normals, prev_points - point[:, None, :])
    parallel = np.abs(denom) <= _PARALLEL_EPS
    bound = num / np.where(parallel, 1.0, denom)
    t_low = np.maximum(
        t_mid - half,
        np.max(np.where(denom > _PARALLEL_EPS, bound, -np.inf), axis=1, initial=-np.inf),
    )
    t_high = np.minimum(
        t_mid + half,
        np.min(np.where(denom < -_PARALLEL_EPS, bound, np.inf), axis=1, initial=np.inf),
    )
    # A parallel earlier line either contains this whole line in its half-plane or none of it.
    feasible = (disc >= 0.0) & ~np.any(parallel & (num > 0.0), axis=1) & (t_low <= t_high)
    return direction, t_low, t_high, feasible


def _linear_program_2d(
    points: np.ndarray,
    normals: np.ndarray,
    radius: np.ndarray,
    target: np.ndarray,
    maximize_along: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Incremental 2-D program over half-planes (S, K, 2) and the disc |x| <= radius (S,).

    Objective: closest to ``target`` (S, 2), or, with ``maximize_along``, furthest along the
    unit vector ``target``. A zero normal is an absent constraint. Returns the solution and,
    per row, the index of the first constraint that made it infeasible (K when none did);
    a failed row keeps the optimum of the constraints before that one.
    """
    count = points.shape[1]
    if maximize_along:
        x = target * radius[:, None]
    else:
        speed = np.sqrt(_dot(target, target))
        x = target * np.minimum(1.0, radius / np.where(speed > 0.0, speed, 1.0))[:, None]
    failed_at = np.full(points.shape[0], count)
    for i in range(count):
        # If the optimum so far satisfies constraint i it stays optimal; otherwise the new
        # optimum lies on line i, which reduces the step to a 1-D program on that line.
        rows = np.flatnonzero((failed_at == count) & (_dot(x - points[:, i], normals[:, i]) < 0.0))
        if rows.size == 0:
            continue
        point = points[rows, i]
        direction, t_low, t_high, feasible = _line_interval(
            point, normals[rows, i], points[rows, :i], normals[rows, :i], radius[rows]
        )
        goal = target[rows]
        if maximize_along:
            t = np.where(_dot(goal, direction) > 0.0, t_high, t_low)
        else:
            t = np.clip(_dot(goal - point, direction), t_low, t_high)
        x[rows[feasible]] = (point + t[:, None] * direction)[feasible]
        failed_at[rows[~feasible]] = i
    return x, failed_at


def _linear_program_3d(
    points: np.ndarray,
    normals: np.ndarray,
    present: np.ndarray,
    x: np.ndarray,
    failed_at: np.ndarray,
    radius: np.ndarray,
) -> np.ndarray:
    """Minimise the largest violation max_k (point_k - x) . normal_k over the speed disc.

    Incremental in the third coordinate d (the violation): ``x`` satisfies all constraints
    before ``failed_at`` (d = 0). When constraint i is violated by more than d, the new optimum
    makes it the most violated one, so it minimises i's violation subject to every earlier
    constraint being violated no more than i, a 2-D program over the bisecting lines.
    """
    x = x.copy()
    violation = np.zeros(x.shape[0])
    for i in range(points.shape[1]):
        rows = np.flatnonzero(
            (failed_at <= i) & (_dot(points[:, i] - x, normals[:, i]) > violation)
        )
        if rows.size == 0:
            continue
        normal, point = normals[rows, i], points[rows, i]
        # (point_j - x) . n_j <= (point_i - x) . n_i  <=>  (n_j - n_i) . x >= c.
        diff = normals[rows, :i] - normal[:, None, :]
        offset = _dot(normals[rows, :i], points[rows, :i]) - _dot(normal, point)[:, None]
        diff_len = np.sqrt(_dot(diff, diff))
        # Equal normals give no line: such a constraint cannot be violated more than i here,
        # since the current x violates it by at most d < violation of i.
        use = present[rows, :i] & (diff_len > _PARALLEL_EPS)
        safe_len = np.where(use, diff_len, 1.0)
        proj_normals = np.where(use[..., None], diff / safe_len[..., None], 0.0)
        proj_points = proj_normals * (offset / safe_len)[..., None]
        candidate, failed = _linear_program_2d(
            proj_points, proj_normals, radius[rows], normal, maximize_along=True
        )
        # The current x is feasible for the projected program, so a failure can only be
        # rounding; keeping x is then the right answer to within that rounding.
        solved = failed == i
        x[rows[solved]] = candidate[solved]
        violation[rows] = _dot(point - x[rows], normal)
    return x


def orca_velocities(
    positions: np.ndarray,
    velocities: np.ndarray,
    radii: np.ndarray,
    preferred_velocities: np.ndarray,
    max_speeds: np.ndarray,
    active: np.ndarray,
    time_horizon: float,
    time_step: float,
) -> np.ndarray:
    """New velocities (E, J, 2) of E independent worlds of J disc agents under ORCA.

    ``positions``, ``velocities`` and ``preferred_velocities`` are (E, J, 2); ``radii``,
    ``max_speeds`` and ``active`` broadcast to (E, J). Inactive agents are not avoided and get
    zero velocity. ``time_horizon`` is tau; ``time_step`` replaces it for pairs that already
    overlap.
    """
    if time_horizon <= 0.0 or time_step <= 0.0:
        raise ValueError("time_horizon and time_step must be positive")
    positions = np.asarray(positions, dtype=np.float64)
    velocities = np.asarray(velocities, dtype=np.float64)
    preferred = np.asarray(preferred_velocities, dtype=np.float64)
    worlds, count = positions.shape[:2]
    radii = np.broadcast_to(np.asarray(radii, dtype=np.float64), (worlds, count))
    max_speeds = np.broadcast_to(np.asarray(max_speeds, dtype=np.float64), (worlds, count))
    active = np.broadcast_to(np.asarray(active, dtype=bool), (worlds, count))

    points, normals = _half_planes(positions, velocities, radii, time_horizon, time_step)
    present = active[:, :, None] & active[:, None, :] & ~np.eye(count, dtype=bool)
    points = np.where(present[..., None], points, 0.0).reshape(worlds * count, count, 2)
    normals = np.where(present[..., None], normals, 0.0).reshape(worlds * count, count, 2)
    present = present.reshape(worlds * count, count)
    radius = max_speeds.reshape(-1)

    x, failed_at = _linear_program_2d(
        points, normals, radius, preferred.reshape(-1, 2), maximize_along=False
    )
    infeasible = np.flatnonzero(failed_at < count)
    if infeasible.size:
        x[infeasible] = _linear_program_3d(
            points[infeasible],
            normals[infeasible],
            present[infeasible],
            x[infeasible],
            failed_at[infeasible],
            radius[infeasible],
        )
    return np.where(active[..., None], x.reshape(worlds, count, 2), 0.0)


def preferred_velocity_toward(
    positions: np.ndarray,
    destinations: np.ndarray,
    max_speeds: np.ndarray,
    time_step: float,
) -> np.ndarray:
    """Velocity (..., 2) straight to ``destinations`` at max speed, slowed to land on it in one
    ``time_step`` rather than overshoot; zero at the destination."""
    offset = np.asarray(destinations, dtype=np.float64) - np.asarray(positions, dtype=np.float64)
    distance = np.sqrt(_dot(offset, offset))
    speed = np.minimum(np.asarray(max_speeds, dtype=np.float64), distance / time_step)
    return _safe_unit(offset, distance) * speed[..., None]
