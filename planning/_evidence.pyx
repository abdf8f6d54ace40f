# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True
# cython: initializedcheck=False
"""The sums of the cloud's jammer search, compiled: for each hypothesis and each power, the
measurements' tabulated log-likelihoods added up (``cloud_service.jammer_evidence``, whose numpy
gather is the reference). numpy builds an index per hypothesis, power and measurement, and
gathers and sums them in float32; here each measurement's entries are read where they lie and
added in float64, so the sums agree with the reference's within its float32 rounding."""

cdef extern from *:
    """
    #ifndef PLANNING_SOURCE_DIGEST
    #define PLANNING_SOURCE_DIGEST ""
    #endif
    """
    const char *PLANNING_SOURCE_DIGEST

import numpy as np

SOURCE_DIGEST = PLANNING_SOURCE_DIGEST.decode()


def add_table_entries(const int[:, ::1] first_entry, const int[::1] power_offsets,
                      const float[::1] table, double[:, ::1] out):
    """``out[h, p]`` += the sum over measurements i of ``table[first_entry[i, h] +
    power_offsets[p]]``: hypothesis h's log-likelihood at power p, each measurement's table
    entry for the lowest power at ``first_entry`` and the others ``power_offsets`` after it.
    Measurement by measurement, so that its entries stay in cache for every hypothesis."""
    cdef Py_ssize_t count = first_entry.shape[0], hypotheses = first_entry.shape[1]
    cdef Py_ssize_t powers = power_offsets.shape[0], h, i, p
    if out.shape[0] != hypotheses or out.shape[1] != powers:
        raise ValueError(f"out of shape ({out.shape[0]}, {out.shape[1]}) for {hypotheses} "
                         f"hypotheses and {powers} powers")
    if powers == 0 or hypotheses == 0 or count == 0:
        return
    offsets, firsts = np.asarray(power_offsets), np.asarray(first_entry)
    if offsets.min() + firsts.min() < 0 or offsets.max() + firsts.max() >= table.shape[0]:
        raise ValueError("an entry beyond the table")
    cdef const float *entries
    cdef double *sums
    with nogil:
        for i in range(count):
            for h in range(hypotheses):
                entries = &table[first_entry[i, h]]
                sums = &out[h, 0]
                for p in range(powers):
                    sums[p] += entries[power_offsets[p]]
