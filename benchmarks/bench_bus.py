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
SWAP_RUN_S = "75"  # wall seconds: 60 s after the swap, 600 s of flight at 10 steps/s


def free_endpoint() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def up_report(run_dir: Path, *argv: str) -> dict:
    """The report of a ``jamnav up`` run to its end."""
    subprocess.run([sys.executable, "-m", "jamnav.cli", "up", *argv, "--no-figures",
                    "--endpoint", free_endpoint(), "--run-dir", str(run_dir)],
                   cwd=ROOT, check=True, capture_output=True, timeout=600)
    return json.loads((run_dir / "report.json").read_text())


def _worst(report: dict, key: str) -> float:
    return max(agent[key] for agent in report["agents"].values())


def run() -> list[Figure]:
    figures = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        alone = up_report(tmp / "one", "--uavs", "1", "--episodes", "40", "--map", "perfect")
        figures.append(Figure("agent decision p99, 1 agent (wall, state in -> action out)",
                              _worst(alone, "decision_p99_us"), "us", 1000, True))
        # What of the wall time is waiting: the state queued while the deciding thread was
        # not running (another of its threads, or another process, on the cores).
        figures.append(Figure("agent decision p99, 1 agent: the state waiting for the "
                              "deciding thread (wall)", _worst(alone, "decision_wait_p99_us"),
                              "us"))
        figures.append(Figure("agent decision p99, 1 agent (CPU)",
                              _worst(alone, "decision_cpu_p99_us"), "us"))
        for uavs, episodes, target in ((4, 60, 200), (10, 30, 100)):
            report = up_report(tmp / f"lockstep{uavs}", "--uavs", str(uavs), "--episodes",
                         str(episodes), "--map", "perfect")
            figures.append(Figure(f"lockstep steps/s, {uavs} agent processes",
                                  report["steps_per_second"], "steps/s", target))
            figures.append(Figure(f"agent decision p99, {uavs} agents (wall, worst agent)",
                                  _worst(report, "decision_p99_us"), "us", 1000, True))
            figures.append(Figure(f"agent decision p99, {uavs} agents (CPU, worst agent)",
                                  _worst(report, "decision_cpu_p99_us"), "us", 1000, True))
        # The scene: real time at the default rate (10 steps of 1 s a second), the
        # jammer set over the control topic 15 s in.
        swap = up_report(tmp / "swap", "--uavs", "4", "--realtime", "--duration", SWAP_RUN_S,
                   "--no-jammer", "--swap-jammer-at", "15", "--swap-to", "25,-10,1",
                   "--map", "online")
    events = swap["events"]
    changed = next(e["t"] for e in events if e["type"] == "jammer_changed")

    def after_change(kind: str) -> float:
        return next((e["t"] - changed for e in events if e["type"] == kind
                     and e["t"] >= changed), float("inf"))

    figures.append(Figure("jammer set -> change detected (real time, 4 UAVs, wall)",
                          after_change("change_detected"), "s", 1, True))
    figures.append(Figure("jammer set -> jammer estimated (real time, 4 UAVs, wall)",
                          after_change("jammer_estimated"), "s"))
    figures.append(Figure("jammer set -> new SINR map published (real time, 4 UAVs, wall)",
                          after_change("sinr_weights_published"), "s", 3, True))
    return figures
