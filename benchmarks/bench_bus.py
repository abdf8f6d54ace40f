"""The runtime over zenoh, every role its own OS process behind a loopback router (``jamnav
up``): lockstep steps/s with 4 and 10 agents, the agents' decision time (state in -> action
out, measured inside each agent), and the live jammer-swap-to-new-map loop."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.common import Figure

ROOT = Path(__file__).resolve().parent.parent


def _up(run_dir: Path, *argv: str) -> dict:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{probe.getsockname()[1]}"
    subprocess.run([sys.executable, "-m", "jamnav.cli", "up", *argv, "--no-figures",
                    "--endpoint", endpoint, "--run-dir", str(run_dir)],
                   cwd=ROOT, check=True, capture_output=True, timeout=600)
    return json.loads((run_dir / "report.json").read_text())


def _worst(report: dict, key: str) -> float:
    return max(agent[key] for agent in report["agents"].values())


def run() -> list[Figure]:
    figures = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        alone = _up(tmp / "one", "--uavs", "1", "--episodes", "40", "--map", "perfect")
        figures.append(Figure("agent decision p99, 1 agent (wall, state in -> action out)",
                              _worst(alone, "decision_p99_us"), "us", 1000, True))
        for uavs, episodes, target in ((4, 60, 200), (10, 30, 100)):
            report = _up(tmp / f"lockstep{uavs}", "--uavs", str(uavs), "--episodes",
                         str(episodes), "--map", "perfect")
            figures.append(Figure(f"lockstep steps/s, {uavs} agent processes",
                                  report["steps_per_second"], "steps/s", target))
            figures.append(Figure(f"agent decision p99, {uavs} agents (wall, worst agent)",
                                  _worst(report, "decision_p99_us"), "us", 1000, True))
            figures.append(Figure(f"agent decision p99, {uavs} agents (CPU, worst agent)",
                                  _worst(report, "decision_cpu_p99_us"), "us", 1000, True))
        swap = _up(tmp / "swap", "--uavs", "4", "--duration", "30", "--no-jammer",
                   "--swap-jammer-at", "5", "--swap-to", "0,0,1", "--map", "online")
    events = swap["events"]
    changed = next(e["t"] for e in events if e["type"] == "jammer_changed")
    detected = [e["t"] - changed for e in events
                if e["type"] == "change_detected" and e["t"] >= changed]
    published = [e["t"] - changed for e in events
                 if e["type"] == "sinr_weights_published" and e["t"] >= changed]
    figures.append(Figure("jammer swap -> change detected (lockstep, 4 UAVs)",
                          detected[0] if detected else float("nan"), "s"))
    figures.append(Figure("jammer swap -> new SINR weights published (4 UAVs)",
                          published[0] if published else float("nan"), "s", 3, True))
    return figures
