"""A UAV's agent flies without torch or scipy: neither importing it nor what it does to fly
(taking both networks from the cloud's messages, sampling the map, deciding) loads them. Nor do the
other processes, but for a cloud that retrains."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

FLY_ONCE = """
import json, logging, sys
import uav_agent.process
from shared.cloud_messages import SinrMap, ValueWeights
from shared.world_messages import AgentObservation
from planning.networks import sha256
from shared.scenario import load_scenario
from shared.shipped import VALUE_NET
from shared.survey_maps import sinr_map_for

scenario = load_scenario()
models = uav_agent.process.Models(scenario, logging.getLogger("agent"))
value, sinr = VALUE_NET.read_bytes(), sinr_map_for(scenario).read_bytes()
models.accept(ValueWeights(version=1, sha256=sha256(value), data=value))
models.accept(SinrMap(version=1, sha256=sha256(sinr), data=sinr, mode="online"))
seen = AgentObservation(
    episode=0, step=1, uav=0, position=(12.5, 0.0), velocity=(0.0, 0.0), heading=0.0,
    destination=(40.0, 30.0), radius=1.0, max_speed=5.0, level=2, below_steps=0,
    others_position=[(0.0, 5.0)], others_velocity=[(1.0, 0.0)], others_radius=[1.0],
    others_present=[True])
decision = models.policy.decide(seen.observation(), models.radio_map)
print(json.dumps({"speed": float(decision.speed[0]),
                  "torch": sorted(name for name in sys.modules if name.split(".")[0] == "torch"),
                  "scipy": sorted(name for name in sys.modules if name.split(".")[0] == "scipy")}))
"""


def test_an_agent_imports_and_flies_without_torch(scenario):
    # A fresh interpreter: this one has torch loaded by other tests.
    done = subprocess.run([sys.executable, "-c", FLY_ONCE], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    flown = json.loads(done.stdout.splitlines()[-1])
    assert flown["torch"] == []
    # An agent is sent its neighbours (the world's k-d tree would cost it 7.5 MiB) and builds
    # its route fields in the compiled core (scipy's Dijkstra would cost 31 MiB).
    assert flown["scipy"] == []
    assert 0.0 <= flown["speed"] <= scenario.uav.max_speed_mps


LOADED = """
import json, sys, importlib
importlib.import_module(sys.argv[1])
print(json.dumps(sorted(name for name in sys.modules if name.split(".")[0] == "torch")))
"""


@pytest.mark.parametrize("module", ["world_sim.process", "jamnav.supervisor",
                                    "jamnav.console.server", "cloud_service.process"])
def test_no_process_but_a_retraining_cloud_loads_torch(module):
    """The world, the supervisor and the console never need torch; the cloud serves weights
    without it and loads it in the background for its first retraining."""
    done = subprocess.run([sys.executable, "-c", LOADED, module], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1]) == []
