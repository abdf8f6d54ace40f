# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True
# cython: initializedcheck=False
"""The cloud's jammer search, compiled: each measurement's table of log-likelihoods over the
jammer's power (``weighted_report_tables``: read from the report tables of
``cloud_service.report_likelihood``, whose numpy gathers are the reference, with the same
arithmetic, so bit for bit the same), and for each hypothesis and each power, those tables'
entries added up (``add_hypothesis_entries``: numpy works out each hypothesis's path gain to
every measurement, builds an index per hypothesis, power and measurement, and gathers and sums
them in float32; here each measurement's gains to every hypothesis are taken at once with
glibc's vector log, its entries read where they lie and added in float64, so the sums agree
with the reference's within its float32 rounding wherever no gain lies on a tie between two
entries)."""

cdef extern from *:
    """
    #ifndef COMPILED_SOURCE_DIGEST
    #define COMPILED_SOURCE_DIGEST ""
    #endif
    """
    const char *COMPILED_SOURCE_DIGEST

cdef extern from "_vector_math.h" nogil:
    void log_many(const double *x, double *out, int n)

from libc.math cimport fabs, isfinite, log, rint
from libc.stdlib cimport free, malloc

import numpy as np

SOURCE_DIGEST = COMPILED_SOURCE_DIGEST.decode()
# Measurements whose tables are read together for each hypothesis: their rows stay in cache
# while every hypothesis reads them, and a hypothesis's sums stay in cache while it does.
cdef enum:
    _CHUNK = 32


def add_hypothesis_entries(const double[:, ::1] positions, const double[:, ::1] xy,
                           const double[::1] offset_db, double slope_db, double gap_sq_m2,
                           double step_db, Py_ssize_t row_length, Py_ssize_t last_first,
                           const int[::1] power_offsets, const float[::1] table,
                           double[:, ::1] out):
    """``out[h, p]`` += the sum over measurements i of ``table[i * row_length + e(h, i) +
    power_offsets[p]]``: hypothesis h's log-likelihood at power p. Measurement i's first
    entry is its path gain from ``positions[h]`` to ``xy[i]``, ``offset_db[i] - slope_db
    * log10(squared distance + gap_sq_m2)``, in ``step_db`` steps (rounded half to even,
    clipped to [0, ``last_first``]). ``_CHUNK`` measurements at a time."""
    cdef Py_ssize_t count = xy.shape[0], hypotheses = positions.shape[0]
    cdef Py_ssize_t powers = power_offsets.shape[0], h, i, p
    if out.shape[0] != hypotheses or out.shape[1] != powers:
        raise ValueError(f"out of shape ({out.shape[0]}, {out.shape[1]}) for {hypotheses} "
                         f"hypotheses and {powers} powers")
    if positions.shape[1] != 2 or xy.shape[1] != 2 or offset_db.shape[0] != count:
        raise ValueError("positions and measurements are (x, y), one offset a measurement")
    if powers == 0 or hypotheses == 0 or count == 0:
        return
    offsets = np.asarray(power_offsets)
    if offsets.min() < 0 or last_first < 0 or (
            (count - 1) * row_length + last_first + offsets.max() >= table.shape[0]):
        raise ValueError("an entry beyond the table")
    cdef double per_log = slope_db / log(10.0) / step_db, dx, dy, entry
    cdef Py_ssize_t chunk, done, c, first
    cdef double *buffers = <double *>malloc((2 * _CHUNK + powers) * sizeof(double))
    if buffers == NULL:
        raise MemoryError()
    cdef double *squared = buffers
    cdef double *logs = buffers + _CHUNK
    cdef double *sums = buffers + 2 * _CHUNK
    cdef const float *entries
    try:
        with nogil:
            done = 0
            while done < count:
                chunk = min(_CHUNK, count - done)
                for h in range(hypotheses):
                    for c in range(chunk):
                        dx = positions[h, 0] - xy[done + c, 0]
                        dy = positions[h, 1] - xy[done + c, 1]
                        squared[c] = dx * dx + dy * dy + gap_sq_m2
                    log_many(squared, logs, <int>chunk)
                    for p in range(powers):
                        sums[p] = 0.0
                    for c in range(chunk):
                        entry = rint(offset_db[done + c] / step_db - per_log * logs[c])
                        first = 0 if not entry > 0 else (
                            last_first if entry > last_first else <Py_ssize_t>entry)
                        entries = &table[(done + c) * row_length + first]
                        for p in range(powers):
                            sums[p] += entries[power_offsets[p]]
                    for p in range(powers):
                        out[h, p] += sums[p]
                done += chunk
    finally:
        free(buffers)


cdef inline Py_ssize_t _entry(double position, double low, double step,
                              Py_ssize_t count) noexcept nogil:
    """numpy's ``clip(rint((position - low) / step).astype(int64), 0, count - 1)``: a value no
    int64 holds (NaN among them) casts there to int64's least, and so clips to 0."""
    cdef double entry = rint((position - low) / step)
    if not fabs(entry) < 9223372036854775808.0 or entry < 0:
        return 0
    if entry > count - 1:
        return count - 1
    return <Py_ssize_t>entry


def _rows_within(rows, row_length: int, size: int) -> bool:
    return rows.min() >= 0 and (rows.max() + 1) * row_length <= size


def weighted_report_tables(const double[::1] believed_db, const double[:, ::1] loss_db,
                           const long[::1] level_rows, const double[::1] level_values,
                           Py_ssize_t sinr_count, double sinr_low_db, double sinr_step_db,
                           const double[::1] reported_db, const long[::1] db_rows,
                           const double[::1] db_values, Py_ssize_t offset_count,
                           double offset_range_db, const double[::1] weights,
                           float[:, ::1] out):
    """``out[i, j]`` = ``weights[i]`` times the log-probability of measurement i's report
    where its SINR is ``believed_db[i] - loss_db[i or 0, j]``, in float32: from the table of
    its level (its row ``level_rows[i]`` of ``level_values``, over ``sinr_count`` SINRs from
    ``sinr_low_db`` in steps of ``sinr_step_db``) or, where its reported SINR is finite, from
    the table of its dB report (row ``db_rows[i]`` of ``db_values``, over ``offset_count``
    offsets of the report from the SINR, from ``-offset_range_db``, in the same steps)."""
    cdef Py_ssize_t count = out.shape[0], columns = out.shape[1], i, j
    cdef Py_ssize_t loss_stride = 0 if loss_db.shape[0] == 1 else 1
    cdef const double *levels_row
    cdef const double *db_row
    cdef const double *loss
    cdef double sinr, weight, value
    if loss_db.shape[1] != columns or loss_db.shape[0] not in (1, count):
        raise ValueError(f"losses of shape ({loss_db.shape[0]}, {loss_db.shape[1]}) for "
                         f"{count} measurements and {columns} columns")
    lengths = {"believed": believed_db.shape[0], "level rows": level_rows.shape[0],
               "reported": reported_db.shape[0], "dB rows": db_rows.shape[0],
               "weights": weights.shape[0]}
    for name, length in lengths.items():
        if length != count:
            raise ValueError(f"{length} {name} for {count} measurements")
    if count and not (_rows_within(np.asarray(level_rows), sinr_count, level_values.shape[0])
                      and _rows_within(np.asarray(db_rows), offset_count, db_values.shape[0])):
        raise ValueError("a row beyond its table")
    with nogil:
        for i in range(count):
            levels_row = &level_values[level_rows[i] * sinr_count]
            db_row = &db_values[db_rows[i] * offset_count]
            loss = &loss_db[i * loss_stride, 0]
            weight = weights[i]
            for j in range(columns):
                sinr = believed_db[i] - loss[j]
                if isfinite(reported_db[i]):
                    value = db_row[_entry((reported_db[i] - sinr) + offset_range_db, 0.0,
                                          sinr_step_db, offset_count)]
                else:
                    value = levels_row[_entry(sinr, sinr_low_db, sinr_step_db, sinr_count)]
                out[i, j] = <float>(weight * value)
