# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True
# cython: initializedcheck=False
"""The received power of every GBS at every point (the numerator of Eq. (1), without
shadowing), compiled: the arithmetic of ``RadioModel``'s numpy reference in the same order, with
its atan2, log and exp taken many at a time from glibc's vector math (``_vector_math.h``),
within 4 ulp of each. It is most of the radio's time: the city's 192 GBSs at each of a step's
550 report points, and every environment's UAVs in training."""

cdef extern from *:
    """
    #ifndef COMPILED_SOURCE_DIGEST
    #define COMPILED_SOURCE_DIGEST ""
    #endif
    """
    const char *COMPILED_SOURCE_DIGEST

cdef extern from "_vector_math.h" nogil:
    void atan2_many(const double *y, const double *x, double *out, int n)
    void exp_many(const double *x, double *out, int n)
    void log_many(const double *x, double *out, int n)

from libc.math cimport sqrt
from libc.stdlib cimport free, malloc

SOURCE_DIGEST = COMPILED_SOURCE_DIGEST.decode()

# Points whose (point, GBS) pairs are taken at once: each vector call gets many values, and
# the block's four buffers (48 KiB with the city's 192 GBSs) stay in a core's L2 cache.
cdef enum:
    POINTS_PER_BLOCK = 8


def gbs_received_power(const double[:, ::1] xy, const double[:, ::1] gbs_xy,
                       double height_gap, double tilt_rad, double beamwidth_rad,
                       double max_attenuation_db, double alpha, double power_w,
                       double ln10, double[:, ::1] out) -> None:
    """``out`` (n, K): the power received from each of the K GBSs at ``gbs_xy`` at each of the
    n points ``xy``, as ``shared.radio.RadioModel``'s numpy reference computes it."""
    cdef Py_ssize_t n = xy.shape[0], k = gbs_xy.shape[0]
    cdef Py_ssize_t size = POINTS_PER_BLOCK * k
    if out.shape[0] != n or out.shape[1] != k or xy.shape[1] != 2 or gbs_xy.shape[1] != 2:
        raise ValueError("xy (n, 2), gbs_xy (K, 2) and out (n, K) do not agree")
    if n == 0 or k == 0:
        return
    cdef double *below = <double *>malloc(size * sizeof(double))
    cdef double *horizontal = <double *>malloc(size * sizeof(double))
    cdef double *slant_sq = <double *>malloc(size * sizeof(double))
    cdef double *work = <double *>malloc(size * sizeof(double))
    if not (below and horizontal and slant_sq and work):
        free(below); free(horizontal); free(slant_sq); free(work)
        raise MemoryError()
    cdef Py_ssize_t block, first, count, point, gbs, pair
    cdef double dx, dy, horizontal_sq, off_boresight, attenuation_db
    cdef double spread = -0.5 * (alpha + 1.0), per_db = ln10 / 10.0, scale = power_w * height_gap
    with nogil:
        for pair in range(size):
            below[pair] = -height_gap
        for block in range((n + POINTS_PER_BLOCK - 1) // POINTS_PER_BLOCK):
            first = block * POINTS_PER_BLOCK
            count = min(POINTS_PER_BLOCK, n - first) * k
            for point in range(first, min(first + POINTS_PER_BLOCK, n)):
                for gbs in range(k):
                    pair = (point - first) * k + gbs
                    dx = xy[point, 0] - gbs_xy[gbs, 0]
                    dy = xy[point, 1] - gbs_xy[gbs, 1]
                    horizontal_sq = dx * dx + dy * dy
                    slant_sq[pair] = horizontal_sq + height_gap * height_gap
                    horizontal[pair] = sqrt(horizontal_sq)
            atan2_many(below, horizontal, work, <int>count)
            log_many(slant_sq, slant_sq, <int>count)
            for pair in range(count):
                off_boresight = (work[pair] - tilt_rad) / beamwidth_rad
                attenuation_db = 12.0 * off_boresight * off_boresight
                if attenuation_db > max_attenuation_db:
                    attenuation_db = max_attenuation_db
                work[pair] = spread * slant_sq[pair] - per_db * attenuation_db
            exp_many(work, &out[first, 0], <int>count)
            for pair in range(count):
                (&out[first, 0])[pair] = scale * (&out[first, 0])[pair]
    free(below); free(horizontal); free(slant_sq); free(work)
