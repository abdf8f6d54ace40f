"""Every benchmark ``make bench`` names loads and has its entry point: a benchmark broken by a
change elsewhere shows here, not hours later in a long run. Their figures are not tests."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

from benchmarks.__main__ import BENCHMARKS


def test_make_bench_names_every_benchmark_module():
    modules = {path.stem for path in (Path(__file__).parent.parent / "benchmarks").glob(
        "bench_*.py")}
    assert set(BENCHMARKS) == modules


@pytest.mark.parametrize("name", BENCHMARKS)
def test_a_benchmark_loads(name):
    module = importlib.import_module(f"benchmarks.{name}")
    assert callable(module.run)
