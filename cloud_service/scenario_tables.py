"""Table I's three maps for a scenario's own jammers (several, driving, blinking): the online
map (``proposed``), the perfect map and the outdated map, each flown on several seeds, the
runs spread over processes. ``jamnav jammers-table`` writes the runs (JSON) and the table
(Markdown)."""

from __future__ import annotations

import json
import multiprocessing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cloud_service.evaluation import RATE_KEYS, evaluate
from planning.compiled import one_planner_thread
from shared.scenario import load_scenario

METHODS = ("proposed", "perfect", "outdated")
SHOWN_RATES = ("success_rate", "disconnection_rate", "collision_rate")


def fly(job: tuple[str, str, int, int]) -> dict[str, Any]:
    """One run: ``(scenario name or path, method, seed, episodes)``, under the scenario's own
    jammers at its cloud latency."""
    name, method, seed, episodes = job
    scenario = load_scenario(name)
    report = evaluate(scenario, method, episodes, seed, scenario.flown_jammers)
    return {"scenario": scenario.name, "method": method, "seed": seed, "episodes": episodes,
            "cloud_latency_s": scenario.online_map.cloud_latency_s, "model": report["model"],
            **{key: report[key] for key in RATE_KEYS}}


def jammer_table_runs(scenarios: Sequence[str], seeds: int, episodes: int, jobs: int,
                      on_run: Callable[[dict[str, Any]], None] | None = None
                      ) -> list[dict[str, Any]]:
    """Every scenario x method x seed, ``jobs`` at a time (each in its own process: the runs
    are independent); ``on_run(run)`` as each ends."""
    work = [(name, method, seed, episodes) for name in scenarios for method in METHODS
            for seed in range(seeds)]
    runs = []
    with multiprocessing.get_context("spawn").Pool(jobs, one_planner_thread) as pool:
        for run in pool.imap_unordered(fly, work):
            runs.append(run)
            if on_run is not None:
                on_run(run)
    order = {(name, method, seed): k for k, (name, method, seed, _) in enumerate(work)}
    return sorted(runs, key=lambda run: order.get(
        (run["scenario"], run["method"], run["seed"]), len(order)))


def write_jammer_table(runs: list[dict[str, Any]], out_dir: Path, command: str
                       ) -> tuple[Path, Path]:
    """``jammers_table.md`` (each scenario x method: the mean over seeds, and the range of
    success) and ``jammers_table.json`` (every run)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path, md_path = out_dir / "jammers_table.json", out_dir / "jammers_table.md"
    json_path.write_text(json.dumps({"command": command, "runs": runs}, indent=1) + "\n",
                         encoding="utf-8")
    first = runs[0]
    lines = ["# A scenario's own jammers: the online, perfect and outdated maps",
             "",
             f"Produced by `{command}`. Success / disconnection / collision in % of "
             f"UAV-episodes, the mean of {len({run['seed'] for run in runs})} seeds x "
             f"{first['episodes']} episodes (every episode counted, the online map's "
             "transients included), at each scenario's cloud latency; the seeds' range of "
             "success in brackets.",
             "",
             "| scenario | map | value network | S / D / C | success, seeds' range |",
             "|---|---|---|---|---|"]
    for name in dict.fromkeys(run["scenario"] for run in runs):
        for method in METHODS:
            chosen = [run for run in runs if run["scenario"] == name and run["method"] == method]
            if not chosen:
                continue
            means = " / ".join(f"{100 * np.mean([run[key] for run in chosen]):.1f}"
                               for key in SHOWN_RATES)
            success = [100 * run["success_rate"] for run in chosen]
            models = ", ".join(sorted({run["model"] for run in chosen}))
            lines.append(f"| {name} | {method} | {models} | {means} | "
                         f"[{min(success):.1f}, {max(success):.1f}] |")
    md_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return md_path, json_path
