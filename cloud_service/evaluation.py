"""Evaluation of the methods of Table I, in-process.

``perfect`` and ``outdated`` fly the lookahead on the true current map or the map without a
jammer. ``proposed`` flies it on the online SINR map: the shipped no-jammer network, updated
by the cloud's own code (memory, change detector, retraining) from the measurements the UAVs
take during the run (the same reports, de-duplicated by the same rule, as the agents upload).
Its episodes fly one after another in a single world, as the real system does, and simulated
time advances one step per world step, so the map adapts at the pace it would in flight. The
headline figures count every episode; the transient (episodes flown on a map older than the
jammer) is also reported apart. ``swap_every`` moves the jammer to a fresh random setting
every so many episodes, the resilience evaluation.
"""

from __future__ import annotations

import tempfile
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from cloud_service.change_handling import RetrainConfig
from cloud_service.rollout import (
    Controller,
    EpisodeResults,
    LookaheadController,
    OrcaController,
    StraightController,
    outcome_rates,
    outdated_maps,
    perfect_maps,
    run_episodes,
)
from cloud_service.rounds import delay_rounds
from cloud_service.sinr_mapping import OnlineSinrMapper
from cloud_service.sinr_memory import SinrMemory
from planning.chosen import lookahead_policy
from planning.maps import RasterMap, sinr_network_raster
from planning.measuring import SpotFilter, scenario_features
from planning.networks import SinrMapNetwork, WeightsError, load_network
from planning.reference import LookaheadPolicy
from shared.measurements import MeasurementBatch, MeasurementSpec
from shared.outcomes import Outcome
from shared.paper import JammerSetting
from shared.scenario import MAX_UAVS, Jammer, Scenario
from shared.shipped import value_net_for, value_net_name
from shared.survey_maps import NoSurveyMapError, sinr_map_for
from world_sim.core import VectorWorld
from world_sim.jammers import JammerSchedule, JammerSet, described_jammers, swapping_jammers

METHODS = ("proposed", "perfect", "outdated", "orca", "straight")
LOOKAHEAD_METHODS = ("proposed", "perfect", "outdated")  # the rest fly without a value network


class EvaluationError(ValueError):
    """Inputs that cannot be evaluated (missing or mismatched weights); one line."""


def load_policy(scenario: Scenario, path: Path) -> LookaheadPolicy:
    """The lookahead with the value network at ``path``; unusable weights are one line."""
    try:
        network, _ = load_network(path, {"kind": "value"})  # its errors name the file
    except WeightsError as exc:
        raise EvaluationError(str(exc)) from None
    try:
        return lookahead_policy(scenario, network)
    except WeightsError as exc:
        raise EvaluationError(f"{path}: {exc}") from None


class OnlineMaps:
    """The proposed method's map provider and upload path: the UAVs' measurements go to an
    ``OnlineSinrMapper`` and the lookahead reads the raster of its network in service."""

    def __init__(self, scenario: Scenario, sinr_map: Path, memory_dir: Path):
        try:
            network, card = load_network(sinr_map, {"kind": "sinr_map"})
        except WeightsError as exc:
            raise EvaluationError(str(exc)) from None
        assert isinstance(network, SinrMapNetwork)
        self.scenario = scenario
        self.now = 0.0
        self.memory = SinrMemory(memory_dir / "measurements.sqlite", MeasurementSpec.of(scenario))
        # No wall-clock budget: a simulated run must not depend on the machine's speed.
        self.mapper = OnlineSinrMapper(
            scenario, self.memory, network, float(card.get("accuracy", 0.99)),
            retrain=RetrainConfig(max_seconds=None), clock=lambda: self.now, background=False,
        )
        # A map the cloud publishes after the upload of step t flies from step t + delay on:
        # the cloud's time to compute it and the UAVs' to receive it, in flight.
        self.delay_steps = delay_rounds(scenario.online_map.cloud_latency_s,
                                        scenario.timing.step_s)
        self.steps_flown = 0
        self._published: deque[tuple[int, int, SinrMapNetwork]] = deque()
        self.served_version, self._served = self.mapper.version, network
        self.service_events: list[dict[str, Any]] = []
        self._raster_version = -1
        self._raster = None
        self.uploads = 0
        self.spots: SpotFilter | None = None

    def __call__(self, world: VectorWorld, rows: np.ndarray) -> RasterMap:
        while self._published and self._published[0][0] <= self.steps_flown:
            _, self.served_version, self._served = self._published.popleft()
            self.service_events.append({"type": "sinr_map_in_service", "t": self.now,
                                        "version": self.served_version})
        if self._raster_version != self.served_version:
            self._raster = sinr_network_raster(self._served, self.scenario)
            self._raster_version = self.served_version
        return RasterMap(self.scenario, [self._raster], np.zeros(rows.size, dtype=np.int64))

    def _note_publication(self) -> None:
        last = self._published[-1][1] if self._published else self.served_version
        if self.mapper.version != last:
            self._published.append((self.steps_flown + self.delay_steps, self.mapper.version,
                                    self.mapper.current_network()))

    def upload(self, world: VectorWorld) -> None:
        """Every UAV that flew this step uploads what its receiver reported along the way,
        de-duplicated as an agent de-duplicates (``SpotFilter``)."""
        self.now += world.dt
        self.steps_flown += 1
        env, uav = np.nonzero(world.measured)
        if env.size == 0:
            return
        if self.spots is None:
            self.spots = SpotFilter(self.scenario, world.num_envs * world.num_uavs)
        xy, levels = world.measured_xy[env, uav], world.measured_level[env, uav]
        kept = self.spots.keep(env * world.num_uavs + uav, xy, levels)
        samples = levels.shape[1]
        taken_at = self.now - world.dt * (1 - np.arange(1, samples + 1) / samples)
        rows, sample = np.nonzero(kept)
        ids = [f"{self.uploads}-{k}" for k in range(rows.size)]
        self.uploads += 1
        batch = MeasurementBatch.of_arrays(
            ids, [f"uav-{u}" for u in uav[rows]], int(world.steps[env[0]]), taken_at[sample],
            scenario_features(self.scenario, xy[rows, sample]), levels[rows, sample],
            world.measured_sinr_db[env, uav][rows, sample],
        )
        self.mapper.ingest(batch)
        self._note_publication()

    def close(self) -> None:
        self.mapper.close()
        self.memory.close()


def transient_episodes(schedule: JammerSchedule, start_version: np.ndarray) -> np.ndarray:
    """Which episodes flew on a map older than the jammer: from each change (the first
    episode under a new setting, or the first episode if it has a jammer, the map starting
    without one) until the first episode that started with a map published since."""
    episodes = len(start_version)
    transient = np.zeros(episodes, dtype=bool)
    previous, changed_at = None, None
    for episode in range(episodes):
        setting = schedule(episode)
        if setting != previous:
            changed_at = episode
            previous = setting
            if episode == 0 and setting is None:
                changed_at = None
        if changed_at is not None and start_version[episode] == start_version[changed_at]:
            transient[episode] = True
        else:
            changed_at = None
    return transient


def _check_integer(name: str, value: Any, low: int, high: int | None = None) -> None:
    """A count or seed refused in one line here rather than deep inside numpy."""
    if (isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low
            or (high is not None and value > high)):
        bound = f"from {low}" + ("" if high is None else f" to {high}")
        raise EvaluationError(f"{name} {value!r}: expected an integer {bound}")


def evaluate(
    scenario: Scenario,
    method: str,
    episodes: int,
    seed: int,
    jammer: JammerSetting | JammerSet | None,
    uavs: int | None = None,
    value_net: Path | None = None,
    sinr_map: Path | None = None,
    on_episode: Callable[[int], None] | None = None,
    swap_every: int | None = None,
    memory_dir: Path | None = None,
) -> dict[str, Any]:
    """Fly ``episodes`` seeded episodes with ``method``; the report of ``jamnav eval``. The
    headline rates count every episode; for ``proposed`` the transient (episodes flown on a
    map older than the jammer) is also reported apart, as is the rest. ``sinr_map``: the
    survey map ``proposed`` starts from (default: the shipped one of the scenario's world).
    ``value_net``: default, the shipped one for the fleet's density and the jammers the run
    starts with (the report's ``model`` names the one flown). ``memory_dir`` keeps the
    cloud's measurement memory of a ``proposed`` run (a scratch directory otherwise)."""
    _check_request(scenario, method, episodes, seed, jammer, uavs, swap_every)
    schedule = swapping_jammers(scenario, jammer, swap_every, seed)
    network = (None if method in ("orca", "straight") else
               value_net_for(value_net, scenario, uavs or scenario.missions.uav_count,
                             schedule(0)))
    with tempfile.TemporaryDirectory(prefix="jamnav-eval-") as scratch:
        controller, online = _controller(scenario, method, network, sinr_map,
                                         memory_dir or Path(scratch))
        results, start_version = _fly(scenario, controller, online, episodes, seed, schedule,
                                      uavs, on_episode)
    report: dict[str, Any] = {
        "method": method,
        "episodes": episodes,
        "uavs": int(results.outcomes.shape[1]),
        "seed": seed,
        "jammers": described_jammers(schedule(0)),
        "swap_every": swap_every,
        "scenario": scenario.name,
        "model": None if network is None else value_net_name(network),
        **outcome_rates(results.outcomes),
    }
    if online is not None:
        report |= _online_report(online, transient_episodes(schedule, start_version),
                                 results.outcomes)
    if swap_every is not None:
        report["swaps"] = [
            {"from_episode": k, "jammers": described_jammers(schedule(k))}
            for k in range(0, episodes, swap_every)]
    report["outcomes"] = [[Outcome(code).label for code in row] for row in results.outcomes]
    report["ended_at_step"] = results.ended_at.tolist()
    return report


def _check_request(scenario: Scenario, method: str, episodes: int, seed: int,
                   jammer: JammerSetting | JammerSet | None, uavs: int | None,
                   swap_every: int | None) -> None:
    """What ``evaluate`` cannot fly, refused in one line before anything is loaded."""
    if method not in METHODS:
        raise EvaluationError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    if not isinstance(scenario, Scenario):
        raise EvaluationError(f"scenario {scenario!r}: expected a Scenario (load_scenario)")
    _check_integer("episodes", episodes, 1)
    _check_integer("seed", seed, 0)
    if uavs is not None:
        _check_integer("uavs", uavs, 1, MAX_UAVS)
    if swap_every is not None:
        _check_integer("swap_every", swap_every, 1)
    if jammer is not None and not isinstance(jammer, JammerSetting) and not (
            isinstance(jammer, tuple) and all(isinstance(one, Jammer) for one in jammer)):
        raise EvaluationError(f"jammer {jammer!r}: expected a JammerSetting(x, y, power_w), a "
                              "scenario's jammers or None")


def _controller(scenario: Scenario, method: str, network: Path | None, sinr_map: Path | None,
                memory_dir: Path) -> tuple[Controller, OnlineMaps | None]:
    """What flies ``method`` (the lookahead's methods with the value network ``network``), and
    for ``proposed`` the online maps it flies on."""
    if method == "orca":
        return OrcaController(scenario), None
    if method == "straight":
        return StraightController(), None
    policy = load_policy(scenario, network)
    if method != "proposed":
        maps = perfect_maps(scenario) if method == "perfect" else outdated_maps(scenario)
        return LookaheadController(policy, maps), None
    try:
        survey = sinr_map or sinr_map_for(scenario)
    except NoSurveyMapError as exc:
        raise EvaluationError(str(exc)) from None
    online = OnlineMaps(scenario, survey, memory_dir)
    return LookaheadController(policy, online), online


def _fly(
    scenario: Scenario,
    controller: Controller,
    online: OnlineMaps | None,
    episodes: int,
    seed: int,
    schedule: JammerSchedule,
    uavs: int | None,
    on_episode: Callable[[int], None] | None,
) -> tuple[EpisodeResults, np.ndarray]:
    """Fly the episodes; with online maps, in one world (the map adapts between episodes,
    as in the real system), noting the map version each episode starts on."""
    start_version = np.zeros(episodes, dtype=np.int64)

    def episode_done(episode: int) -> None:
        if online is not None and episode + 1 < episodes:
            start_version[episode + 1] = online.served_version
        if on_episode is not None:
            on_episode(episode)

    try:
        results = run_episodes(
            scenario, controller, episodes, seed, schedule, uavs,
            num_envs=1 if online else 64,
            on_step=online.upload if online else None,
            on_episode=episode_done,
            record_measurements=online is not None,
        )
    finally:
        if online is not None:
            online.close()
    return results, start_version


def _online_report(online: OnlineMaps, transient: np.ndarray,
                   outcomes: np.ndarray) -> dict[str, Any]:
    """The proposed method's part of the report: the transient and steady episodes apart,
    and what the cloud did and when."""
    report: dict[str, Any] = {}
    for part, rows in (("transient", transient), ("steady", ~transient)):
        report[part] = {"episodes": int(rows.sum()),
                        **(outcome_rates(outcomes[rows]) if rows.any() else {})}
    report["transient"]["rule"] = ("episodes flown on a map older than the jammer: from a "
                                   "change until a map published since")
    report["events"] = sorted(online.mapper.events + online.service_events,
                              key=lambda event: event["t"])
    report["cloud_latency_s"] = online.scenario.online_map.cloud_latency_s
    report["flight_seconds"] = round(online.now, 3)  # what the cloud saw flown, all told
    return report


TABLE_METHODS = ("proposed", "outdated", "perfect")
RATE_KEYS = ("success_rate", "disconnection_rate", "collision_rate", "timeout_rate")


def table_one(
    scenario: Scenario,
    episodes: int,
    seed: int,
    value_nets: dict[str, Path],
    on_run: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Table I's four jammer settings x three methods, for each named value network."""
    from shared.paper import TABLE_I_JAMMERS, TABLE_I_RESULTS

    rows = []
    for setting_index, setting in enumerate(TABLE_I_JAMMERS):
        for method in TABLE_METHODS:
            paper = dict(zip(("success", "disconnection", "collision"),
                             TABLE_I_RESULTS[method][setting_index], strict=True))
            for name, path in value_nets.items():
                if on_run is not None:
                    on_run(f"{setting.label} {method} {name}")
                report = evaluate(scenario, method, episodes, seed, setting, value_net=path)
                row = {"jammer": setting.label, "method": method, "value_net": name,
                       **{key: report[key] for key in RATE_KEYS},
                       "episodes": episodes,
                       "transient_episodes": report.get("transient", {}).get("episodes", 0),
                       **{f"paper_{key}": value / 100 for key, value in paper.items()}}
                rows.append(row)
    return rows


def write_table(rows: list[dict[str, Any]], out_dir: Path, command: str) -> tuple[Path, Path]:
    import csv

    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path, md_path = out_dir / "table1.csv", out_dir / "table1.md"
    with csv_path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

    def pct(value: float) -> str:
        return "n/a" if value != value else f"{100 * value:.1f}"

    lines = [
        "# Table I: ours beside the paper's",
        "",
        f"Produced by `{command}`. Success / disconnection / collision / timeout in % of",
        "UAV-episodes; the paper's figures (success / disconnection / collision) and the",
        "difference in success. Every episode counts, the transient of `proposed` included (the",
        "episodes flown on the map without a jammer until the first corrected map); its length",
        "is given.",
        "",
        "| jammer | method | value network | ours: S / D / C / T | paper: S / D / C | "
        "delta S | transient |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        ours = " / ".join(pct(row[key]) for key in RATE_KEYS)
        paper = " / ".join(pct(row[f"paper_{key}"]) for key in
                           ("success", "disconnection", "collision"))
        delta = 100 * (row["success_rate"] - row["paper_success"])
        transient = row["transient_episodes"] if row["method"] == "proposed" else ""
        lines.append(f"| {row['jammer']} | {row['method']} | {row['value_net']} | {ours} | "
                     f"{paper} | {delta:+.1f} | {transient} |")
    md_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return md_path, csv_path


def trajectories(
    scenario: Scenario, setting: JammerSetting | None, seed: int, value_net: Path
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """One episode on the true map: positions (steps + 1, J, 2), destinations (J, 2) and
    each UAV's outcome, for the paper's Fig. 3."""
    policy = load_policy(scenario, value_net)
    track: list[np.ndarray] = []
    destinations: list[np.ndarray] = []

    def record(world: VectorWorld) -> None:
        if not track:
            track.append(world.start[0].copy())
            destinations.append(world.destination[0].copy())
        track.append(world.position[0].copy())

    results = run_episodes(scenario, LookaheadController(policy, perfect_maps(scenario)), 1,
                           seed, setting, num_envs=1, on_step=record)
    return (np.stack(track), destinations[0],
            [Outcome(code).label for code in results.outcomes[0]])
