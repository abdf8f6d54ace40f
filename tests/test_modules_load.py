"""Every module of the project imports, and every benchmark ``make bench`` names is one with an
entry point: a name removed in one module but still imported by another shows here, not in
a process that only a long run or a benchmark starts. Benchmark figures are not tests."""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

import pytest

from benchmarks.__main__ import BENCHMARKS

PACKAGES = ("shared", "planning", "world_sim", "uav_agent", "cloud_service", "jamnav", "benchmarks")


def _modules() -> list[str]:
    names = []
    for package in PACKAGES:
        path = [str(Path(__file__).parent.parent / package.replace(".", "/"))]
        names += [package, *(info.name for info in pkgutil.walk_packages(path, f"{package}.")
                             if not info.name.endswith("__main__"))]
    return names


@pytest.mark.parametrize("name", _modules())
def test_a_module_imports(name):
    importlib.import_module(name)


def test_make_bench_names_every_benchmark_module():
    modules = {path.stem for path in (Path(__file__).parent.parent / "benchmarks").glob(
        "bench_*.py")}
    assert set(BENCHMARKS) == modules


@pytest.mark.parametrize("name", BENCHMARKS)
def test_a_benchmark_has_its_entry_point(name):
    assert callable(importlib.import_module(f"benchmarks.{name}").run)
