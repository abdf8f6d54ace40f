# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True
# cython: initializedcheck=False
"""What a UAV's reports become on board, compiled: the SINR map's input features at each
report (``nearby_gbs_features``) and the spot filter's choice of the reports to upload
(``keep_spots``). An agent runs both on its ten reports at every step, where numpy's cost per
call is the whole cost. The numpy functions of ``planning.measuring`` are the reference: the
same float64 operations in the same order (libm's ``hypot``, which numpy calls too), so the
same GBSs are chosen and the same reports kept; the angles come from libm's ``atan2``, which
numpy replaces by its own vector code on some CPUs, so a feature may differ from the
reference's by one float32 rounding step."""

cdef extern from *:
    """
    #ifndef COMPILED_SOURCE_DIGEST
    #define COMPILED_SOURCE_DIGEST ""
    #endif
    """
    const char *COMPILED_SOURCE_DIGEST

from libc.math cimport atan2, hypot
from libc.stdint cimport int64_t, uint8_t
from libc.stdlib cimport free, malloc

SOURCE_DIGEST = COMPILED_SOURCE_DIGEST.decode()

# Slack on the candidates' reach (m): rounding must not drop a GBS on the boundary.
cdef double CANDIDATE_SLACK_M = 1e-3


cdef void insert_nearest(double distance, Py_ssize_t index, double *best, Py_ssize_t *chosen,
                         Py_ssize_t *held, Py_ssize_t wanted) noexcept nogil:
    """Keep the ``wanted`` smallest distances seen, nearest first; ties in the order seen (the
    GBSs are offered in index order, so ties keep the lower index first)."""
    cdef Py_ssize_t place
    if held[0] == wanted and not distance < best[wanted - 1]:
        return
    place = held[0] if held[0] < wanted else wanted - 1
    while place > 0 and best[place - 1] > distance:
        best[place] = best[place - 1]
        chosen[place] = chosen[place - 1]
        place -= 1
    best[place] = distance
    chosen[place] = index
    if held[0] < wanted:
        held[0] += 1


cdef Py_ssize_t gather_candidates(const double[:, ::1] xy, const double[:, ::1] gbs_xy,
                                  Py_ssize_t nearby, Py_ssize_t *candidates,
                                  double *scratch, Py_ssize_t *scratch_index) noexcept nogil:
    """The GBSs, ascending, that can be among the ``nearby`` nearest of some point of ``xy``:
    all of them, but for a compact block of points on a large layout only those within the
    centre's ``nearby``-th distance plus the block's diameter (the reference's rule)."""
    cdef Py_ssize_t count = xy.shape[0], gbs_count = gbs_xy.shape[0], i, g, taken = 0, held = 0
    cdef double low_x, low_y, high_x, high_y, centre_x, centre_y, reach, kth
    if gbs_count <= 2 * nearby or count == 0:
        for g in range(gbs_count):
            candidates[g] = g
        return gbs_count
    low_x = high_x = xy[0, 0]
    low_y = high_y = xy[0, 1]
    for i in range(1, count):
        low_x = min(low_x, xy[i, 0])
        high_x = max(high_x, xy[i, 0])
        low_y = min(low_y, xy[i, 1])
        high_y = max(high_y, xy[i, 1])
    centre_x, centre_y = (low_x + high_x) / 2, (low_y + high_y) / 2
    reach = hypot(high_x - low_x, high_y - low_y) / 2
    for g in range(gbs_count):
        insert_nearest(hypot(gbs_xy[g, 0] - centre_x, gbs_xy[g, 1] - centre_y), g, scratch,
                       scratch_index, &held, nearby)
    kth = scratch[nearby - 1]
    for g in range(gbs_count):
        if hypot(gbs_xy[g, 0] - centre_x, gbs_xy[g, 1] - centre_y) <= (
                kth + 2 * reach + CANDIDATE_SLACK_M):
            candidates[taken] = g
            taken += 1
    return taken


def nearby_gbs_features(const double[:, ::1] xy, const double[:, ::1] gbs_xy,
                        const int64_t[::1] gbs_channels, Py_ssize_t nearby, double altitude,
                        double gbs_height, bint nearest_position, float[:, ::1] features):
    """``features[i]`` for point ``xy[i]``: per GBS of the ``nearby`` nearest, nearest first,
    [dx, dy, distance, elevation, azimuth] and, where ``gbs_channels`` is not empty, whether
    it shares the nearest GBS's channel; then, with ``nearest_position``, the nearest GBS's
    position."""
    cdef Py_ssize_t count = xy.shape[0], gbs_count = gbs_xy.shape[0]
    cdef bint channels = gbs_channels.shape[0] > 0
    cdef Py_ssize_t per_gbs = 5 + channels, i, k, c, g, candidate_count, held
    cdef double x, y, dx, dy, distance, rise = gbs_height - altitude
    cdef float *row
    if not 0 < nearby <= gbs_count:
        raise ValueError(f"{nearby} nearby GBSs of {gbs_count}")
    if channels and gbs_channels.shape[0] != gbs_count:
        raise ValueError(f"{gbs_channels.shape[0]} channels for {gbs_count} GBSs")
    if features.shape[0] != count or features.shape[1] != per_gbs * nearby + 2 * nearest_position:
        raise ValueError(f"features of shape ({features.shape[0]}, {features.shape[1]}) for "
                         f"{count} points")
    cdef Py_ssize_t *candidates = <Py_ssize_t *> malloc(gbs_count * sizeof(Py_ssize_t))
    cdef Py_ssize_t *chosen = <Py_ssize_t *> malloc(gbs_count * sizeof(Py_ssize_t))
    cdef double *best = <double *> malloc(gbs_count * sizeof(double))
    if candidates == NULL or chosen == NULL or best == NULL:
        free(candidates)
        free(chosen)
        free(best)
        raise MemoryError()
    with nogil:
        candidate_count = gather_candidates(xy, gbs_xy, nearby, candidates, best, chosen)
        for i in range(count):
            x, y = xy[i, 0], xy[i, 1]
            held = 0
            for c in range(candidate_count):
                g = candidates[c]
                insert_nearest(hypot(gbs_xy[g, 0] - x, gbs_xy[g, 1] - y), g, best, chosen,
                               &held, nearby)
            row = &features[i, 0]
            for k in range(nearby):
                g = chosen[k]
                dx, dy, distance = gbs_xy[g, 0] - x, gbs_xy[g, 1] - y, best[k]
                row[0], row[1], row[2] = <float> dx, <float> dy, <float> distance
                row[3], row[4] = <float> atan2(rise, distance), <float> atan2(dy, dx)
                if channels:
                    row[5] = 1.0 if gbs_channels[g] == gbs_channels[chosen[0]] else 0.0
                row += per_gbs
            if nearest_position:
                row[0], row[1] = <float> gbs_xy[chosen[0], 0], <float> gbs_xy[chosen[0], 1]
    free(candidates)
    free(chosen)
    free(best)


def keep_spots(double[:, ::1] last_xy, int64_t[::1] last_level, const int64_t[::1] uavs,
               const double[:, :, ::1] xy, const int64_t[:, ::1] levels, double spacing,
               uint8_t[:, ::1] kept):
    """``kept[i, s]``: whether UAV ``uavs[i]`` keeps its report ``s`` at ``xy[i, s]`` of level
    ``levels[i, s]`` (taken in that order): at least ``spacing`` from its last kept report
    (``last_xy``), or of another level than the report before (the last kept one's, since only
    a report of that level is ever dropped). ``last_xy`` and ``last_level`` move on with each
    UAV's reports."""
    cdef Py_ssize_t rows = uavs.shape[0], reports = xy.shape[1], i, s, uav
    cdef double here_x, here_y, kept_x, kept_y
    cdef int64_t level
    if (xy.shape[0] != rows or levels.shape[0] != rows or levels.shape[1] != reports
            or kept.shape[0] != rows or kept.shape[1] != reports or xy.shape[2] != 2):
        raise ValueError("reports, levels or kept of different shapes")
    for i in range(rows):
        uav = uavs[i]
        if not 0 <= uav < last_xy.shape[0]:
            raise IndexError(f"uav {uav} of {last_xy.shape[0]}")
    with nogil:
        for i in range(rows):
            uav = uavs[i]
            kept_x, kept_y, level = last_xy[uav, 0], last_xy[uav, 1], last_level[uav]
            for s in range(reports):
                here_x, here_y = xy[i, s, 0], xy[i, s, 1]
                if levels[i, s] != level or hypot(here_x - kept_x, here_y - kept_y) >= spacing:
                    kept[i, s] = 1
                    kept_x, kept_y = here_x, here_y
                else:
                    kept[i, s] = 0
                level = levels[i, s]
            if reports > 0:
                last_xy[uav, 0], last_xy[uav, 1], last_level[uav] = kept_x, kept_y, level
