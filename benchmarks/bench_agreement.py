"""One result, whichever way it is run: ``jamnav up --lockstep --map online`` (every role its
own process, the cloud on the lockstep clock) against ``jamnav eval --method proposed``, the
same seed, jammers (a fresh one every 10 episodes) and cloud latency: the share of UAV-episodes
with the same outcome, and the two success rates, at the scenario's latency and at 0 s."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from benchmarks.bench_bus import up_report
from benchmarks.common import Figure
from cloud_service.evaluation import evaluate
from shared.paper import JammerSetting
from shared.scenario import load_scenario

UAVS, EPISODES, SEED, SWAP_EVERY = 4, 30, 17, 10
JAMMER = JammerSetting(-25.0, 15.0, 1.0)


def run() -> list[Figure]:
    figures = []
    scenario = load_scenario()
    for latency in (scenario.online_map.cloud_latency_s, 0.0):
        flown = scenario.changed({"online_map.cloud_latency_s": latency})
        with tempfile.TemporaryDirectory() as tmp:
            bus = up_report(Path(tmp) / "up", "--lockstep", "--map", "online", "--uavs",
                            str(UAVS), "--episodes", str(EPISODES), "--seed", str(SEED),
                            "--jammer", f"{JAMMER.x},{JAMMER.y},{JAMMER.power_w}",
                            "--swap-every", str(SWAP_EVERY), "--cloud-latency", str(latency),
                            "--deadline", "10")
        in_process = evaluate(flown, "proposed", EPISODES, SEED, JAMMER, UAVS,
                              swap_every=SWAP_EVERY)
        same = np.array(bus["outcomes"]) == np.array(in_process["outcomes"])
        label = f"latency {latency:g} s, {EPISODES} episodes x {UAVS} UAVs"
        figures += [
            Figure(f"bus vs eval, per-UAV outcome agreement, {label} %", 100 * same.mean(),
                   "%", 99),
            Figure(f"bus success, {label} %", 100 * bus["success_rate"], "%"),
            Figure(f"eval success, {label} %", 100 * in_process["success_rate"], "%"),
            Figure(f"success difference, {label}, points",
                   100 * abs(bus["success_rate"] - in_process["success_rate"]), "points", 1,
                   lower_is_better=True),
        ]
    return figures
