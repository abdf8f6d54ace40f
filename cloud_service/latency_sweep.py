"""How fast must the cloud be? Missions flown on the online map against the cloud's latency.

The jammer moves to a fresh random setting every few episodes, and each run flies the proposed
method with the map a change triggers put in service ``latency`` seconds of flight later
(``online_map.cloud_latency_s``). The perfect map, which knows every change at once, flies the
same episodes as the bound. ``jamnav cloud-latency`` writes the runs (JSON), a table (Markdown)
and the figure (PNG).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cloud_service.evaluation import RATE_KEYS, evaluate
from shared.scenario import Scenario

LATENCIES_S = (0.0, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0)


def sweep(scenario: Scenario, latencies: Sequence[float], seeds: int, episodes: int,
          swap_every: int, uavs: int | None = None,
          on_run: Callable[[dict[str, Any], str], None] | None = None) -> dict[str, Any]:
    """Every seed's perfect-map run and one proposed run per latency, the same episodes and
    jammers each; returns the runs' rates (JSON-ready). ``on_run(result so far, label)``
    after each run."""
    first = scenario.flown_jammers
    runs: list[dict[str, Any]] = []
    result = {"scenario": scenario.name, "episodes": episodes, "seeds": seeds,
              "swap_every": swap_every, "uavs": uavs or scenario.missions.uav_count,
              "latencies_s": [float(latency) for latency in latencies], "runs": runs}
    for seed in range(seeds):
        cases = [("perfect", None)] + [("proposed", latency) for latency in latencies]
        for method, latency in cases:
            flown = scenario if latency is None else scenario.changed(
                {"online_map.cloud_latency_s": float(latency)})
            report = evaluate(flown, method, episodes, seed, first, uavs, swap_every=swap_every)
            runs.append({"method": method, "cloud_latency_s": latency, "seed": seed,
                         **{key: report[key] for key in RATE_KEYS}})
            if on_run is not None:
                on_run(result, f"seed {seed}, {method}"
                       + ("" if latency is None else f", {latency:g} s"))
    return result


def save_runs(result: dict[str, Any], out_dir: Path, command: str) -> Path:
    """The runs so far, as ``cloud_latency_<scenario>.json``: a long sweep stopped keeps
    what it flew."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"cloud_latency_{result['scenario']}.json"
    path.write_text(json.dumps({**result, "command": command}, indent=1) + "\n",
                    encoding="utf-8")
    return path


def summary(result: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per latency (and the perfect map's, latency None): each rate's mean and
    standard deviation over the seeds, in percent."""
    rows = []
    for latency in [None, *result["latencies_s"]]:
        runs = [run for run in result["runs"] if run["cloud_latency_s"] == latency]
        row: dict[str, Any] = {"cloud_latency_s": latency}
        for key in RATE_KEYS:
            rates = 100 * np.array([run[key] for run in runs])
            row[key] = (float(rates.mean()), float(rates.std(ddof=1)) if rates.size > 1 else 0.0)
        rows.append(row)
    return rows


def write_outputs(result: dict[str, Any], out_dir: Path, command: str) -> list[Path]:
    """``cloud_latency_<scenario>.json``, ``.md`` and ``.png`` in ``out_dir``."""
    stem = save_runs(result, out_dir, command).with_suffix("")
    rows = summary(result)
    seeds = result["seeds"]
    spread = "mean +- sd over the seeds" if seeds > 1 else "seed 0"
    lines = [f"Command: `{command}`. {result['uavs']} UAVs, {result['episodes']} episodes x "
             f"{seeds} seed{'s' if seeds > 1 else ''}, the jammer moved every "
             f"{result['swap_every']} episodes; {spread}, %.", "",
             "| cloud latency (s) | success | disconnection | collision |", "|---|---|---|---|"]
    for row in rows:
        label = "perfect map" if row["cloud_latency_s"] is None else f"{row['cloud_latency_s']:g}"
        cells = [f"{mean:.1f}" + (f" +- {sd:.1f}" if seeds > 1 else "") for mean, sd in
                 (row[key] for key in ("success_rate", "disconnection_rate", "collision_rate"))]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    _plot(rows, result, stem.with_suffix(".png"))
    return [stem.with_suffix(suffix) for suffix in (".json", ".md", ".png")]


def _plot(rows: list[dict[str, Any]], result: dict[str, Any], out: Path) -> None:
    # Imported here: the sweep itself draws nothing.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    perfect, online = rows[0], rows[1:]
    latency = np.array([row["cloud_latency_s"] for row in online])
    success = np.array([row["success_rate"] for row in online])
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    ax.errorbar(latency, success[:, 0], yerr=success[:, 1], marker="o", color="#0072B2",
                capsize=3, label="online map")
    ax.axhline(perfect["success_rate"][0], color="#009E73", ls="--", label="perfect map")
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xticks(latency, [f"{value:g}" for value in latency])
    ax.set_xlim(-0.3, latency.max() * 1.3)
    top = max(perfect["success_rate"][0], (success[:, 0] + success[:, 1]).max())
    ax.set_ylim(min((success[:, 0] - success[:, 1]).min(), top - 5) - 1, min(top + 1.5, 100.5))
    ax.set_xlabel("cloud latency (s of flight)")
    ax.set_ylabel("success (%)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title(f"{result['scenario']}: jammer moved every {result['swap_every']} episodes, "
                 f"{result['uavs']} UAVs", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
