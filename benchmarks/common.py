"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from planning import PLANNER_VARIABLE


def cpu_name() -> str:
    """The CPU's model as the kernel names it: a figure is a fact about one CPU."""
    info = Path("/proc/cpuinfo")
    lines = info.read_text().splitlines() if info.exists() else []
    names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")]
    return names[0] if names else platform.processor() or platform.machine()


@dataclass
class Figure:
    name: str
    value: float
    unit: str
    target: float | None = None  # higher is better unless lower_is_better
    lower_is_better: bool = False

    @property
    def verdict(self) -> str:
        if self.target is None:
            return ""
        met = self.value <= self.target if self.lower_is_better else self.value >= self.target
        relation = "<=" if self.lower_is_better else ">="
        target = f"{self.target:,.0f}" if abs(self.target) >= 100 else f"{self.target:g}"
        return f"{'met' if met else 'MISSED'} (target {relation} {target})"


def best_rate(work: Callable[[], int], repeats: int = 5, min_seconds: float = 0.5) -> float:
    """Items per second of ``work`` (which returns how many items it did): best of repeats."""
    best = 0.0
    for _ in range(repeats):
        items, start = 0, time.perf_counter()
        while (elapsed := time.perf_counter() - start) < min_seconds:
            items += work()
        best = max(best, items / elapsed)
    return best


@contextmanager
def planner_chosen(planner: str) -> Iterator[None]:
    """``JAMNAV_PLANNER`` set to ``planner`` for the block, as it was after it."""
    before = os.environ.get(PLANNER_VARIABLE)
    os.environ[PLANNER_VARIABLE] = planner
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(PLANNER_VARIABLE)
        else:
            os.environ[PLANNER_VARIABLE] = before
