"""Adaptation to a jammer change with four UAVs, in both radio worlds: how soon the change is
detected, how soon a corrected map is out and how right it is, where the jammer is found, and
how often a still jammer is taken for a change. One CPU thread.

Uploads come from ``online_map_sim.Fleet``: four UAVs on straight legs across the area at top
speed, reporting along their path as the agents do (``uav.measurements_per_step`` reports a
step, the receiver's noise, the agents' de-duplication). The mapper runs inline in simulated
time, so every figure is seconds of flight after the change, the same on any machine.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from benchmarks.common import Figure
from cloud_service.change_detection import ChangeDetector
from cloud_service.evaluation import evaluate
from cloud_service.jammer_estimation import estimate_jammer
from cloud_service.no_jammer_belief import SinrBelief
from cloud_service.online_map_sim import Fleet
from cloud_service.report_likelihood import report_shares
from cloud_service.rounds import delay_rounds
from cloud_service.sinr_mapping import OnlineSinrMapper
from cloud_service.sinr_memory import SinrMemory
from cloud_service.upload_positions import positions_from_features
from planning.measuring import scenario_features
from planning.networks import SinrMapNetwork, load_network, predict_levels, predict_probabilities
from shared.measurements import MeasurementBatch, MeasurementSpec
from shared.paper import JammerSetting, jammer_params
from shared.radio import RadioModel
from shared.scenario import Scenario, load_scenario
from shared.survey_maps import sinr_map_for
from world_sim.jammers import random_jammer

UAVS = 4
CHANGES = 20
WARM_UP_S = 20.0  # flight before the change, so the fleet is spread over the area
# Where the receivers report dB, the flight before the change in which the cloud gathers its
# no-jammer reference as well (cloud_service/sinr_reference.py): a fleet in service has flown.
REFERENCE_WARM_UP_S = 300.0
AFTER_S = 60.0  # flight after the change
STILL_S = 1800.0  # "30 min of flight with a still jammer"
LOCALIZATION_SETTINGS = 50
LOCALIZATION_FLIGHT_S = 10.0
TOLD_SD_DB = 0.05  # how well the localization rows "told the true no-jammer world" know it
TRUTH_SPACING_M = 2.0
# How much of a change the fleet can see within the detection target's 5 s: the most the new
# jammer lowers the true SINR at any report taken in that time.
VISIBLE_WITHIN_S = 5.0
# Flight after a change at which the map in service (the scenario's cloud latency counted) is
# scored against the truth: a change the old map still describes is served right.
SERVED_AT_S = (0.0, 2.0, 5.0, 10.0, 30.0)
SERVED_TARGETS = {"icc2021": {10.0: 95.0, 30.0: 97.0}}  # 10th percentile over the changes, %


def run() -> list[Figure]:
    """The paper's level reports in both worlds; in the shadowed world also after the fleet
    has flown a while, with level reports and with dB reports, as NR's receivers give."""
    shadowed = load_scenario("icc2021-shadowed")
    reporting = shadowed.changed({"uav.report": "db"}, name="icc2021-shadowed, dB reports")
    figures = adaptation_figures(load_scenario("icc2021"), WARM_UP_S)
    figures += adaptation_figures(shadowed, WARM_UP_S)
    figures += adaptation_figures(shadowed, REFERENCE_WARM_UP_S, quiet=False)
    figures += adaptation_figures(reporting, REFERENCE_WARM_UP_S)
    return figures + localization_figures(shadowed) + localization_figures(reporting)


class TruthGrid:
    """The true levels (shadowing included, no receiver noise) over the area, to score maps."""

    def __init__(self, scenario: Scenario):
        area = scenario.area
        xs = np.arange(area.x_min, area.x_max + 1e-9, TRUTH_SPACING_M)
        ys = np.arange(area.y_min, area.y_max + 1e-9, TRUTH_SPACING_M)
        self.xy = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
        self.features = scenario_features(scenario, self.xy)
        self.radio = RadioModel(scenario)
        self.scenario = scenario
        self._levels: dict[JammerSetting | None, np.ndarray] = {}

    def levels(self, setting: JammerSetting | None) -> np.ndarray:
        """The true level at every point with the jammer of ``setting`` (None: none), worked
        out once per setting: a trial scores several maps against the same truth."""
        if setting not in self._levels:
            self._levels[setting] = self.radio.evaluate(
                self.xy, jammer_params(self.scenario, setting)).level
        return self._levels[setting]

    def accuracy(self, network: SinrMapNetwork, setting: JammerSetting | None) -> float:
        return float((predict_levels(network, self.features) == self.levels(setting)).mean())

    def moved(self, setting: JammerSetting) -> float:
        """The share of the area whose level the jammer of ``setting`` changes."""
        return float((self.levels(setting) != self.levels(None)).mean())

    def sinr_shift_db(self, uploads: MeasurementBatch, setting: JammerSetting) -> float:
        """The most the jammer of ``setting`` lowers the true SINR at any of ``uploads``."""
        xy = positions_from_features(self.scenario, uploads.features)
        jammed = self.radio.evaluate(xy, jammer_params(self.scenario, setting)).sinr_db
        return float(np.max(self.radio.evaluate(xy).sinr_db - jammed, initial=0.0))


def _mapper(scenario: Scenario, now: list[float], seed: int) -> OnlineSinrMapper:
    network, card = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    memory = SinrMemory(":memory:", MeasurementSpec.of(scenario))
    return OnlineSinrMapper(scenario, memory, network, float(card["accuracy"]),
                            clock=lambda: now[0], background=False, seed=seed)


def _trial(scenario: Scenario, truth: TruthGrid, seed: int, warm_up_s: float) -> dict:
    """No jammer for ``warm_up_s``, then a random jammer for AFTER_S."""
    rng = np.random.default_rng(seed)
    setting = random_jammer(scenario, rng)
    now = [0.0]
    mapper = _mapper(scenario, now, seed)
    survey = truth.accuracy(mapper.current_network(), setting)  # the map flown until one comes
    fleet = Fleet(scenario, UAVS, rng)
    dt = scenario.timing.step_s
    first_map, accuracy_first, accuracy_30, evidence = None, None, None, None
    shift_db = 0.0
    # Maps by the flight after the change from which they are in service: the one in service
    # at the change, then each published after it, the cloud's latency later.
    delay_s = delay_rounds(scenario.online_map.cloud_latency_s, dt) * dt
    in_service: list[tuple[float, SinrMapNetwork]] = []
    for step in range(int((warm_up_s + AFTER_S) / dt)):
        now[0] = step * dt
        after = now[0] - warm_up_s
        fleet.fly()
        version = mapper.version
        uploads = fleet.uploads(jammer_params(scenario, setting if after >= 0 else None),
                                now[0], step)
        if evidence is None and after >= 0 and _contradicts(mapper, uploads):
            evidence = after
        if 0 <= after < VISIBLE_WITHIN_S:
            shift_db = max(shift_db, truth.sinr_shift_db(uploads, setting))
        if after >= 0 and not in_service:
            in_service.append((0.0, mapper.current_network()))
        mapper.ingest(uploads)
        if mapper.version != version and after >= 0:
            in_service.append((after + delay_s, mapper.current_network()))
        if mapper.version != version and first_map is None and after >= 0:
            first_map = after + dt
            accuracy_first = truth.accuracy(mapper.current_network(), setting)
        if accuracy_30 is None and after >= 30.0:
            accuracy_30 = truth.accuracy(mapper.current_network(), setting)
    detected = [e["t"] - warm_up_s for e in mapper.events if e["type"] == "change_detected"]
    mapper.close()
    served = {at: truth.accuracy([net for since, net in in_service if since <= at][-1], setting)
              for at in SERVED_AT_S}
    return {"setting": setting, "detected": detected, "first_map": first_map, "served": served,
            "accuracy_first": accuracy_first, "accuracy_30": accuracy_30, "evidence": evidence,
            "accuracy_survey": survey, "moved": truth.moved(setting), "shift_db": shift_db}


def _contradicts(mapper: OnlineSinrMapper, uploads: MeasurementBatch) -> bool:
    """Whether a report of this step contradicts the survey map where the survey map is right
    without a jammer: the first evidence of the change any detector could have."""
    xy = positions_from_features(mapper.scenario, uploads.features)
    survey = predict_levels(mapper.current_network(), uploads.features)
    quiet = RadioModel(mapper.scenario).evaluate(xy).level
    return bool(((survey != uploads.levels) & (survey == quiet)).any())


def _still_detections(scenario: Scenario, seed: int) -> int:
    """Change detections in STILL_S of flight with no jammer, from the survey map."""
    now = [0.0]
    mapper = _mapper(scenario, now, seed)
    for step, batch in enumerate(_still_uploads(scenario, seed)):
        now[0] = step * scenario.timing.step_s
        mapper.ingest(batch)
    mapper.close()
    return sum(e["type"] == "change_detected" for e in mapper.events)


MISSION_EPISODES = 200  # about 70 min of flight


def _mission_detections(scenario: Scenario, seed: int) -> tuple[float, float]:
    """Change detections per STILL_S of flight, and the success rate, of four UAVs flying
    missions with no jammer (``jamnav eval --method proposed --no-jammer``): the regime the
    agents fly, where the planner keeps UAVs near the edges of coverage, where the survey map
    errs; the straight legs of ``_still_detections`` cross the area blind to it."""
    report = evaluate(scenario, "proposed", MISSION_EPISODES, seed, None)
    detections = sum(e["type"] == "change_detected" for e in report["events"])
    return detections * STILL_S / report["flight_seconds"], report["success_rate"]


THRESHOLDS = (8.0, 12.0, 16.0, 24.0)  # the detector thresholds the scenarios chose between
FLOORS = (0.05, 0.01, 0.002, 0.0005)  # the probability floors icc2021 chose between


def _still_uploads(scenario: Scenario, seed: int) -> list[MeasurementBatch]:
    """What four UAVs on straight legs upload over STILL_S with no jammer."""
    fleet = Fleet(scenario, UAVS, np.random.default_rng(seed))
    uploads = []
    for step in range(int(STILL_S / scenario.timing.step_s)):
        fleet.fly()
        uploads.append(fleet.uploads(None, step * scenario.timing.step_s, step))
    return uploads


def _false_alarms(detector: ChangeDetector, probabilities: list[np.ndarray],
                  uploads: list[MeasurementBatch]) -> int:
    """Detections of the detector alone (reset after each) fed each upload's probabilities."""
    count = 0
    for probability, batch in zip(probabilities, uploads, strict=True):
        check = detector.update(probability, batch.sources, batch.times)
        if check is not None and check.fired:
            count += 1
            detector.reset()
    return count


def _detector_alone(scenario: Scenario, seed: int) -> list[Figure]:
    """Detections the survey map would raise over STILL_S of flight with no jammer, each
    report weighed as the mapper weighs it (``report_probability``): for each of THRESHOLDS
    (the scenario's floor); and for each of FLOORS (the scenario's threshold), and there also
    with the survey map alone where the mapper lets the ideal model vouch. The figures the
    scenarios' ``online_map`` comments quote."""
    uploads = _still_uploads(scenario, seed)
    mapper = _mapper(scenario, [0.0], seed)
    alone, vouched = [], []
    for batch in uploads:
        probabilities = predict_probabilities(mapper.current_network(), batch.features)
        alone.append(probabilities[np.arange(len(batch)), batch.levels])
        vouched.append(mapper.report_probability(batch, probabilities))
    base = ChangeDetector.of(scenario)
    figures = [
        Figure(f"{scenario.name}: same, detector alone at threshold {threshold:g}",
               _false_alarms(dataclasses.replace(base, threshold=threshold), vouched, uploads),
               "count")
        for threshold in THRESHOLDS]
    for floor in FLOORS:
        figures.append(Figure(
            f"{scenario.name}: same, detector alone at floor {floor:g}",
            _false_alarms(dataclasses.replace(base, floor=floor), vouched, uploads), "count"))
        if mapper.model_spread_db is not None:
            figures.append(Figure(
                f"{scenario.name}: same, detector alone at floor {floor:g}, the survey map "
                "alone", _false_alarms(dataclasses.replace(base, floor=floor), alone, uploads),
                "count"))
    mapper.close()
    return figures


def _percentiles(values: list[float | None]) -> tuple[float, float]:
    """Median and 90th percentile; a change never handled counts as infinitely late."""
    data = np.array([np.inf if v is None else v for v in values])
    if data.size == 0:
        return float("nan"), float("nan")
    # No interpolation: between two infinitely late changes there is nothing to average.
    low, high = np.percentile(data, [50, 90], method="inverted_cdf")
    return float(low), float(high)


def adaptation_figures(scenario: Scenario, warm_up_s: float, quiet: bool = True
                       ) -> list[Figure]:
    """CHANGES changes, each after ``warm_up_s`` of flight with no jammer; with ``quiet``,
    also the false detections with no jammer at all."""
    truth = TruthGrid(scenario)
    trials = [_trial(scenario, truth, 100 + k, warm_up_s) for k in range(CHANGES)]
    # Detection: the first detection at or after the change (earlier ones are false alarms).
    detection = [min((t for t in r["detected"] if t >= 0), default=None) for r in trials]
    early = sum(t < 0 for r in trials for t in r["detected"])
    name = f"{scenario.name}, {UAVS} UAVs, {CHANGES} changes after {warm_up_s:.0f} s"
    d50, d90 = _percentiles(detection)
    # Reaction: from the first report that contradicts the map to the detection.
    reaction = [None if t is None or r["evidence"] is None else t - r["evidence"]
                for t, r in zip(detection, trials, strict=True) if r["evidence"] is not None]
    r50, r90 = _percentiles(reaction)
    never = sum(r["evidence"] is None for r in trials)
    m50, m90 = _percentiles([r["first_map"] for r in trials])
    # What a change that goes unnoticed changed: a weak jammer moves few levels, near the edges.
    missed = [100 * r["moved"] for t, r in zip(detection, trials, strict=True) if t is None]
    caught = [100 * r["moved"] for t, r in zip(detection, trials, strict=True) if t is not None]
    # What the fleet could see: the changes detected late shifted the SINR where it flew least.
    late = [r["shift_db"] for t, r in zip(detection, trials, strict=True)
            if t is None or t > VISIBLE_WITHIN_S]
    prompt = [r["shift_db"] for t, r in zip(detection, trials, strict=True)
              if t is not None and t <= VISIBLE_WITHIN_S]
    first = [r["accuracy_first"] for r in trials if r["accuracy_first"] is not None]
    at_30 = [r["accuracy_30"] for r in trials]
    return _served_figures(scenario, name, trials) + [
        Figure(f"{name}: change detected, median s", d50, "s", 2, lower_is_better=True),
        Figure(f"{name}: change detected, p90 s", d90, "s", 5, lower_is_better=True),
        Figure(f"{name}: no report contradicts the map in {AFTER_S:.0f} s", never, "count"),
        Figure(f"{name}: detection after the first contradicting report, median s", r50, "s"),
        Figure(f"{name}: detection after the first contradicting report, p90 s", r90, "s"),
        Figure(f"{name}: changes never detected in {AFTER_S:.0f} s", len(missed), "count"),
        Figure(f"{name}: levels moved by a change never detected, most %",
               max(missed, default=0.0), "%"),
        Figure(f"{name}: levels moved by a change detected, least %",
               min(caught, default=0.0), "%"),
        Figure(f"{name}: SINR shift at the reports of the first {VISIBLE_WITHIN_S:.0f} s, "
               f"most of a change detected later (or never), dB", max(late, default=0.0), "dB"),
        Figure(f"{name}: the same, least of a change detected within {VISIBLE_WITHIN_S:.0f} s, "
               "dB", min(prompt, default=np.inf), "dB"),
        Figure(f"{name}: first corrected map, median s", m50, "s", 5, lower_is_better=True),
        Figure(f"{name}: first corrected map, p90 s", m90, "s", 10, lower_is_better=True),
        Figure(f"{name}: first map's accuracy vs truth, median %",
               100 * float(np.median(first)) if first else 0.0, "%", 95),
        Figure(f"{name}: the survey map's accuracy vs truth (no map yet), median %",
               100 * float(np.median([r["accuracy_survey"] for r in trials])), "%"),
        Figure(f"{name}: accuracy vs truth 30 s after, median %", 100 * float(np.median(at_30)),
               "%", 97),
        Figure(f"{name}: accuracy vs truth 30 s after, worst %", 100 * float(np.min(at_30)),
               "%"),
        Figure(f"{name}: detections before the change ({warm_up_s:.0f} s each)", early, "count",
               0, lower_is_better=True),
    ] + (_quiet_figures(scenario) if quiet else [])


def _quiet_figures(scenario: Scenario) -> list[Figure]:
    """False detections with no jammer: on straight legs, flying missions, and the detector
    alone at other thresholds and floors."""
    on_missions, mission_success = _mission_detections(scenario, 0)
    return [
        Figure(f"{scenario.name}: false detections, {UAVS} UAVs, {STILL_S / 60:.0f} min still",
               _still_detections(scenario, 7), "count", 0, lower_is_better=True),
        Figure(f"{scenario.name}: false detections flying missions, {UAVS} UAVs, per "
               f"{STILL_S / 60:.0f} min, no jammer", on_missions, "count", 0,
               lower_is_better=True),
        Figure(f"{scenario.name}: success of those missions %", 100 * mission_success, "%"),
    ] + _detector_alone(scenario, 7)


def _served_figures(scenario: Scenario, name: str, trials: list[dict]) -> list[Figure]:
    """The map in service against the truth at each of SERVED_AT_S after the change: the
    10th percentile and the median over the changes."""
    latency = scenario.online_map.cloud_latency_s
    targets = SERVED_TARGETS.get(scenario.name, {})
    figures = []
    for at in SERVED_AT_S:
        scores = 100 * np.array([r["served"][at] for r in trials])
        label = f"{name}: map in service {at:g} s after (latency {latency:g} s) vs truth"
        figures += [Figure(f"{label}, p10 %", float(np.percentile(scores, 10)), "%",
                           targets.get(at)),
                    Figure(f"{label}, median %", float(np.median(scores)), "%")]
    return figures


def localization_figures(scenario: Scenario) -> list[Figure]:
    """The estimator alone on LOCALIZATION_FLIGHT_S of four UAVs' uploads after a change."""
    dt = scenario.timing.step_s
    survey, _ = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    errors, power_errors, failures = [], [], 0
    told_errors, told_sds = [], []
    radio = RadioModel(scenario)
    for k in range(LOCALIZATION_SETTINGS):
        rng = np.random.default_rng(1000 + k)
        setting = random_jammer(scenario, rng)
        fleet = Fleet(scenario, UAVS, rng)
        batches = []
        for step in range(int(LOCALIZATION_FLIGHT_S / dt)):
            fleet.fly()
            batches.append(fleet.uploads(jammer_params(scenario, setting), step * dt, step))
        data = MeasurementBatch.concatenate(batches)
        xy = positions_from_features(scenario, data.features)
        # What the reports themselves hold: the estimate told the true no-jammer world (the
        # share of reports at each level at each point) and made whatever its certainty.
        # With dB reports, told the no-jammer SINR itself, to a twentieth of a dB.
        no_jammer_db = radio.evaluate(xy).sinr_db
        told = estimate_jammer(
            scenario, xy, data.levels, reported_db=data.sinr_db,
            no_jammer_levels=report_shares(radio, no_jammer_db,
                                           scenario.uav.measurement_noise_db),
            no_jammer_db=(SinrBelief(no_jammer_db, np.full(len(xy), TOLD_SD_DB))
                          if scenario.uav.report == "db" else None),
            max_position_sd_m=np.inf, presence_llr=-np.inf)
        if told is not None and told.present:
            told_errors.append(float(np.hypot(told.x - setting.x, told.y - setting.y)))
            told_sds.append(max(told.sd_x_m, told.sd_y_m))
        estimate = estimate_jammer(scenario, xy, data.levels, reported_db=data.sinr_db,
                                   no_jammer_levels=predict_probabilities(survey, data.features))
        if estimate is None or not estimate.present:
            failures += 1
            continue
        errors.append(float(np.hypot(estimate.x - setting.x, estimate.y - setting.y)))
        power_errors.append(abs(10 * np.log10(estimate.power_w / setting.power_w)))
    name = f"{scenario.name}, jammer located from {LOCALIZATION_FLIGHT_S:.0f} s of {UAVS} UAVs"
    e50, e90 = _percentiles(errors + [None] * failures)
    return [
        Figure(f"{name}: error median m", e50, "m", 5, lower_is_better=True),
        Figure(f"{name}: error p90 m (no estimate = inf)", e90, "m", 10, lower_is_better=True),
        Figure(f"{name}: power error median dB",
               float(np.median(power_errors)) if power_errors else np.inf, "dB", 2,
               lower_is_better=True),
        Figure(f"{name}: no estimate, of {LOCALIZATION_SETTINGS}", failures, "count"),
        Figure(f"{name}: told the true no-jammer world, any certainty: error median m",
               float(np.median(told_errors)) if told_errors else np.inf, "m"),
        Figure(f"{name}: the same, posterior sd along its least certain axis, median m",
               float(np.median(told_sds)) if told_sds else np.inf, "m"),
        Figure(f"{scenario.name}: one estimate from {COSTED_REPORTS:,} uniform reports, best of 3",
               _estimate_seconds(scenario, survey), "s", 1, lower_is_better=True),
    ]


COSTED_REPORTS = 2000


def _estimate_seconds(scenario: Scenario, survey: SinrMapNetwork) -> float:
    """What one ``estimate_jammer`` costs the cloud on COSTED_REPORTS reports spread over the
    area, a 1 W jammer among them (the search, its refits at other report spreads)."""
    rng = np.random.default_rng(10)
    area = scenario.area
    xy = rng.uniform((area.x_min, area.y_min), (area.x_max, area.y_max), (COSTED_REPORTS, 2))
    radio = RadioModel(scenario)
    levels = radio.measured_reports(
        radio.evaluate(xy, jammer_params(scenario, JammerSetting(10.0, -20.0, 1.0))).sinr_db,
        rng).level
    no_jammer = predict_probabilities(survey, scenario_features(scenario, xy))
    seconds = []
    for _ in range(3):
        start = time.perf_counter()
        estimate_jammer(scenario, xy, levels, no_jammer_levels=no_jammer)
        seconds.append(time.perf_counter() - start)
    return min(seconds)
