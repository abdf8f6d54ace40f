"""Figures in the style of the paper's Fig. 3: coverage in yellow, GBSs green, jammer red."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402

from shared.radio import JammerParams, RadioModel  # noqa: E402
from shared.scenario import Scenario  # noqa: E402

_COVERAGE_COLOURS = ListedColormap(["white", "#f5e663"])


def jammer_title(jammer: JammerParams | None) -> str:
    if jammer is None:
        return "No jammer"
    return f"Jammer at ({jammer.x:g}, {jammer.y:g}), $P_J$ = {jammer.power_w:g} W"


def draw_coverage(
    ax, scenario: Scenario, jammer: JammerParams | None, resolution: int = 301
) -> float:
    """Draw the coverage map on ``ax``; returns the covered share of the area."""
    radio = RadioModel(scenario)
    xs, ys, reading = radio.grid(scenario, resolution, jammer)
    covered = reading.level > 0
    area = scenario.area
    ax.imshow(
        covered.astype(np.int8),
        origin="lower",
        extent=(area.x_min, area.x_max, area.y_min, area.y_max),
        cmap=_COVERAGE_COLOURS,
        vmin=0,
        vmax=1,
        interpolation="nearest",
    )
    gbs = radio.gbs_xy
    ax.plot(gbs[:, 0], gbs[:, 1], "^", color="tab:green", markersize=9, label="GBS")
    if jammer is not None:
        ax.plot([jammer.x], [jammer.y], "^", color="tab:red", markersize=11, label="jammer")
    ax.set_xlim(area.x_min, area.x_max)
    ax.set_ylim(area.y_min, area.y_max)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    share = float(covered.mean())
    ax.set_title(f"{jammer_title(jammer)} — covered {share:.0%}", fontsize=10)
    return share


def save_coverage_map(
    scenario: Scenario, jammer: JammerParams | None, out: Path, resolution: int = 301
) -> float:
    fig, ax = plt.subplots(figsize=(5.2, 5.2))
    share = draw_coverage(ax, scenario, jammer, resolution)
    ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return share


def plot_reward_curve(log_csv: Path, out: Path, window: int = 200) -> None:
    """Accumulated reward per episode against the straight-line bound (the paper's Fig. 2a),
    both as moving averages over ``window`` episodes."""
    data = np.genfromtxt(log_csv, delimiter=",", names=True)
    data = np.atleast_1d(data)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    if data.size:
        width = max(1, min(window, data.size // 5 or 1))
        kernel = np.ones(width) / width
        episodes = data["episode"][width - 1 :]
        ax.plot(episodes, np.convolve(data["mean_return"], kernel, "valid"),
                label="value network (training, with exploration)")
        ax.plot(episodes, np.convolve(data["straight_bound"], kernel, "valid"), "s-",
                markevery=max(1, episodes.size // 12), color="tab:green",
                label="straight line, ignoring $R_s$ and $R_c$ (upper bound)")
    ax.set_xlabel("episode")
    ax.set_ylabel("accumulated reward per UAV")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def save_trajectory_figure(
    scenario: Scenario,
    panels: list[tuple[JammerParams | None, np.ndarray, np.ndarray, list[str]]],
    out: Path,
) -> None:
    """The paper's Fig. 3: trajectories (lines with dots) and destinations (crosses) over the
    coverage map of each jammer setting. ``panels``: (jammer, positions (T, J, 2),
    destinations (J, 2), outcomes)."""
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.8))
    for ax, (jammer, positions, destinations, outcomes) in zip(np.atleast_1d(axes), panels,
                                                               strict=True):
        draw_coverage(ax, scenario, jammer, resolution=201)
        for uav in range(positions.shape[1]):
            line = ax.plot(positions[:, uav, 0], positions[:, uav, 1], ".-", markersize=3,
                           linewidth=1.2, label=f"UAV {uav}: {outcomes[uav]}")[0]
            ax.plot(*destinations[uav], "x", color=line.get_color(), markersize=9, mew=2)
        ax.legend(loc="lower left", fontsize=6, framealpha=0.85)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
