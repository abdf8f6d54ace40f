"""`make test`'s schedule: the modules that run systems of processes share one worker."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from tests.conftest import SYSTEM_MODULES

ROOT = Path(__file__).resolve().parent.parent
THREE_TESTS = "\n\n".join(f"def test_{name}():\n    pass\n" for name in ("one", "two", "three"))


def test_every_systems_module_named_exists():
    # A renamed module would leave the group without a word.
    assert {path.stem for path in (ROOT / "tests").glob("test_*.py")} >= SYSTEM_MODULES


def test_two_systems_modules_run_on_one_worker_and_the_rest_on_the_other(tmp_path):
    # Two systems modules first in collection order, then one other: xdist's own schedules
    # (load, loadscope, and loadgroup, whose marks pytest 9.2 loses) each put the two systems
    # modules on different workers here; the suite's schedule puts them on one.
    for module in ("test_bus_inprocess", "test_chaos", "test_orca"):
        (tmp_path / f"{module}.py").write_text(THREE_TESTS)
    (tmp_path / "conftest.py").write_text(
        "from tests.conftest import pytest_xdist_make_scheduler  # noqa: F401\n")
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadscope", "-v",
         "-p", "no:cacheprovider", "-o", "addopts=", "--rootdir", str(tmp_path), str(tmp_path)],
        cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True,
        text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    workers = {}
    for worker, module in re.findall(r"\[(gw\d)\] \[ *\d+%\] PASSED (\w+)\.py::", done.stdout):
        workers.setdefault(module, set()).add(worker)
    assert set(workers) == {"test_bus_inprocess", "test_chaos", "test_orca"}, done.stdout
    assert workers["test_bus_inprocess"] == workers["test_chaos"]
    assert len(workers["test_chaos"]) == 1
    assert workers["test_orca"].isdisjoint(workers["test_chaos"])
