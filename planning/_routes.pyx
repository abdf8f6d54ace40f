# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True
# cython: initializedcheck=False
"""The route fields of ``planning.routes`` compiled: Dijkstra from each destination over the
8-connected grid, a binary heap of the nodes reached but not yet settled, on the float64 edge
weights of ``planning.routes.EdgeWeights``. The numpy sweep of ``planning.routes`` is the
reference: both reach the one fixpoint of d[v] = min(d[v], d[u] + w(u, v)) by the same float64
additions, so their fields are the same bit for bit.

A field may stop at a limit, as scipy's Dijkstra does: a node whose distance exceeds it is never
reached and reads infinity; every other node has its exact distance, since the nodes on its
shortest route are nearer still and settle first.
"""

import numpy as np

from libc.math cimport INFINITY
from libc.stdint cimport int64_t
from libc.stdlib cimport free, malloc


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
    NOT_QUEUED = -1


cdef struct Queue:
    # A binary min-heap of nodes keyed by their distance in ``field``; ``place[node]`` is the
    # node's index in ``heap``, NOT_QUEUED while it is not there.
    Py_ssize_t *heap
    Py_ssize_t *place
    Py_ssize_t size
    double *field


cdef inline void put(Queue *queue, Py_ssize_t index, Py_ssize_t node) noexcept nogil:
    queue.heap[index] = node
    queue.place[node] = index


cdef inline double key_at(Queue *queue, Py_ssize_t index) noexcept nogil:
    return queue.field[queue.heap[index]]


cdef inline void sift_up(Queue *queue, Py_ssize_t index) noexcept nogil:
    cdef Py_ssize_t node = queue.heap[index], parent
    cdef double key = queue.field[node]
    while index > 0:
        parent = (index - 1) >> 1
        if key_at(queue, parent) <= key:
            break
        put(queue, index, queue.heap[parent])
        index = parent
    put(queue, index, node)


cdef inline Py_ssize_t pop_nearest(Queue *queue) noexcept nogil:
    cdef Py_ssize_t nearest = queue.heap[0], index = 0, child
    queue.place[nearest] = NOT_QUEUED
    queue.size -= 1
    if queue.size == 0:
        return nearest
    cdef Py_ssize_t last = queue.heap[queue.size]
    cdef double key = queue.field[last]
    while True:
        child = 2 * index + 1
        if child >= queue.size:
            break
        if child + 1 < queue.size and key_at(queue, child + 1) < key_at(queue, child):
            child += 1
        if key <= key_at(queue, child):
            break
        put(queue, index, queue.heap[child])
        index = child
    put(queue, index, last)
    return nearest


cdef inline void relax(Queue *queue, Py_ssize_t node, double reached, double limit) noexcept nogil:
    # A settled node is never shortened: its distance is at most the one being settled.
    if reached >= queue.field[node] or reached > limit:
        return
    queue.field[node] = reached
    cdef Py_ssize_t index = queue.place[node]
    if index == NOT_QUEUED:
        index = queue.size
        queue.size += 1
        put(queue, index, node)
    sift_up(queue, index)


cdef void fill_field(Queue *queue, const double[:, ::1] down, const double[:, ::1] right,
                     const double[:, ::1] down_right, const double[:, ::1] down_left,
                     Py_ssize_t destination, double limit) noexcept nogil:
    """``queue.field`` (rows x cols) becomes the route distance of every node to
    ``destination``, infinite beyond ``limit``; ``queue.place`` must be all NOT_QUEUED, and is
    again after."""
    cdef Py_ssize_t rows = right.shape[0], cols = down.shape[1], node, r, c
    cdef double here
    for node in range(rows * cols):
        queue.field[node] = INFINITY
    queue.field[destination] = 0.0
    put(queue, 0, destination)
    queue.size = 1
    while queue.size:
        node = pop_nearest(queue)
        here = queue.field[node]
        r = node // cols
        c = node - r * cols
        if r > 0:
            relax(queue, node - cols, here + down[r - 1, c], limit)
            if c > 0:
                relax(queue, node - cols - 1, here + down_right[r - 1, c - 1], limit)
            if c < cols - 1:
                relax(queue, node - cols + 1, here + down_left[r - 1, c], limit)
        if r < rows - 1:
            relax(queue, node + cols, here + down[r, c], limit)
            if c > 0:
                relax(queue, node + cols - 1, here + down_left[r, c - 1], limit)
            if c < cols - 1:
                relax(queue, node + cols + 1, here + down_right[r, c], limit)
        if c > 0:
            relax(queue, node - 1, here + right[r, c - 1], limit)
        if c < cols - 1:
            relax(queue, node + 1, here + right[r, c], limit)


def route_fields(const double[:, ::1] down, const double[:, ::1] right,
                 const double[:, ::1] down_right, const double[:, ::1] down_left,
                 const int64_t[::1] destinations, const double[::1] limits):
    """The route fields (destinations, rows, cols) float64 to each node of ``destinations``
    (flat indices into the grid), each infinite beyond its own of ``limits``, on the edge
    weights of ``planning.routes.EdgeWeights`` (``down`` (rows - 1, cols), ``right``
    (rows, cols - 1), both diagonals (rows - 1, cols - 1))."""
    cdef Py_ssize_t rows = right.shape[0], cols = down.shape[1], count = destinations.shape[0]
    cdef Py_ssize_t nodes = rows * cols, k
    if (down.shape[0] != rows - 1 or right.shape[1] != cols - 1
            or down_right.shape[0] != rows - 1 or down_right.shape[1] != cols - 1
            or down_left.shape[0] != rows - 1 or down_left.shape[1] != cols - 1):
        raise ValueError("edge weights of different grids")
    if limits.shape[0] != count:
        raise ValueError(f"{count} destinations but {limits.shape[0]} limits")
    for k in range(count):
        if not 0 <= destinations[k] < nodes:
            raise ValueError(f"destination {destinations[k]} is not a node of {rows} x {cols}")
    fields = np.empty((count, rows, cols))
    cdef double[:, :, ::1] out = fields
    cdef Queue queue
    queue.heap = <Py_ssize_t *> malloc(max(nodes, 1) * sizeof(Py_ssize_t))
    queue.place = <Py_ssize_t *> malloc(max(nodes, 1) * sizeof(Py_ssize_t))
    if queue.heap == NULL or queue.place == NULL:
        free(queue.heap)
        free(queue.place)
        raise MemoryError()
    with nogil:
        for k in range(nodes):
            queue.place[k] = NOT_QUEUED
        for k in range(count):
            queue.field = &out[k, 0, 0]
            fill_field(&queue, down, right, down_right, down_left, destinations[k], limits[k])
    free(queue.heap)
    free(queue.place)
    return fields
