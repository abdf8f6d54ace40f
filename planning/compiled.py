"""Which planner the environment chooses (``JAMNAV_PLANNER``: ``compiled``, the default, or
``reference``), and the modules of the compiled core it flies, each refused in one line naming
the fix where it is not built or was built from other source than is beside it: never a silent
fall back to the numpy reference."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from types import ModuleType

from planning import PlannerError
from shared import compiled_core


def chosen_planner() -> str:
    return compiled_core.chosen_core()


def compiled_module(name: str) -> ModuleType:
    """The compiled core's module ``planning.<name>`` (``_lookahead``, ``_routes``)."""
    return compiled_core.compiled_module(f"planning.{name}")


def require_modules(*names: str) -> None:
    """Each of the compiled core's ``planning.<name>`` modules checked where the environment
    chooses the compiled core: a process that needs them stops as it starts, in one line."""
    if chosen_planner() == "compiled":
        for name in names:
            compiled_module(name)


THREADS_VARIABLE = "JAMNAV_PLANNER_THREADS"


def planner_threads() -> int:
    """The threads the compiled core may use at once: ``JAMNAV_PLANNER_THREADS``, 1 or 2
    (the default)."""
    choice = os.environ.get(THREADS_VARIABLE, "2")
    if choice not in ("1", "2"):
        raise PlannerError(f"{THREADS_VARIABLE}={choice!r}: expected 1 or 2")
    return int(choice)


def one_planner_thread() -> None:
    """Keep this process's planning to one thread (and a training run's validations in it):
    a pool's workers, which fill the cores between them, start with it."""
    os.environ[THREADS_VARIABLE] = "1"


# Rows below this many are decided on one thread: a second one costs more to start than it
# saves on a small batch (an agent's one UAV).
SPLIT_AT = 32
_second_thread: ThreadPoolExecutor | None = None


def on_two_cores(work: Callable[[slice], None], count: int, split_at: int = SPLIT_AT) -> None:
    """``work(part)`` over ``count`` items, the second half on a second thread while this one
    does the first, where both are worth it: at least ``split_at`` items, a second core, and
    JAMNAV_PLANNER_THREADS not 1 (the benchmarks' one core). The core's loops run without the
    GIL and decide each item alone, so the halves give what one call over all of them gives."""
    global _second_thread
    if planner_threads() == 1 or count < split_at or (os.cpu_count() or 1) < 2:
        work(slice(0, count))
        return
    if _second_thread is None:
        _second_thread = ThreadPoolExecutor(1, thread_name_prefix="planning")
    half = count // 2
    second = _second_thread.submit(work, slice(half, count))
    work(slice(0, half))
    second.result()
