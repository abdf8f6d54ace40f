# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True
# cython: initializedcheck=False
"""The lookahead of ``planning.reference.LookaheadPolicy`` for one UAV at a time, compiled: its
nearest others, candidate moves, the others' predicted motion (constant velocity or
reciprocal), gaps and rewards, safe cells, joint-state features, the value network's forward
(float32), the risk and escape checks and the deeper search. ``planning.reference`` is the
reference: every step here follows its arithmetic, in the same order where it can.

A row's decision reads no Python object: the maps come as plain arrays (a level raster per
row, a route field per row), the network as its float32 tensors.
"""

from libc.math cimport INFINITY, M_PI, atan2, copysign, cos, fmod, hypot, isfinite
from libc.math cimport rint, sin, sqrt, tanhf
from libc.stdint cimport int8_t, int64_t, uint8_t
from libc.stdlib cimport calloc, free


cdef extern from "_vector_math.h" nogil:
    void atan2_many(const double *y, const double *x, double *out, int n)
    void hypot_many(const double *x, const double *y, double *out, int n)


cdef extern from "_dense.h" nogil:
    enum: DENSE_BLOCK
    void dense_standardize(const float *states, long stride, int features, const float *mean,
                           const float *std, float *out)
    void dense_layer(const float *weight, const float *bias, int inputs, int outputs,
                     const float *inp, float *out, int relu)


# The build passes the sha256 of the compiled sources: planning.compiled compares it with the
# sources beside it, so a module left from older source is refused, not run.
cdef extern from *:
    """
    #ifndef COMPILED_SOURCE_DIGEST
    #define COMPILED_SOURCE_DIGEST ""
    #endif
    """
    const char *COMPILED_SOURCE_DIGEST

SOURCE_DIGEST = COMPILED_SOURCE_DIGEST.decode()

cdef enum:
    MAX_WATCHED = 16  # shared.scenario bounds observed_uavs so
    MAX_LAYERS = 8
    MAX_DEPTH = 3  # shared.scenario bounds lookahead_depth so
    MAX_TURNS = 64  # distinct heading changes: shared.scenario's 63 heading choices and hovering

# How the others' next velocity is predicted (planning.reference.LookaheadPolicy.others_velocity).
cdef enum OthersModel:
    CONSTANT_VELOCITY = 0
    RECIPROCAL = 1


cdef struct Scene:
    # One UAV and the others it watches, present ones only, nearest first.
    double x, y, vx, vy, heading, dest_x, dest_y, radius, max_speed
    int64_t level, below, step
    int count
    double ox[MAX_WATCHED]
    double oy[MAX_WATCHED]
    double ovx[MAX_WATCHED]
    double ovy[MAX_WATCHED]
    double orad[MAX_WATCHED]


cdef struct Step:
    # Every candidate action of one scene, one step ahead (arrays of the actions).
    double *heading
    double *vx
    double *vy
    double *x
    double *y
    double *reward
    double *score
    int64_t *level
    int64_t *below
    uint8_t *terminal
    float *states  # feature-major: feature i of action a at states[i * stride + a]
    Py_ssize_t stride  # the actions rounded up to whole blocks of the forward
    # The features' angles, taken together once every action's are known: for action a, the
    # direction to the goal, then to each other, at a * (others + 1) + ...
    double *angle_y
    double *angle_x
    double *angle
    # Each action's closest approach to the destination, its offset and length.
    double *arrival_x
    double *arrival_y
    double *arrival
    # The others after the step, and the velocity that took them there.
    double ox[MAX_WATCHED]
    double oy[MAX_WATCHED]
    double ovx[MAX_WATCHED]
    double ovy[MAX_WATCHED]


cdef struct MapView:
    # One row's radio map: its level raster and its route field.
    const int8_t *levels
    Py_ssize_t rows, cols
    double x0, y0, spacing
    const float *field
    Py_ssize_t field_rows, field_cols
    double field_x0, field_y0, cell, offset
    bint route_missing  # the field was read where it is not computed


cdef inline double wrap_angle(double angle) nogil:
    # numpy's remainder: the sign of the divisor, as shared.kinematics.wrap_angle computes.
    # Within one period of zero fmod returns its argument exactly: skip its cost there.
    cdef double period = 2.0 * M_PI
    cdef double shifted = angle + M_PI
    cdef double mod = shifted if -period < shifted < period else fmod(shifted, period)
    if mod != 0.0:
        if (mod < 0.0) != (period < 0.0):
            mod += period
    else:
        mod = copysign(0.0, period)
    return mod - M_PI


cdef inline double clamp(double value, double low, double high) nogil:
    return min(max(value, low), high)


cdef inline void closest_offset(double px, double py, double vx, double vy, double duration,
                                double *x, double *y) noexcept nogil:
    # Where the closest approach's offset lies: its length is closest_approach.
    cdef double speed_sq = vx * vx + vy * vy
    cdef double toward = -(px * vx + py * vy)
    cdef double time = toward / speed_sq if speed_sq > 0.0 else 0.0
    time = clamp(time, 0.0, duration)
    x[0], y[0] = px + vx * time, py + vy * time


cdef inline double closest_approach(double px, double py, double vx, double vy,
                                    double duration) noexcept nogil:
    cdef double x, y
    closest_offset(px, py, vx, vy, duration, &x, &y)
    return hypot(x, y)


cdef inline int64_t level_at(const MapView *m, double x, double y) nogil:
    cdef Py_ssize_t col = <Py_ssize_t>rint((x - m.x0) / m.spacing)
    cdef Py_ssize_t row = <Py_ssize_t>rint((y - m.y0) / m.spacing)
    col = min(max(col, 0), m.cols - 1)
    row = min(max(row, 0), m.rows - 1)
    return m.levels[row * m.cols + col]


cdef inline double route_distance(MapView *m, double x, double y) nogil:
    # planning.routes.RouteGrid._read, then the offset RouteGrid.distance adds.
    cdef double fx = clamp((x - m.field_x0) / m.cell, 0, m.field_cols - 1)
    cdef double fy = clamp((y - m.field_y0) / m.cell, 0, m.field_rows - 1)
    # fx and fy are clamped to 0 or more: truncation is their floor, without a call to libm.
    cdef Py_ssize_t c0 = min(<Py_ssize_t>fx, m.field_cols - 2)
    cdef Py_ssize_t r0 = min(<Py_ssize_t>fy, m.field_rows - 2)
    cdef double tx = fx - c0, ty = fy - r0
    cdef double sx = 1 - tx, sy = 1 - ty
    cdef const float *corner = m.field + r0 * m.field_cols + c0
    cdef double value = (<double>corner[0] * sx * sy + <double>corner[1] * tx * sy
                         + <double>corner[m.field_cols] * sx * ty
                         + <double>corner[m.field_cols + 1] * tx * ty)
    if not isfinite(value):
        m.route_missing = True
    return value + m.offset


cdef class Kernel:
    """The lookahead's settings and value network, read by every decision."""

    cdef int actions, distinct_turns, watched, features, depth, others_model, beam
    cdef bint safe_cells, memory, route
    cdef double dt, gamma, tolerance, top_speed, discomfort, collision, arrival, step_reward
    cdef double lost_reward, margin_m, closing_tolerance, gap_slack, clearance, horizon
    cdef double absent_distance, absent_azimuth
    cdef int64_t lost_after, check_every, weak
    cdef float value_scale
    cdef const double[::1] speeds
    cdef const double[::1] turns
    cdef const int64_t[::1] turn_of_action
    cdef const double[::1] by_level
    cdef const float[::1] mean
    cdef const float[::1] std
    cdef int layers
    cdef int widths[MAX_LAYERS + 1]
    cdef const float *weights[MAX_LAYERS]
    cdef const float *biases[MAX_LAYERS]
    cdef int widest
    cdef object tensors  # keeps the arrays the pointers above read alive

    def __init__(self, settings, tensors):
        """``settings``: a mapping of the lookahead's settings (planning.lookahead builds it
        from a planning.reference.LookaheadPolicy); ``tensors``: (mean, std, [(weight, bias)])
        as planning.networks.Network.layers gives them, float32 and C-contiguous."""
        self.actions = len(settings["speeds"])
        self.speeds = settings["speeds"]
        self.turns = settings["distinct_turns"]
        self.distinct_turns = len(settings["distinct_turns"])
        if self.distinct_turns > MAX_TURNS:
            raise ValueError(f"at most {MAX_TURNS} distinct heading changes")
        self.turn_of_action = settings["turn_of_action"]
        self.by_level = settings["connectivity_by_level"]
        self.watched = settings["observed_uavs"]
        if self.watched > MAX_WATCHED:
            raise ValueError(f"at most {MAX_WATCHED} observed UAVs")
        self.depth = settings["depth"]
        if not 1 <= self.depth <= MAX_DEPTH:
            raise ValueError(f"lookahead depth {self.depth} outside 1..{MAX_DEPTH}")
        self.others_model = (RECIPROCAL if settings["others_model"] == "reciprocal"
                             else CONSTANT_VELOCITY)
        self.beam = settings["beam"]
        self.safe_cells = settings["safe_cells"]
        self.memory = settings["disconnection_memory"]
        self.route = settings["route_distance"]
        self.dt = settings["dt"]
        self.gamma = settings["gamma"]
        self.tolerance = settings["arrival_tolerance"]
        self.top_speed = settings["top_speed"]
        self.discomfort = settings["discomfort"]
        self.collision = settings["collision"]
        self.arrival = settings["arrival"]
        self.step_reward = settings["step_reward"]
        self.lost_reward = settings["disconnection_reward"]
        self.margin_m = settings["collision_margin"]
        self.closing_tolerance = settings["closing_tolerance"]
        self.gap_slack = settings["gap_slack"]
        self.clearance = settings["cell_clearance"]
        self.horizon = settings["orca_time_horizon"]
        self.absent_distance = settings["absent_distance"]
        self.absent_azimuth = atan2(0.0, -self.absent_distance)
        self.lost_after = settings["disconnection_limit"]
        self.check_every = settings["check_every"]
        self.weak = settings["weak_levels"]
        self.value_scale = settings["value_scale"]
        self.features = settings["features"]

        mean, std, layers = tensors
        self.tensors = tensors
        self.mean, self.std = mean, std
        if len(layers) > MAX_LAYERS or len(mean) != self.features:
            raise ValueError("the value network does not fit the lookahead")
        self.layers = len(layers)
        self.widths[0] = len(mean)
        self.widest = len(mean)
        cdef const float[:, ::1] weight
        cdef const float[::1] bias
        for index, (weight, bias) in enumerate(layers):
            if weight.shape[1] != self.widths[index] or bias.shape[0] != weight.shape[0]:
                raise ValueError("the value network's layers do not chain")
            self.weights[index] = &weight[0, 0]
            self.biases[index] = &bias[0]
            self.widths[index + 1] = weight.shape[0]
            self.widest = max(self.widest, weight.shape[0])
        if self.widths[self.layers] != 1:
            raise ValueError("a value network has one output")

    def decide(self, const double[:, ::1] position, const double[:, ::1] velocity,
               const double[::1] heading, const double[:, ::1] destination,
               const double[::1] radius, const double[::1] max_speed,
               const int64_t[::1] level, const int64_t[::1] below_steps,
               const int64_t[::1] step, const double[:, :, ::1] others_position,
               const double[:, :, ::1] others_velocity, const double[:, ::1] others_radius,
               const uint8_t[:, ::1] others_present, const int8_t[:, :, ::1] levels,
               const int64_t[::1] raster_of_row, double x0, double y0, double spacing,
               list stores, const int64_t[::1] slots, const double[::1] offset,
               double field_x0, double field_y0, double cell,
               int64_t[::1] action, double[::1] speed, double[::1] new_heading,
               double[::1] value, double[:, ::1] score, uint8_t[:, ::1] allowed,
               uint8_t[::1] route_missing):
        """Decide every row (one UAV each, as shared.observation.Observation holds them) into
        ``action``, ``speed``, ``new_heading`` and ``value`` (N,), ``score`` and ``allowed``
        (N, A); ``route_missing`` marks the rows that read a route field beyond where it is
        computed (their decision must be taken again on the whole field)."""
        cdef Py_ssize_t n = position.shape[0], others = others_position.shape[1]
        cdef Py_ssize_t row, k
        cdef const float *field_base[64]
        cdef const float[:, :, ::1] store
        cdef Py_ssize_t field_rows = 0, field_cols = 0
        if len(stores) > 64:
            raise ValueError("at most 64 rasters in one map")
        if self.route:
            for k, store in enumerate(stores):
                field_rows, field_cols = store.shape[1], store.shape[2]
                field_base[k] = &store[0, 0, 0] if store.shape[0] else NULL
        cdef Workspace work = Workspace(self)
        cdef Scene scene
        cdef MapView view
        view.rows, view.cols = levels.shape[1], levels.shape[2]
        view.x0, view.y0, view.spacing = x0, y0, spacing
        view.field_rows, view.field_cols = field_rows, field_cols
        view.field_x0, view.field_y0, view.cell = field_x0, field_y0, cell
        view.field = NULL
        cdef int64_t chosen
        # Each row alone, free of Python objects: callers may decide a batch's halves on two
        # threads at once (planning.compiled.on_two_cores).
        with nogil:
            for row in range(n):
                view.levels = &levels[raster_of_row[row], 0, 0]
                if self.route:
                    view.field = (field_base[raster_of_row[row]]
                                  + slots[row] * field_rows * field_cols)
                    view.offset = offset[row]
                view.route_missing = False
                scene.x, scene.y = position[row, 0], position[row, 1]
                scene.vx, scene.vy = velocity[row, 0], velocity[row, 1]
                scene.heading = heading[row]
                scene.dest_x, scene.dest_y = destination[row, 0], destination[row, 1]
                scene.radius, scene.max_speed = radius[row], max_speed[row]
                scene.level, scene.below, scene.step = level[row], below_steps[row], step[row]
                watch_nearest(self, &scene, &others_position[row, 0, 0] if others else NULL,
                              &others_velocity[row, 0, 0] if others else NULL,
                              &others_radius[row, 0] if others else NULL,
                              &others_present[row, 0] if others else NULL, others)
                chosen = decide_row(self, work, &scene, &view,
                                    &others_position[row, 0, 0] if others else NULL,
                                    &others_present[row, 0] if others else NULL, others,
                                    &score[row, 0], &allowed[row, 0])
                action[row] = chosen
                speed[row] = self.speeds[chosen]
                new_heading[row] = wrap_angle(scene.heading
                                              + self.turns[self.turn_of_action[chosen]])
                value[row] = score[row, chosen]
                route_missing[row] = view.route_missing


cdef class Workspace:
    """Scratch memory of one call: a Step per depth, the forward's blocks."""

    cdef Step steps[MAX_DEPTH]
    cdef double *values
    cdef double *deep
    cdef uint8_t *searched
    cdef uint8_t *escape
    cdef float *block_in
    cdef float *block_out
    cdef void *memory

    def __cinit__(self, Kernel kernel):
        cdef Py_ssize_t a = kernel.actions
        cdef Py_ssize_t padded = (a + DENSE_BLOCK - 1) // DENSE_BLOCK * DENSE_BLOCK
        cdef Py_ssize_t angles = a * (kernel.watched + 1)
        cdef Py_ssize_t per_step = (10 * sizeof(double) + 2 * sizeof(int64_t) + 1) * a \
            + sizeof(float) * padded * kernel.features + 3 * sizeof(double) * angles
        cdef Py_ssize_t total = (kernel.depth * per_step + 2 * sizeof(double) * padded + 2 * a
                                 + 2 * sizeof(float) * DENSE_BLOCK * kernel.widest + 64 * 16)
        self.memory = calloc(1, total)
        if self.memory == NULL:
            raise MemoryError()
        cdef char *cursor = <char *>self.memory
        cdef int d
        for d in range(kernel.depth):
            # float and double arrays first, each a multiple of 8 bytes: all stay aligned.
            # Zeros in the padding: the forward computes them along, and ignores them.
            self.steps[d].states = <float *>cursor
            self.steps[d].stride = padded
            cursor += sizeof(float) * padded * kernel.features + 8
            self.steps[d].angle_y = <double *>cursor; cursor += sizeof(double) * angles
            self.steps[d].angle_x = <double *>cursor; cursor += sizeof(double) * angles
            self.steps[d].angle = <double *>cursor; cursor += sizeof(double) * angles
            self.steps[d].arrival_x = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].arrival_y = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].arrival = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].heading = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].vx = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].vy = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].x = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].y = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].reward = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].score = <double *>cursor; cursor += sizeof(double) * a
            self.steps[d].level = <int64_t *>cursor; cursor += sizeof(int64_t) * a
            self.steps[d].below = <int64_t *>cursor; cursor += sizeof(int64_t) * a
            self.steps[d].terminal = <uint8_t *>cursor; cursor += a
            cursor = <char *>((<size_t>cursor + 63) & ~(<size_t>63))
        self.values = <double *>cursor; cursor += sizeof(double) * padded
        self.deep = <double *>cursor; cursor += sizeof(double) * padded
        self.block_in = <float *>cursor; cursor += sizeof(float) * DENSE_BLOCK * kernel.widest
        self.block_out = <float *>cursor; cursor += sizeof(float) * DENSE_BLOCK * kernel.widest
        self.searched = <uint8_t *>cursor; cursor += a
        self.escape = <uint8_t *>cursor

    def __dealloc__(self):
        free(self.memory)


cdef void watch_nearest(Kernel k, Scene *scene, const double *position,
                        const double *velocity, const double *radius, const uint8_t *present,
                        Py_ssize_t others) noexcept nogil:
    # Observation.nearest_neighbours: the J_n nearest present others, nearest first, ties
    # in the order given (a stable sort).
    cdef double distance[MAX_WATCHED]
    cdef int picked[MAX_WATCHED]
    cdef int count = 0, slot
    cdef Py_ssize_t o
    cdef double d
    if k.watched == 0:
        scene.count = 0
        return
    for o in range(others):
        if not present[o]:
            continue
        d = hypot(position[2 * o] - scene.x, position[2 * o + 1] - scene.y)
        if count == k.watched and not d < distance[count - 1]:
            continue
        slot = count if count < k.watched else count - 1
        while slot > 0 and d < distance[slot - 1]:
            distance[slot] = distance[slot - 1]
            picked[slot] = picked[slot - 1]
            slot -= 1
        distance[slot] = d
        picked[slot] = <int>o
        if count < k.watched:
            count += 1
    scene.count = count
    for slot in range(count):
        o = picked[slot]
        scene.ox[slot], scene.oy[slot] = position[2 * o], position[2 * o + 1]
        scene.ovx[slot], scene.ovy[slot] = velocity[2 * o], velocity[2 * o + 1]
        scene.orad[slot] = radius[o]


cdef inline double proximity(Kernel k, double gap) noexcept nogil:
    # shared.rewards.RewardModel.proximity
    cdef double share
    if gap <= 0:
        return k.collision
    if k.discomfort > 0:
        share = clamp(1.0 - gap / k.discomfort, 0.0, 1.0)
    else:
        share = 0.0
    return k.collision * share


cdef void reciprocal_velocity(Kernel k, const Scene *s, int o, double *vx,
                              double *vy) noexcept nogil:
    # planning.orca.orca_velocities for the two-agent world of the observer and the other: the
    # other's half-plane of ORCA^tau (planning.orca._half_planes), then its velocity closest to
    # its own inside that half-plane and its speed disc (the one-constraint programs of
    # _linear_program_2d and, when the half-plane misses the disc, _linear_program_3d).
    cdef double px = s.x - s.ox[o], py = s.y - s.oy[o]  # the observer seen from the other
    cdef double rvx = s.ovx[o] - s.vx, rvy = s.ovy[o] - s.vy
    cdef double combined = s.orad[o] + s.radius
    cdef double dist_sq = px * px + py * py
    cdef bint apart = dist_sq > combined * combined
    cdef double nx, ny, ux, uy
    cdef double wx, wy, w_len, w_dot_p, w_safe, leg, dsq, lx, ly, along, dist, wc_len
    if apart:
        wx, wy = rvx - px / k.horizon, rvy - py / k.horizon
        w_len = sqrt(wx * wx + wy * wy)
        w_dot_p = wx * px + wy * py
        w_safe = w_len if w_len > 0.0 else 1.0
        if w_dot_p < 0.0 and w_dot_p * w_dot_p > combined * combined * (w_len * w_len):
            nx, ny = wx / w_safe, wy / w_safe
            ux, uy = (combined / k.horizon - w_len) * nx, (combined / k.horizon - w_len) * ny
        else:
            leg = sqrt(max(dist_sq - combined * combined, 0.0))
            dsq = dist_sq
            if px * wy - py * wx > 0.0:  # the left leg
                lx, ly = (px * leg - py * combined) / dsq, (px * combined + py * leg) / dsq
                nx, ny = -ly, lx
            else:
                lx, ly = (px * leg + py * combined) / dsq, (-px * combined + py * leg) / dsq
                nx, ny = ly, -lx
            along = rvx * lx + rvy * ly
            ux, uy = along * lx - rvx, along * ly - rvy
    else:
        wx, wy = rvx - px / k.dt, rvy - py / k.dt
        wc_len = sqrt(wx * wx + wy * wy)
        dist = sqrt(dist_sq)
        if wc_len > 0.0:
            nx, ny = wx / wc_len, wy / wc_len
        elif dist > 0.0:
            nx, ny = -(px / dist), -(py / dist)
        else:
            nx, ny = 1.0, 0.0  # coincident: the later agent of the pair is pushed along +x
        ux, uy = (combined / k.dt - wc_len) * nx, (combined / k.dt - wc_len) * ny
    cdef double point_x = s.ovx[o] + 0.5 * ux, point_y = s.ovy[o] + 0.5 * uy
    cdef double limit = s.max_speed  # the others' top speed is not observed: the UAV's own
    cdef double speed = sqrt(s.ovx[o] * s.ovx[o] + s.ovy[o] * s.ovy[o])
    cdef double scale = min(1.0, limit / (speed if speed > 0.0 else 1.0))
    cdef double x = s.ovx[o] * scale, y = s.ovy[o] * scale
    cdef double dx, dy, t_mid, disc, half, t
    if (x - point_x) * nx + (y - point_y) * ny < 0.0:
        dx, dy = -ny, nx
        t_mid = -(point_x * dx + point_y * dy)
        disc = t_mid * t_mid - (point_x * point_x + point_y * point_y) + limit * limit
        if disc >= 0.0:
            half = sqrt(disc)
            t = clamp((s.ovx[o] - point_x) * dx + (s.ovy[o] - point_y) * dy,
                      t_mid - half, t_mid + half)
            x, y = point_x + t * dx, point_y + t * dy
        else:
            x, y = nx * limit, ny * limit  # the least violation the disc allows
    vx[0], vy[0] = x, y


cdef void predict_others(Kernel k, const Scene *s, Step *st) noexcept nogil:
    # planning.reference.LookaheadPolicy.others_velocity: constant velocity, or a reciprocal ORCA
    # agent's half of the avoidance for the others on collision course within the horizon.
    cdef int o
    for o in range(s.count):
        st.ovx[o], st.ovy[o] = s.ovx[o], s.ovy[o]
        if k.others_model == RECIPROCAL and closest_approach(
                s.ox[o] - s.x, s.oy[o] - s.y, s.ovx[o] - s.vx, s.ovy[o] - s.vy,
                k.horizon) < s.radius + s.orad[o]:
            reciprocal_velocity(k, s, o, &st.ovx[o], &st.ovy[o])
        st.ox[o] = s.ox[o] + st.ovx[o] * k.dt
        st.oy[o] = s.oy[o] + st.ovy[o] * k.dt


cdef void write_features(Kernel k, const Scene *s, Step *st, int a, MapView *m) noexcept nogil:
    # planning.features.joint_state of action a's next state, in float64, rounded to float32.
    cdef float *f = st.states + a
    cdef Py_ssize_t stride = st.stride
    cdef double x = st.x[a], y = st.y[a], vx = st.vx[a], vy = st.vy[a]
    cdef double gx = s.dest_x - x, gy = s.dest_y - y
    # Distances that only a feature reads: sqrt is several times cheaper than hypot, and the
    # two differ in float64's last bits, far below the float32 the features are rounded to.
    cdef double goal = sqrt(gx * gx + gy * gy)
    cdef double c = 1.0, sn = 0.0
    if goal != 0.0:
        c, sn = gx / goal, gy / goal
    f[0] = vx * c + vy * sn
    f[1 * stride] = vy * c - vx * sn
    f[2 * stride] = goal
    f[3 * stride] = 0.0
    f[4 * stride] = goal
    f[5 * stride] = 0.0
    f[6 * stride] = s.radius
    f[7 * stride] = s.max_speed
    cdef double *toward_y = st.angle_y + a * (s.count + 1)
    cdef double *toward_x = st.angle_x + a * (s.count + 1)
    toward_y[0], toward_x[0] = sn, c  # the heading feature: see write_angles
    cdef int j, column
    cdef double rx, ry, px, py
    for j in range(k.watched):
        column = 9 + 6 * j
        if j >= s.count:  # an absent other: a still UAV far behind, the same for every move
            f[column * stride] = -k.absent_distance
            f[(column + 1) * stride] = 0.0
            f[(column + 2) * stride] = 0.0
            f[(column + 3) * stride] = 0.0
            f[(column + 4) * stride] = k.absent_distance
            f[(column + 5) * stride] = k.absent_azimuth
            continue
        rx, ry = st.ox[j] - x, st.oy[j] - y
        px, py = rx * c + ry * sn, ry * c - rx * sn
        f[column * stride] = px
        f[(column + 1) * stride] = py
        f[(column + 2) * stride] = st.ovx[j] * c + st.ovy[j] * sn
        f[(column + 3) * stride] = st.ovy[j] * c - st.ovx[j] * sn
        f[(column + 4) * stride] = sqrt(px * px + py * py)
        toward_y[j + 1], toward_x[j + 1] = py, px
    column = 9 + 6 * k.watched
    f[column * stride] = st.level[a]
    if k.memory:
        column += 1
        f[column * stride] = st.below[a]
    if k.route:
        f[(column + 1) * stride] = route_distance(m, x, y)


cdef void write_angles(Kernel k, const Scene *s, Step *st) noexcept nogil:
    # The features write_features left for here, taken together (shared/_vector_math.h): the
    # heading against the direction to the goal, and each present other's azimuth.
    cdef int per_action = s.count + 1, a, j
    atan2_many(st.angle_y, st.angle_x, st.angle, k.actions * per_action)
    for a in range(k.actions):
        st.states[8 * st.stride + a] = wrap_angle(st.heading[a] - st.angle[a * per_action])
        for j in range(s.count):
            st.states[(9 + 6 * j + 5) * st.stride + a] = st.angle[a * per_action + j + 1]


cdef void expand(Kernel k, const Scene *s, MapView *m, Step *st) noexcept nogil:
    # planning.reference.LookaheadPolicy.expand (with _margins and _gaps) for one scene. Its
    # rules of arrival and disconnection are the world's, shared.outcomes.arrivals and
    # shared.outcomes.disconnections, repeated here in C.
    cdef double margin[MAX_WATCHED]
    cdef uint8_t near[MAX_WATCHED]
    cdef double heading[MAX_TURNS]
    cdef double cosine[MAX_TURNS]
    cdef double sine[MAX_TURNS]
    cdef bint any_near = False, arrived, lost
    cdef int o, a, t
    cdef double rx, ry, reach, vx, vy, gap, reward
    predict_others(k, s, st)
    for o in range(s.count):
        rx, ry = s.ox[o] - s.x, s.oy[o] - s.y
        margin[o] = 0.0
        if k.margin_m != 0.0:
            margin[o] = clamp(sqrt(rx * rx + ry * ry) - s.radius - s.orad[o]
                              - k.closing_tolerance, 0.0, k.margin_m)
        reach = (k.top_speed + hypot(st.ovx[o], st.ovy[o])) * k.dt
        near[o] = (hypot(rx, ry) - reach - margin[o] - s.radius - s.orad[o]
                   < k.discomfort + k.gap_slack)
        any_near = any_near or near[o]
    for t in range(k.distinct_turns):
        heading[t] = wrap_angle(s.heading + k.turns[t])
        cosine[t], sine[t] = cos(heading[t]), sin(heading[t])
    cdef bint check_now = s.step % k.check_every == 0
    for a in range(k.actions):
        t = k.turn_of_action[a]
        vx, vy = k.speeds[a] * cosine[t], k.speeds[a] * sine[t]
        st.heading[a], st.vx[a], st.vy[a] = heading[t], vx, vy
        closest_offset(s.x - s.dest_x, s.y - s.dest_y, vx, vy, k.dt, &st.arrival_x[a],
                       &st.arrival_y[a])
    hypot_many(st.arrival_x, st.arrival_y, st.arrival, k.actions)
    for a in range(k.actions):
        vx, vy = st.vx[a], st.vy[a]
        arrived = st.arrival[a] <= k.tolerance
        if arrived:
            st.x[a], st.y[a] = s.dest_x, s.dest_y
        else:
            st.x[a], st.y[a] = s.x + vx * k.dt, s.y + vy * k.dt
        gap = INFINITY
        if any_near:
            for o in range(s.count):
                if near[o]:
                    gap = min(gap, closest_approach(
                        s.ox[o] - s.x, s.oy[o] - s.y, st.ovx[o] - vx, st.ovy[o] - vy, k.dt)
                        - s.radius - s.orad[o] - margin[o])
        st.level[a] = level_at(m, st.x[a], st.y[a])
        st.below[a] = s.below + 1 if st.level[a] == 0 else 0
        reward = (proximity(k, gap) + (k.by_level[st.level[a]] if check_now else 0.0)
                  + (k.arrival if arrived else 0.0) + k.step_reward)
        st.terminal[a] = arrived or gap <= 0
        if k.memory:
            lost = not arrived and gap > 0 and st.below[a] > k.lost_after
            if lost:
                st.terminal[a] = True
                reward = reward + k.lost_reward
        st.reward[a] = reward
        write_features(k, s, st, a, m)
    write_angles(k, s, st)


cdef void forward(Kernel k, Workspace w, const Step *st, Py_ssize_t n,
                  double *values) noexcept nogil:
    # planning.networks.ValueNetwork: standardization, the layers, tanh times the scale.
    cdef Py_ssize_t start, count, s
    cdef int layer
    cdef float *inputs
    cdef float *outputs
    cdef float *swap
    start = 0
    while start < n:
        count = min(DENSE_BLOCK, n - start)
        dense_standardize(st.states + start, st.stride, k.features, &k.mean[0], &k.std[0],
                          w.block_in)
        inputs, outputs = w.block_in, w.block_out
        for layer in range(k.layers):
            dense_layer(k.weights[layer], k.biases[layer], k.widths[layer],
                        k.widths[layer + 1], inputs, outputs, layer < k.layers - 1)
            swap = inputs
            inputs = outputs
            outputs = swap
        for s in range(count):
            values[start + s] = tanhf(inputs[s]) * k.value_scale
        start += DENSE_BLOCK


cdef void leaf_scores(Kernel k, Workspace w, Step *st, double *score) noexcept nogil:
    # R + gamma V(next state), nothing after a terminal action.
    forward(k, w, st, k.actions, w.values)
    cdef int a
    for a in range(k.actions):
        score[a] = st.reward[a] + k.gamma * (0.0 if st.terminal[a] else w.values[a])


cdef void deep_scores(Kernel k, Workspace w, const Scene *s, MapView *m, int index, int depth,
                      const uint8_t *searched, double *score) noexcept nogil:
    # planning.reference.LookaheadPolicy.deep_scores: w.steps[index] holds the expansion of s.
    cdef Step *st = &w.steps[index]
    if depth == 1:
        leaf_scores(k, w, st, score)
        return
    cdef Scene onward
    cdef Step *next_step = &w.steps[index + 1]
    cdef int a, b
    cdef double best
    for a in range(k.actions):
        best = 0.0
        if (searched == NULL or searched[a]) and not st.terminal[a]:
            onward = s[0]
            onward.x, onward.y, onward.vx, onward.vy = st.x[a], st.y[a], st.vx[a], st.vy[a]
            onward.heading, onward.level, onward.below = st.heading[a], st.level[a], st.below[a]
            onward.step = s.step + 1
            for b in range(s.count):
                onward.ox[b], onward.oy[b] = st.ox[b], st.oy[b]
                onward.ovx[b], onward.ovy[b] = st.ovx[b], st.ovy[b]
            expand(k, &onward, m, next_step)
            deep_scores(k, w, &onward, m, index + 1, depth - 1, NULL, next_step.score)
            best = -INFINITY
            for b in range(k.actions):
                best = max(best, next_step.score[b])
        score[a] = st.reward[a] + k.gamma * (0.0 if st.terminal[a] else best)


cdef bint escapes(Kernel k, Step *st, int a, MapView *m) noexcept nogil:
    # planning.reference.LookaheadPolicy.escapes for action a: after it, some next move lands on a
    # connected level (or it ends the mission, or lands on one itself).
    if st.terminal[a] or st.level[a] >= k.weak:
        return True
    cdef int t, b
    cdef double heading[MAX_TURNS]
    cdef double cosine[MAX_TURNS]
    cdef double sine[MAX_TURNS]
    for t in range(k.distinct_turns):
        heading[t] = wrap_angle(st.heading[a] + k.turns[t])
        cosine[t], sine[t] = cos(heading[t]), sin(heading[t])
    for b in range(k.actions):
        t = k.turn_of_action[b]
        if level_at(m, st.x[a] + k.speeds[b] * cosine[t] * k.dt,
                    st.y[a] + k.speeds[b] * sine[t] * k.dt) >= k.weak:
            return True
    return False


cdef void mark_beam(Kernel k, const double *score, const uint8_t *among,
                    uint8_t *marked) noexcept nogil:
    # The k.beam best finite scores (of the actions ``among`` marks, if given), ties to the
    # lower index: the head of a stable sort by descending score.
    cdef double last = INFINITY, value, best
    cdef int last_index = -1, pick, a, taken
    for taken in range(k.beam):
        pick = -1
        best = -INFINITY
        for a in range(k.actions):
            value = score[a] if among == NULL or among[a] else -INFINITY
            if value < last or (value == last and a > last_index):
                if pick < 0 or value > best:
                    pick, best = a, value
        if pick < 0 or not isfinite(best):
            return
        marked[pick] = True
        last, last_index = best, pick


cdef int argmax(Kernel k, const double *score) noexcept nogil:
    cdef int a, best = 0
    for a in range(1, k.actions):
        if score[a] > score[best]:
            best = a
    return best


cdef void safe_cells(Kernel k, const Scene *s, Step *st, const double *position,
                     const uint8_t *present, Py_ssize_t others, uint8_t *allowed) noexcept nogil:
    # planning.reference.inside_safe_cells with every other in sight.
    cdef int a
    cdef Py_ssize_t o
    cdef double mx, my, tx, ty, distance, unit
    for a in range(k.actions):
        mx = (s.x + st.vx[a] * k.dt) - s.x
        my = (s.y + st.vy[a] * k.dt) - s.y
        allowed[a] = True
        if mx == 0 and my == 0:
            continue
        for o in range(others):
            if not present[o]:
                continue
            tx, ty = position[2 * o] - s.x, position[2 * o + 1] - s.y
            distance = sqrt(tx * tx + ty * ty)
            unit = max(distance, 1e-12)
            if mx * (tx / unit) + my * (ty / unit) > distance / 2 - s.radius - k.clearance:
                allowed[a] = False
                break


cdef int64_t decide_row(Kernel k, Workspace w, Scene *s, MapView *m, const double *position,
                        const uint8_t *present, Py_ssize_t others, double *score,
                        uint8_t *allowed) noexcept nogil:
    # planning.reference.LookaheadPolicy.scored (with deepened and first_moves), then the argmax.
    cdef Step *st = &w.steps[0]
    cdef int a
    expand(k, s, m, st)
    leaf_scores(k, w, st, score)
    for a in range(k.actions):
        allowed[a] = True
    if k.safe_cells:
        safe_cells(k, s, st, position, present, others, allowed)
        for a in range(k.actions):
            if not allowed[a]:
                score[a] = -INFINITY
    if k.depth == 1:
        return argmax(k, score)
    a = argmax(k, score)
    if not (s.level < k.weak or st.level[a] < k.weak) or escapes(k, st, a, m):
        return a  # not at risk: one step shows all a deeper search would
    for a in range(k.actions):
        w.escape[a] = escapes(k, st, a, m)
        w.searched[a] = False
    mark_beam(k, score, NULL, w.searched)
    mark_beam(k, score, w.escape, w.searched)
    for a in range(k.actions):
        w.searched[a] = w.searched[a] and allowed[a]
    deep_scores(k, w, s, m, 0, k.depth, w.searched, w.deep)
    for a in range(k.actions):
        score[a] = w.deep[a] if w.searched[a] else -INFINITY
    return argmax(k, score)
