"""How many jammers the cloud counts, and where it places each, from the uploads of four UAVs
(the target's; last, sixteen) flying for 20 s after the jammers appeared: 40 seeded
settings, ten each of 0, 1, 2 and 3 jammers, each anywhere in the area at a power of the
scenario's training range; uploads come from ``online_map_sim.Fleet``.

A count is right where it is the true number of jammers, whether or not each is placed yet
(its estimate converged); the figures also tell the counts right with every jammer placed.

First the cloud itself: its mapper flown over a quiet spell and then 20 s of the jammers, and
its count at the end (none when it detected no change: no jammer), beside the estimate behind
its map. In the idealized world after 10 s of quiet, and in the shadowed world with dB reports
after 60 s (a dB report enters the cloud's no-jammer reference 10 s after it was taken).

Then the estimator alone (``locate_jammer``, whose estimate is ``estimate_jammers``') on the
20 s of uploads, reading them as the cloud does (its no-jammer model and report spread,
``EstimateInputs``): in the idealized world with level reports, in the shadowed world with dB
reports (with no dB reference yet), and in the idealized world again after 120 s, to show what
longer flights bring.

Then what the idealized world's 20 s and 120 s hold for any search: in how many settings
every jammer changes the level of some report (with it and without it, the others there),
and in how many the cloud's likelihood would count right were the search perfect: the true
jammers, each placed at its best with the others known as the search places them, explain
the uploads better than every set of one fewer, placed alike, by more than the rule asks
(``PRESENCE_LLR`` alone, BIC's penalty beside others), and one more, all of them known, does
not. With the others where they truly are instead, each jammer seemed to pay its way more
often: the others, placed at their best without it, explain some of what it explains.

Last, the cloud's count, the estimator's and that ceiling in the idealized world after 20 s
of a denser fleet (``DENSER_UAVS``): whether the target lies past what four UAVs' uploads hold
or past the search."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from benchmarks.common import Figure
from cloud_service.change_handling import RetrainConfig
from cloud_service.estimate_inputs import EstimateInputs
from cloud_service.estimated_jammer import JammerEstimate
from cloud_service.jammer_estimation import (
    PRESENCE_LLR,
    locate_jammer,
    one_more_evidence,
    placed_evidence,
)
from cloud_service.map_refit import prior_positions
from cloud_service.online_map_sim import Fleet, SimulatedClock
from cloud_service.report_models import ReportModels
from cloud_service.sinr_mapping import OnlineSinrMapper
from cloud_service.sinr_memory import SinrMemory
from cloud_service.sinr_reference import SinrReference
from planning.networks import load_network
from shared.measurements import MeasurementBatch, MeasurementSpec
from shared.paper import jammer_params
from shared.radio import JammerParams, RadioModel
from shared.scenario import Scenario, load_scenario
from shared.survey_maps import sinr_map_for
from world_sim.jammers import random_jammer

SETTINGS = 40
MOST_JAMMERS = 3  # settings cycle through 0..MOST_JAMMERS jammers
FLIGHT_S = 20.0  # the target's
LONGER_FLIGHT_S = 120.0
# The cloud's flight before the jammers appear: to settle on the survey map, and in the
# shadowed world with dB reports to gather a no-jammer reference.
QUIET_S = 10
REFERENCE_QUIET_S = 60
UAVS = 4  # the target's
# A denser fleet, to tell what the search loses from what the uploads lack: 16 UAVs also met
# the convoy's tracking target.
DENSER_UAVS = 16


class Counted(NamedTuple):
    """What a setting's count was."""

    jammers: list[JammerParams]  # the truth
    count: int | None  # how many were counted, placed or not; None: no count yet
    placed: list[JammerEstimate]  # those the estimate placed


def run() -> list[Figure]:
    shadowed = load_scenario("icc2021-shadowed")
    reporting = shadowed.changed({"uav.report": "db"}, name="icc2021-shadowed, dB reports")
    idealized = load_scenario("icc2021")
    return (cloud_figures(idealized, QUIET_S) + cloud_figures(reporting, REFERENCE_QUIET_S)
            + count_figures(idealized, FLIGHT_S) + count_figures(reporting, FLIGHT_S)
            + count_figures(idealized, LONGER_FLIGHT_S)
            + evidence_figures(idealized, FLIGHT_S) + evidence_figures(idealized, LONGER_FLIGHT_S)
            + cloud_figures(idealized, QUIET_S, DENSER_UAVS)
            + count_figures(idealized, FLIGHT_S, DENSER_UAVS)
            + evidence_figures(idealized, FLIGHT_S, DENSER_UAVS))


def cloud_figures(scenario: Scenario, quiet_s: float, uavs: int = UAVS) -> list[Figure]:
    """The cloud's counts after ``FLIGHT_S`` of each setting's jammers."""
    return tally(f"{scenario.name}, the cloud's count after {FLIGHT_S:.0f} s of {uavs} UAVs",
                 [_cloud_count(scenario, k, quiet_s, uavs) for k in range(SETTINGS)],
                 uavs == UAVS)


def count_figures(scenario: Scenario, flight_s: float, uavs: int = UAVS) -> list[Figure]:
    """The estimator's counts from each setting's uploads, read as the cloud reads."""
    inputs = _cloud_reading(scenario)
    counted = []
    for k in range(SETTINGS):
        jammers, data = _uploads(scenario, k, flight_s, uavs)
        xy, levels, keywords = inputs.of(data)
        fit = locate_jammer(scenario, xy, levels, **keywords)
        counted.append(Counted(jammers, fit.count,
                               [] if fit.estimate is None else list(fit.estimate.members)))
    return tally(f"{scenario.name}, jammers counted from {flight_s:.0f} s of {uavs} UAVs",
                 counted, flight_s == FLIGHT_S and uavs == UAVS)


def tally(name: str, counted: list[Counted], targeted: bool) -> list[Figure]:
    """The counts right, wrong and undecided, by the true count; those right with every
    jammer placed, and how far each of those lies from its estimate."""
    right, placed, undecided, errors = 0, 0, 0, []
    by_count = np.zeros((MOST_JAMMERS + 1, 3), dtype=int)  # truth x (right, wrong, undecided)
    for jammers, count, found in counted:
        if count is None:
            undecided += 1
            by_count[len(jammers), 2] += 1
            continue
        hit = count == len(jammers)
        right += hit
        by_count[len(jammers), 0 if hit else 1] += 1
        if hit and len(found) == count:
            placed += 1
            errors += [min(np.hypot(e.x - j.x, e.y - j.y) for e in found) for j in jammers]
    figures = [Figure(f"{name}: count right, of {SETTINGS} settings of 0-{MOST_JAMMERS}",
                      100.0 * right / SETTINGS, "%", 95.0 if targeted else None),
               Figure(f"{name}: count right with every jammer placed",
                      100.0 * placed / SETTINGS, "%"),
               Figure(f"{name}: undecided (no count yet)", 100.0 * undecided / SETTINGS, "%")]
    for count, (hit, wrong, open_) in enumerate(by_count.tolist()):
        figures += [Figure(f"{name}: {count} jammer(s), counted right", hit, "settings"),
                    Figure(f"{name}: {count} jammer(s), counted wrong", wrong, "settings"),
                    Figure(f"{name}: {count} jammer(s), undecided", open_, "settings")]
    if errors:
        figures.append(Figure(f"{name}: position error of each jammer when counted right and "
                              "placed, median", float(np.median(errors)), "m"))
    return figures


def evidence_figures(scenario: Scenario, flight_s: float, uavs: int = UAVS) -> list[Figure]:
    """What the uploads of each setting hold, for any search and for the cloud's likelihood
    searched perfectly (the module's docstring)."""
    radio = RadioModel(scenario)
    inputs = _cloud_reading(scenario)
    visible = countable = 0
    for k in range(SETTINGS):
        jammers, data = _uploads(scenario, k, flight_s, uavs)
        xy, levels, keywords = inputs.of(data)
        truth = radio.evaluate(xy, jammers).level
        visible += all((radio.evaluate(xy, _others(jammers, i)).level != truth).any()
                       for i in range(len(jammers)))
        countable += _counted_by_a_perfect_search(scenario, xy, levels, keywords, jammers)
    name = f"{scenario.name}, {flight_s:.0f} s of {uavs} UAVs"
    return [Figure(f"{name}: settings where each jammer changes a report's level", visible,
                   f"of {SETTINGS}"),
            Figure(f"{name}: settings a perfect search would count right", countable,
                   f"of {SETTINGS}")]


def _counted_by_a_perfect_search(scenario: Scenario, xy: np.ndarray, levels: np.ndarray,
                                 keywords: dict, jammers: list[JammerParams]) -> bool:
    """Whether the cloud's likelihood, searched perfectly, counts ``jammers``: the true set,
    each placed at its best with the others known, explains the uploads better than each of
    its sets of one fewer, placed alike, by more than the rule asks (``PRESENCE_LLR`` for one
    alone, BIC's penalty beside others); and one more, all of them known, does not."""
    placed = [_placed(scenario, jammer) for jammer in jammers]
    if placed:
        placed, log_likelihood, penalty = placed_evidence(scenario, xy, levels, placed,
                                                          **keywords)
        for index in range(len(placed)):
            _, fewer, _ = placed_evidence(scenario, xy, levels, _others(placed, index),
                                          **keywords)
            if log_likelihood - fewer <= (penalty if len(placed) > 1 else PRESENCE_LLR):
                return False
    llr, penalty = one_more_evidence(scenario, xy, levels, placed, **keywords)
    return llr <= (penalty if placed else PRESENCE_LLR)


def _others(jammers: list, index: int) -> list:
    return jammers[:index] + jammers[index + 1:]


def _placed(scenario: Scenario, jammer: JammerParams) -> tuple[np.ndarray, float]:
    """A jammer as the estimator takes one as known: its position and effective power (dBW)."""
    return (np.array([jammer.x, jammer.y]),
            10.0 * np.log10(jammer.power_w) + scenario.jammer.efficiency_db)


def _cloud_reading(scenario: Scenario) -> EstimateInputs:
    """How the cloud reads uploads for an estimate: its no-jammer model built on the shipped
    survey map, and a dB reference of no reports yet."""
    survey, _ = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    reference = SinrReference(scenario)
    return EstimateInputs(ReportModels(scenario, survey, reference, prior_positions(scenario, 0)),
                          reference, SinrMemory(":memory:", MeasurementSpec.of(scenario)))


def _jammers(scenario: Scenario, seed: int) -> tuple[list[JammerParams], np.random.Generator]:
    """Setting ``seed``'s jammers (``seed`` mod 4 of them), and its generator for the fleet."""
    rng = np.random.default_rng([seed, 0x40])
    return [jammer_params(scenario, random_jammer(scenario, rng))
            for _ in range(seed % (MOST_JAMMERS + 1))], rng


def _uploads(scenario: Scenario, seed: int, flight_s: float,
             uavs: int) -> tuple[list[JammerParams], MeasurementBatch]:
    """Setting ``seed``'s jammers and the uploads of ``flight_s`` of a fleet of ``uavs``."""
    jammers, rng = _jammers(scenario, seed)
    fleet = Fleet(scenario, uavs, rng)
    dt = scenario.timing.step_s
    batches = []
    for step in range(int(flight_s / dt)):
        fleet.fly()
        batches.append(fleet.uploads(jammers, step * dt, step))
    return jammers, MeasurementBatch.concatenate(batches)


def _cloud_count(scenario: Scenario, seed: int, quiet_s: float, uavs: int) -> Counted:
    """The cloud's mapper over ``quiet_s`` of quiet, then ``FLIGHT_S`` of setting ``seed``'s
    jammers; its count at the end (none where it detected no change), and the jammers of the
    estimate behind its map."""
    jammers, rng = _jammers(scenario, seed)
    survey, card = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    clock = SimulatedClock()
    mapper = OnlineSinrMapper(scenario, SinrMemory(":memory:", MeasurementSpec.of(scenario)),
                              survey, card["accuracy"], clock=clock, background=False,
                              seed=seed, retrain=RetrainConfig(max_seconds=None))
    fleet = Fleet(scenario, uavs, rng)
    dt = scenario.timing.step_s
    for step in range(int((quiet_s + FLIGHT_S) / dt)):
        clock.now = step * dt
        fleet.fly()
        mapper.ingest(fleet.uploads(jammers if clock.now >= quiet_s else [], clock.now, step))
    return Counted(jammers, mapper.state()["jammers_counted"],
                   [] if mapper.estimate is None else list(mapper.estimate.members))
