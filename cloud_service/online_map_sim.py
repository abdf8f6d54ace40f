"""Simulated uploads for the online SINR map, and the paper's Fig. 2b from them.

A fleet of UAVs crosses the area on straight legs between waypoints drawn uniformly over it,
at the scenario's top speed, reporting along its path as an agent does. This is not a
mission simulation: it spreads measurements over the map the way through-traffic does, which
is what the cloud's detector and retraining see. The jammer follows a schedule; everything
runs in simulated time through ``OnlineSinrMapper`` in synchronous mode, so a seed gives one
timeline.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cloud_service.change_detection import ChangeDetector
from cloud_service.change_handling import RetrainConfig
from cloud_service.simulated_measurements import labelled_batch
from cloud_service.sinr_mapping import RECENT_KEPT, OnlineSinrMapper
from cloud_service.sinr_memory import SinrMemory
from planning.measuring import SpotFilter, scenario_features
from planning.networks import SinrMapNetwork, predict_levels
from shared.measurements import MeasurementBatch, MeasurementSpec
from shared.paper import TABLE_I_JAMMERS, JammerSetting, jammer_params
from shared.radio import Jammers, RadioModel
from shared.scenario import Scenario

DEFAULT_UAVS = 20  # ~200 reports a step: a busy sky, without making the figure a long run


class Fleet:
    """UAVs on straight legs between uniform waypoints, reporting along their path as the
    agents do: ``uav.measurements_per_step`` reports a step with the receiver's noise,
    de-duplicated by the agents' rule (``SpotFilter``)."""

    def __init__(self, scenario: Scenario, uavs: int, rng: np.random.Generator):
        self.scenario = scenario
        self.radio = RadioModel(scenario)
        self.rng = rng
        self.step_length = scenario.uav.max_speed_mps * scenario.timing.step_s
        self.sources = np.array([f"uav-{i}" for i in range(uavs)])
        self.spots = SpotFilter(scenario, uavs)
        self.position = self._draw(uavs)
        self.previous = self.position.copy()
        self.waypoint = self._draw(uavs)

    def _draw(self, n: int) -> np.ndarray:
        area = self.scenario.area
        return self.rng.uniform((area.x_min, area.y_min), (area.x_max, area.y_max), (n, 2))

    def fly(self) -> None:
        """One time step along the legs; a UAV that reaches its waypoint gets a new one."""
        offset = self.waypoint - self.position
        distance = np.hypot(offset[:, 0], offset[:, 1])
        arrived = distance <= self.step_length
        heading = offset / np.maximum(distance, 1e-9)[:, None]
        self.previous = self.position
        self.position = np.where(arrived[:, None], self.waypoint,
                                 self.position + heading * self.step_length)
        self.waypoint[arrived] = self._draw(int(arrived.sum()))

    def uploads(self, jammer: Jammers, time: float, step: int) -> MeasurementBatch:
        """What the UAVs report along their last step and keep, stamped along the step."""
        samples = self.scenario.uav.measurements_per_step
        share = np.arange(1, samples + 1) / samples
        xy = self.previous[:, None] + share[None, :, None] * (self.position - self.previous)[
            :, None]
        reports = self.radio.measured_reports(self.radio.evaluate(xy, jammer).sinr_db, self.rng)
        rows, sample = np.nonzero(self.spots.keep(np.arange(len(xy)), xy, reports.level))
        taken_at = time - self.scenario.timing.step_s * (1 - share)
        return labelled_batch(self.scenario, xy[rows, sample], reports.level[rows, sample],
                              self.rng, time=taken_at[sample], step=step,
                              source=self.sources[rows].tolist(),
                              sinr_db=reports.sinr_db[rows, sample])


@dataclass(frozen=True)
class Schedule:
    """The jammer over simulated time: ``settings[i]`` from ``starts[i]`` on."""

    starts: tuple[float, ...]
    settings: tuple[JammerSetting | None, ...]

    @classmethod
    def table_i(cls, first_change: float = 60.0, period: float = 120.0) -> Schedule:
        """No jammer, then Table I's four settings in turn, each for ``period`` seconds."""
        starts = (0.0,) + tuple(first_change + i * period for i in range(len(TABLE_I_JAMMERS)))
        return cls(starts, (None, *TABLE_I_JAMMERS))

    def at(self, t: float) -> JammerSetting | None:
        index = int(np.searchsorted(self.starts, t, side="right")) - 1
        return self.settings[max(index, 0)]

    def label(self, setting: JammerSetting | None) -> str:
        return "no jammer" if setting is None else setting.label


def simulate_online_map(
    scenario: Scenario,
    network: SinrMapNetwork,
    accuracy: float,
    schedule: Schedule,
    duration: float,
    *,
    uavs: int = DEFAULT_UAVS,
    seed: int = 0,
    test_points: int = 5000,
    detector: ChangeDetector | None = None,
    retrain: RetrainConfig | None = None,
    on_step: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Fly the fleet for ``duration`` simulated seconds through a synchronous mapper;
    ``on_step(steps done, steps)`` before the first step and after each.

    Every step the true accuracy of the network in service is measured on ``test_points``
    fixed uniform positions under the jammer of the moment. Returns the timeline (JSON-ready).
    Retraining runs without its wall-clock budget unless ``retrain`` sets one, so the
    timeline does not depend on how busy the machine is.
    """
    rng = np.random.default_rng(seed)
    dt = scenario.timing.step_s
    clock = SimulatedClock()
    memory = SinrMemory(":memory:", MeasurementSpec.of(scenario))
    mapper = OnlineSinrMapper(scenario, memory, network, accuracy, detector=detector,
                              retrain=retrain or RetrainConfig(max_seconds=None),
                              clock=clock, background=False, seed=seed)
    probe = AccuracyProbe(scenario, schedule, test_points, seed + 1)
    fleet = Fleet(scenario, uavs, rng)
    series: dict[str, list] = {"t": [], "accuracy": [], "version": [], "monitor": []}
    steps = int(round(duration / dt))
    if on_step is not None:
        on_step(0, steps)
    for step in range(steps):
        clock.now = step * dt
        setting = schedule.at(clock.now)
        fleet.fly()
        mapper.ingest(fleet.uploads(jammer_params(scenario, setting), clock.now, step))
        series["monitor"].append(mapper.state()["recent_accuracy"])
        series["accuracy"].append(probe.accuracy(mapper, setting))
        series["t"].append(clock.now)
        series["version"].append(mapper.version)
        if on_step is not None:
            on_step(step + 1, steps)
    memory.close()
    return {
        "scenario": scenario.name,
        "seed": seed,
        "uavs": uavs,
        "step_s": dt,
        "test_points": test_points,
        "jammer_changes": [{"t": start, "jammer": schedule.label(setting)}
                           for start, setting in zip(schedule.starts, schedule.settings,
                                                     strict=True)],
        "detector": {"probability_floor": mapper.detector.floor,
                     "threshold": mapper.detector.threshold},
        **series,
        "events": mapper.events,
    }


class SimulatedClock:
    """The mapper's clock in a simulation: the time the simulation sets."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class AccuracyProbe:
    """The true accuracy of the map in service: its levels at fixed uniform positions
    against the true ones under the jammer of the moment. The map's levels are predicted
    again only when a new map is in service."""

    def __init__(self, scenario: Scenario, schedule: Schedule, points: int, seed: int):
        area = scenario.area
        xy = np.random.default_rng(seed).uniform(
            (area.x_min, area.y_min), (area.x_max, area.y_max), size=(points, 2))
        self.features = scenario_features(scenario, xy)
        radio = RadioModel(scenario)
        self.truth = {setting: radio.evaluate(xy, jammer_params(scenario, setting)).level
                      for setting in set(schedule.settings)}
        self.predicted: np.ndarray | None = None
        self.version: int | None = None

    def accuracy(self, mapper: OnlineSinrMapper, setting: JammerSetting | None) -> float:
        if self.version != mapper.version:
            self.predicted = predict_levels(mapper.current_network(), self.features)
            self.version = mapper.version
        return float((self.predicted == self.truth[setting]).mean())


def save_online_map_figure(timeline: dict[str, Any], out: Path) -> None:
    """Fig. 2b: accuracy of the online map over time; writes ``out`` (PNG) and the timeline
    as JSON beside it."""
    # Imported here: benchmarks and tests run the simulation without drawing anything.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.2))
    ax.plot(timeline["t"], np.array(timeline["accuracy"]) * 100, color="tab:blue", lw=1.4,
            label="online map, fresh positions")
    monitor = [np.nan if a is None else 100 * a for a in timeline["monitor"]]
    ax.plot(timeline["t"], monitor, color="tab:gray", lw=0.8, alpha=0.7,
            label=f"monitor, last {RECENT_KEPT} uploads")
    for change in timeline["jammer_changes"][1:]:
        ax.axvline(change["t"], color="tab:red", ls="--", lw=0.9)
        ax.annotate(change["jammer"], (change["t"], 0.02), xycoords=("data", "axes fraction"),
                    rotation=90, fontsize=7, color="tab:red", ha="right", va="bottom")
    _mark(ax, timeline, "change_detected", "v", "tab:orange", "change detected")
    _mark(ax, timeline, "sinr_weights_published", "^", "tab:green", "new weights published")
    ax.set_xlabel("simulated time (s)")
    ax.set_ylabel("level accuracy (%)")
    ax.set_ylim(min(70.0, min(timeline["accuracy"]) * 100 - 2), 100.5)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=7)
    ax.set_title(f"Online SINR map, {timeline['uavs']} UAVs uploading every "
                 f"{timeline['step_s']:g} s (seed {timeline['seed']})", fontsize=10)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    out.with_suffix(".json").write_text(json.dumps(timeline, indent=1) + "\n", encoding="utf-8")


def _mark(ax, timeline: dict[str, Any], kind: str, marker: str, colour: str, label: str) -> None:
    times = np.array(timeline["t"])
    accuracy = np.array(timeline["accuracy"]) * 100
    at = [event["t"] for event in timeline["events"] if event["type"] == kind]
    if at:
        index = np.clip(np.searchsorted(times, at), 0, len(times) - 1)
        ax.plot(at, accuracy[index], marker, color=colour, ms=7, ls="none", label=label)
