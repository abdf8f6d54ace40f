"""An installed jamnav carries its scenarios and networks: the wheel, built from a copy of the
sources and installed into a directory outside the checkout, runs ``jamnav eval`` and ``jamnav
up`` from yet another directory, with nothing imported from the checkout."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from jamnav.cli import main as jamnav
from shared.scenario import tomllib
from tests.support import free_endpoint

ROOT = Path(__file__).resolve().parent.parent
PIP = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
TOP_LEVEL = ("shared", "planning", "world_sim", "uav_agent", "cloud_service", "jamnav")

# Run by the installed copy with the top-level packages as arguments: where each project module
# it loads lives, the data files it finds, and its error for an unknown scenario.
PROBE = """
import json, sys
import cloud_service.process, jamnav.cli, planning.lookahead, uav_agent.process, world_sim.process
from planning.chosen import require_planner
from planning.compiled import compiled_module
require_planner()
compiled_module("_regression")
from shared.radio import radio_core
radio_core()
from shared.scenario import SCENARIO_DIR, ScenarioError, resolve_scenario_path
from shared.shipped import MODELS_DIR
try:
    resolve_scenario_path("no-such-world")
except ScenarioError as exc:
    error = str(exc)
print(json.dumps({
    "modules": {n: m.__file__ for n, m in sys.modules.items()
                if n.split(".")[0] in sys.argv[1:] and getattr(m, "__file__", None)},
    "scenarios": sorted(p.name for p in SCENARIO_DIR.iterdir() if p.suffix == ".toml"),
    "models": sorted(p.name for p in MODELS_DIR.iterdir() if p.is_file()),
    "error": error,
}))
"""


def checked(argv: list[str], **kwargs) -> subprocess.CompletedProcess:
    result = subprocess.run(argv, capture_output=True, text=True, **kwargs)
    assert result.returncode == 0, f"{' '.join(argv)[:300]}: {result.stderr[-2000:]}"
    return result


def copy_sources(dest: Path) -> Path:
    """What the build reads: pyproject.toml, setup.py (the compiled core), the readme and the
    directory of every package it names, without the checkout's own build of the core (a build
    in the checkout would leave build/ there, stale files included)."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    setuptools = config["tool"]["setuptools"]
    mapped = setuptools.get("package-dir", {})
    for top in {mapped.get(p, p.replace(".", "/")).split("/")[0] for p in setuptools["packages"]}:
        shutil.copytree(ROOT / top, dest / top,
                        ignore=shutil.ignore_patterns("__pycache__", "*.so", "*.c"))
    for name in ("pyproject.toml", "setup.py", config["project"]["readme"]):
        shutil.copy(ROOT / name, dest / name)
    return dest


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict:
    """The wheel installed with ``pip --target``; how to run it from a directory of its own."""
    base = tmp_path_factory.mktemp("packaging")
    source = copy_sources(base / "source")
    checked([*PIP, "wheel", "--no-deps", "--no-build-isolation", "--no-index",
             "--wheel-dir", str(base / "dist"), str(source)])
    (wheel,) = (base / "dist").glob("jamnav-*.whl")
    site = base / "site"
    checked([*PIP, "install", "--no-deps", "--no-index", "--target", str(site), str(wheel)])
    elsewhere = base / "elsewhere"
    elsewhere.mkdir()
    env = dict(os.environ, PYTHONPATH=str(site), OMP_NUM_THREADS="1")
    return {"site": site, "jamnav": str(site / "bin" / "jamnav"), "cwd": elsewhere, "env": env}


def test_the_installed_copy_runs_on_its_own_files(installed):
    probe = json.loads(checked([sys.executable, "-c", PROBE, *TOP_LEVEL], cwd=installed["cwd"],
                               env=installed["env"]).stdout)
    site = installed["site"].resolve()
    assert {name.split(".")[0] for name in probe["modules"]} == set(TOP_LEVEL)
    outside = [f for f in probe["modules"].values() if not Path(f).resolve().is_relative_to(site)]
    assert outside == []
    # The wheel carries the compiled core, built from the copied sources.
    for module in ("planning._lookahead", "planning._routes", "planning._regression",
                   "shared._radio"):
        assert Path(probe["modules"][module]).suffix == ".so"
    shipped_scenarios = sorted(p.name for p in (ROOT / "scenarios").glob("*.toml"))
    assert probe["scenarios"] == shipped_scenarios
    assert probe["models"] == sorted(
        p.name for p in (ROOT / "models").iterdir()
        if p.suffix in (".safetensors", ".json") or p.name == "train_log.csv")
    known = ", ".join(sorted(Path(name).stem for name in shipped_scenarios))
    assert probe["error"].endswith(f"(known names: {known})")


def test_installed_eval_flies_the_episodes_of_the_checkout(installed, capsys):
    argv = ["eval", "--method", "straight", "--episodes", "2", "--json", "--per-episode"]
    result = checked([installed["jamnav"], *argv], cwd=installed["cwd"], env=installed["env"],
                     timeout=120)
    assert jamnav(argv) == 0
    assert json.loads(result.stdout) == json.loads(capsys.readouterr().out)


def test_installed_up_runs_an_episode_as_eval_does(installed, capsys):
    run_dir = installed["cwd"] / "run"
    checked([installed["jamnav"], "up", "--lockstep", "--uavs", "2", "--episodes", "1",
             "--map", "perfect", "--jammer", "0,0,1", "--seed", "3", "--no-figures",
             "--endpoint", free_endpoint(), "--run-dir", str(run_dir)],
            cwd=installed["cwd"], env=installed["env"], timeout=150)
    report = json.loads((run_dir / "report.json").read_text())
    # The console too: it serves its page from the package's data.
    assert sorted(p["role"] for p in report["processes"]) == [
        "agent", "agent", "cloud", "console", "router", "world"]
    assert report["restarts"]["console"] == 0
    assert jamnav(["eval", "--method", "perfect", "--uavs", "2", "--episodes", "1", "--seed", "3",
                   "--jammer", "0,0,1", "--per-episode", "--json"]) == 0
    assert report["outcomes"] == json.loads(capsys.readouterr().out)["outcomes"]
