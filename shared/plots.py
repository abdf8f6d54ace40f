"""Figures in the style of the paper's Fig. 3: coverage in yellow, GBSs green, jammer red.

Colours are from the Okabe-Ito palette, safe for colour-blind readers. The UAVs' colours are
kept apart from the GBSs' green, the jammer's vermillion and the coverage's yellow, and the
markers differ in shape as well as colour."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from shared.radio import Jammers, RadioModel, as_jammers  # noqa: E402
from shared.scenario import Scenario  # noqa: E402

_COVERAGE_COLOURS = ListedColormap(["white", "#f7ec8f"])
GBS_COLOUR, JAMMER_COLOUR = "#009E73", "#D55E00"
# One colour per UAV, cycled with a dashed line style past the first eight.
UAV_COLOURS = ("#0072B2", "#CC79A7", "#000000", "#56B4E9", "#882255", "#332288", "#999933",
               "#777777")


def jammer_title(jammers: Jammers) -> str:
    jammers = as_jammers(jammers)
    if not jammers:
        return "No jammer"
    if len(jammers) > 1:
        return f"{len(jammers)} jammers, $P_J$ = " + ", ".join(
            f"{jammer.power_w:g}" for jammer in jammers) + " W"
    jammer = jammers[0]
    return f"Jammer at ({jammer.x:g}, {jammer.y:g}), $P_J$ = {jammer.power_w:g} W"


def draw_coverage(
    ax, scenario: Scenario, jammers: Jammers, resolution: int = 301
) -> float:
    """Draw the coverage map on ``ax``; returns the covered share of the area."""
    radio = RadioModel(scenario)
    xs, ys, reading = radio.grid(scenario, resolution, jammers)
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
    ax.plot(gbs[:, 0], gbs[:, 1], "^", color=GBS_COLOUR, markersize=9, label="GBS")
    for index, jammer in enumerate(as_jammers(jammers)):
        ax.plot([jammer.x], [jammer.y], "*", color=JAMMER_COLOUR, markersize=16, mec="black",
                mew=0.8, label="jammer" if index == 0 else None)
    ax.set_xlim(area.x_min, area.x_max)
    ax.set_ylim(area.y_min, area.y_max)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    share = float(covered.mean())
    ax.set_title(f"{jammer_title(jammers)} — covered {share:.0%}", fontsize=10)
    return share


def save_coverage_map(
    scenario: Scenario, jammers: Jammers, out: Path, resolution: int = 301
) -> float:
    fig, ax = plt.subplots(figsize=(5.2, 5.2))
    share = draw_coverage(ax, scenario, jammers, resolution)
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


def draw_trajectories(ax, positions: np.ndarray, destinations: np.ndarray,
                      outcomes: list[str]) -> None:
    """Each UAV's path from its start (circle) to where it ended (square), its destination a
    cross of its colour; ``positions`` (T, J, 2), ``destinations`` (J, 2). The legend sits
    below the map, where it hides no path."""
    for uav in range(positions.shape[1]):
        colour = UAV_COLOURS[uav % len(UAV_COLOURS)]
        style = "-" if uav < len(UAV_COLOURS) else "--"
        track = positions[:, uav]
        ax.plot(track[:, 0], track[:, 1], style, color=colour, lw=1.5,
                label=f"UAV {uav}: {outcomes[uav]}")
        ax.plot(*track[0], "o", color=colour, ms=5)
        ax.plot(*track[-1], "s", color=colour, ms=6, mfc="white", mew=1.5)
        ax.plot(*destinations[uav], "X", color=colour, ms=10, mec="white", mew=0.8)
    key = [Line2D([], [], ls="none", marker=m, color="0.3", ms=s, mfc=f, label=label)
           for m, s, f, label in (("o", 5, "0.3", "start"), ("s", 6, "white", "end"),
                                  ("X", 9, "0.3", "destination"))]
    key.append(Patch(facecolor=_COVERAGE_COLOURS(1), edgecolor="0.6", label="covered"))
    handles, _ = ax.get_legend_handles_labels()
    ax.legend(handles=handles + key, loc="upper center", bbox_to_anchor=(0.5, -0.13),
              ncol=3, fontsize=7, frameon=False)


def save_trajectory_figure(
    scenario: Scenario,
    panels: list[tuple[str, Jammers, np.ndarray, np.ndarray, list[str]]],
    out: Path,
    dpi: int = 100,
) -> None:
    """Trajectories over the coverage map of each panel's jammers (the paper's Fig. 3).
    ``panels``: (title, jammers, positions (T, J, 2), destinations (J, 2), outcomes)."""
    fig, axes = plt.subplots(1, len(panels), figsize=(4.8 * len(panels), 6.0), squeeze=False)
    for ax, (title, jammers, positions, destinations, outcomes) in zip(axes[0], panels,
                                                                       strict=True):
        draw_coverage(ax, scenario, jammers, resolution=201)
        draw_trajectories(ax, positions, destinations, outcomes)
        if title:
            ax.set_title(f"{title}\n{ax.get_title()}", fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
