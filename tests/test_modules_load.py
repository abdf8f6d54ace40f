"""Every module of the project imports alone, before any other of the project's, and every
benchmark ``make bench`` names is one with an entry point: a name removed in one module but
still imported by another, or a module that loads only after some other has, shows here, not
in a process that only a long run or a benchmark starts. Benchmark figures are not tests."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys
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


# Lists, in the order they loaded, the modules from outside the checkout (run in its root)
# that importing every module of the project (argv) loads.
CENSUS = """
import importlib, os, sys
for name in sys.argv[1:]:
    try:
        importlib.import_module(name)
    except Exception:
        pass  # the import test below reports it
def in_checkout(name):
    top = name.split(".")[0]
    return os.path.exists(top) or os.path.exists(top + ".py")
print("\\n".join(name for name in list(sys.modules)
                if not name.startswith("__") and not in_checkout(name)))
"""

# Loads the census's modules (stdin), then imports each module of the project (argv) in a
# process of its own forked from this one, as many at once as there are cores; prints what
# goes wrong.
FORKED_IMPORTS = """
import importlib, multiprocessing, sys, traceback
for name in sys.stdin.read().split():
    try:
        importlib.import_module(name)
    except Exception:
        pass  # a name a library registers but that does not import on its own
def import_alone(name):
    try:
        importlib.import_module(name)
    except BaseException:
        return name + ": " + traceback.format_exc()
with multiprocessing.get_context("fork").Pool(maxtasksperchild=1) as pool:
    for failure in pool.imap(import_alone, sys.argv[1:]):
        if failure:
            print(failure, flush=True)
"""


def test_each_module_imports_alone_before_any_other_of_the_project():
    # Each module in a process that has loaded the libraries the project uses (torch, scipy,
    # matplotlib, ...) and none of the project's own: what an interpreter of its own per module
    # checks, without loading torch again for every module.
    modules = _modules()
    census = subprocess.run([sys.executable, "-c", CENSUS, *modules], cwd=ROOT,
                            capture_output=True, text=True, timeout=300, check=True)
    libraries = census.stdout.split()
    assert "torch" in libraries and not {"shared", "tests"} & {name.split(".")[0]
                                                              for name in libraries}
    imports = subprocess.run([sys.executable, "-c", FORKED_IMPORTS, *modules], cwd=ROOT,
                             input=census.stdout, capture_output=True, text=True, timeout=300)
    assert imports.returncode == 0, imports.stderr
    assert not imports.stdout, imports.stdout


def test_make_bench_names_every_benchmark_module():
    modules = {path.stem for path in (ROOT / "benchmarks").glob("bench_*.py")}
    assert set(BENCHMARKS) == modules


@pytest.mark.parametrize("name", BENCHMARKS)
def test_a_benchmark_has_its_entry_point(name):
    assert callable(importlib.import_module(f"benchmarks.{name}").run)
