from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from shared.threads import one_blas_thread

# The test run is a program of its own: its in-process flights and the processes it starts run
# BLAS on one thread, as the system's do. Set before numpy loads (shared.scenario loads it).
one_blas_thread(os.environ)
# Two test workers share the two cores: the planner's second thread is tested where asked for.
os.environ.setdefault("JAMNAV_PLANNER_THREADS", "1")

from shared.scenario import SCENARIO_DIR, Scenario, load_scenario  # noqa: E402


def pytest_sessionstart(session) -> None:
    """The run's first line says where it runs: float32 results differ between CPUs in their
    last bits, so a failure report names the CPU and the kernels torch chose on it."""
    import torch

    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is None or hasattr(session.config, "workerinput"):  # an xdist worker
        return
    cpuinfo = Path("/proc/cpuinfo")
    models = [line.split(":", 1)[1].strip() for line in
              (cpuinfo.read_text().splitlines() if cpuinfo.exists() else [])
              if line.startswith("model name")]
    reporter.write_line(f"cpu: {models[0] if models else 'unknown'} ({os.cpu_count()} cores), "
                        f"torch kernels: {torch.backends.cpu.get_cpu_capability()}")


@pytest.fixture(autouse=True)
def signal_handlers_restored():
    """A command run in-process installs its process's SIGINT and SIGTERM handlers, as it
    would running alone (some before they find their bad input): each test starts from the
    handlers the one before it found, so that tests of Ctrl-C see Python's own."""
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    yield
    for sig, handler in handlers.items():
        signal.signal(sig, handler)


@pytest.fixture(scope="session")
def scenario() -> Scenario:
    return load_scenario()


def write_variant(tmp_path: Path, old: str, new: str, base: str = "icc2021") -> Path:
    """A copy of a shipped scenario file with ``old`` replaced by ``new`` once."""
    text = (SCENARIO_DIR / f"{base}.toml").read_text()
    assert old in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(old, new, 1))
    return path


def variant(base: Scenario, **sections) -> Scenario:
    """A copy of ``base`` with some fields of some sections replaced."""
    return base.changed({f"{section}.{key}": value for section, values in sections.items()
                         for key, value in values.items()})


@pytest.fixture
def supervisor():
    """Start ``jamnav up`` in the background; whatever happens, stop it and its children.
    Without the web console unless ``web`` (tests/test_console_browser.py runs it)."""
    root = Path(__file__).resolve().parent.parent
    started: list[subprocess.Popen] = []

    def start(*argv: str, web: bool = False, **kwargs) -> subprocess.Popen:
        env = dict(os.environ, PYTHONPATH=str(root))
        argv = argv if web else (*argv, "--no-web")
        process = subprocess.Popen([sys.executable, "-m", "jamnav.cli", "up", *argv], env=env,
                                   cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   text=True, **kwargs)
        started.append(process)
        return process

    yield start
    for process in started:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()  # its children stop by themselves when it disappears
                process.wait()


# Modules whose tests run systems of processes and zenoh sessions against wall-clock waits.
# `make test` runs the suite on two pytest-xdist workers: these modules share one worker, one
# test at a time, so two systems never fight each other for the cores while the other worker
# runs the in-process tests; every other module stays whole on one worker (its module-scoped
# fixtures, such as the packaging test's wheel, are built once). The packaging test runs on the
# other worker: it is mostly a wheel's build, and its one system, a lockstep episode of two
# UAVs, waits up to 2 s a step for actions that take milliseconds. There it evens the workers'
# loads, the systems' being the larger.
SYSTEM_MODULES = frozenset({
    "test_bus_inprocess", "test_bus_supervisor", "test_chaos", "test_checkpoint",
    "test_console_browser", "test_examples", "test_faults", "test_fuzz", "test_recording",
    "test_security", "test_two_routers",
})

# The load-balancing schedules of pytest-xdist; the others (each, worksteal) are left as asked.
_LOAD_SCHEDULES = frozenset({"load", "loadscope", "loadfile", "loadgroup"})


def work_unit_of(nodeid: str) -> str:
    """The unit of work a test belongs to: "systems", or its module."""
    module = Path(nodeid.split("::", 1)[0]).stem
    return "systems" if module in SYSTEM_MODULES else module


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """Units of work as ``work_unit_of`` says, the largest first (so the systems start at
    once). The grouping reads node ids, not ``xdist_group`` marks: pytest 9.2 keeps a node's id
    where pytest-xdist 3.8 no longer renames it, and the marks' groups are lost there."""
    if config.getvalue("dist") not in _LOAD_SCHEDULES:
        return None
    from xdist.scheduler import LoadScopeScheduling

    class SystemsOnOneWorker(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return work_unit_of(nodeid)

    return SystemsOnOneWorker(config, log)
