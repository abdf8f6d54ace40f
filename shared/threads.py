"""One BLAS and OpenMP thread for each process of the system, set where a program starts.

The networks are small: numpy's BLAS (and torch) spreading one forward over several threads
costs more CPU than it saves, and a system's processes already share the cores. BLAS sizes its
pool when numpy loads, so a program sets this before it imports numpy, and hands it on in the
environment of the processes it starts; a setting of the user's own wins.
"""

from __future__ import annotations

from collections.abc import MutableMapping

THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread(environ: MutableMapping[str, str]) -> MutableMapping[str, str]:
    """``environ`` (``os.environ`` or a child's) with one thread for each pool the user has
    not sized."""
    for variable in THREAD_VARIABLES:
        environ.setdefault(variable, "1")
    return environ
