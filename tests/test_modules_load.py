"""Every module of the project imports alone, first, in a fresh interpreter, and every
benchmark ``make bench`` names is one with an entry point: a name removed in one module but
still imported by another, or a module that loads only after some other has, shows here, not
in a process that only a long run or a benchmark starts. Benchmark figures are not tests."""

from __future__ import annotations

import importlib
import os
import pkgutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from benchmarks.__main__ import BENCHMARKS

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("shared", "planning", "world_sim", "uav_agent", "cloud_service", "jamnav", "benchmarks")


def _modules() -> list[str]:
    names = []
    for package in PACKAGES:
        path = [str(ROOT / package)]
        names += [package, *(info.name for info in pkgutil.walk_packages(path, f"{package}.")
                             if not info.name.endswith("__main__"))]
    return names


def _import_alone(name: str) -> str | None:
    """What goes wrong importing ``name`` in an interpreter of its own; None if nothing."""
    done = subprocess.run([sys.executable, "-c", f"import {name}"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    return None if done.returncode == 0 else f"{name}: {done.stderr.strip()}"


def test_each_module_imports_alone_in_a_fresh_interpreter():
    # One interpreter per module, as many at once as there are cores: the project's modules
    # in ~18 s on two idle cores, most of it the time torch, scipy and matplotlib take to load.
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        failures = [failure for failure in pool.map(_import_alone, _modules()) if failure]
    assert not failures, "\n\n".join(failures)


def test_make_bench_names_every_benchmark_module():
    modules = {path.stem for path in (ROOT / "benchmarks").glob("bench_*.py")}
    assert set(BENCHMARKS) == modules


@pytest.mark.parametrize("name", BENCHMARKS)
def test_a_benchmark_has_its_entry_point(name):
    assert callable(importlib.import_module(f"benchmarks.{name}").run)
