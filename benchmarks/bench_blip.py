"""A jammer that comes and goes: how long maps corrected for a jammer stay in service after
it is switched off (on for 1 s, a blip, and for 10 s), and how often a still jammer's
estimate is withdrawn. One CPU thread.

Uploads come from ``online_map_sim.Fleet`` (four UAVs on straight legs at top speed, reporting
as the agents do) into a mapper that runs inline in simulated time. A map published after the
uploads of step t flies from step t + ceil(latency / dt) on (``online_map.cloud_latency_s``),
as in ``jamnav eval``. Every figure is seconds of flight, the same on any machine.
"""

from __future__ import annotations

import math

import numpy as np

from benchmarks.common import Figure
from cloud_service.change_handling import RetrainConfig
from cloud_service.mapper_outputs import PublishedWeights
from cloud_service.online_map_sim import Fleet
from cloud_service.sinr_mapping import OnlineSinrMapper
from cloud_service.sinr_memory import SinrMemory
from planning.networks import load_network
from shared.measurements import MeasurementSpec
from shared.paper import TABLE_I_JAMMERS, JammerSetting, jammer_params
from shared.scenario import Scenario, load_scenario
from shared.survey_maps import sinr_map_for
from world_sim.jammers import random_jammer

SCENARIOS = ("icc2021", "icc2021-shadowed")
UAVS = 4
BLIPS = 10  # random jammers (place and power), one blip each
WARM_UP_S = 20.0  # flight before the blip, so the fleet is spread over the area
BLIP_S = 1.0
ON_S = 10.0  # a jammer long enough on to be confirmed, estimated and mapped, then off
AFTER_S = 60.0  # flight after the blip: a corrected map still in service then is "never"
TARGET_S = 5.0
STILL_S = 900.0  # flight with a still jammer, per Table I setting


def run() -> list[Figure]:
    figures = []
    for name in SCENARIOS:
        scenario = load_scenario(name)
        figures += blip_figures(scenario, BLIP_S, TARGET_S)
        figures += blip_figures(scenario, ON_S, None)
        figures += still_figures(scenario)
    return figures


class _Flight:
    """A mapper fed by the fleet in simulated time, and when each map it publishes enters
    service (``online_map.cloud_latency_s`` later, in whole steps)."""

    def __init__(self, scenario: Scenario, seed: int):
        self.scenario = scenario
        self.dt = scenario.timing.step_s
        self.delay_steps = math.ceil(scenario.online_map.cloud_latency_s / self.dt - 1e-9)
        self.step = 0
        self.fleet = Fleet(scenario, UAVS, np.random.default_rng(seed))
        self.in_service: list[tuple[float, bool]] = []  # (from when, corrected) per map
        network, card = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
        self.mapper = OnlineSinrMapper(
            scenario, SinrMemory(":memory:", MeasurementSpec.of(scenario)), network,
            float(card["accuracy"]), publish=self._published, clock=self.now,
            retrain=RetrainConfig(max_seconds=None), background=False, seed=seed)

    def now(self) -> float:
        return self.step * self.dt

    def _published(self, weights: PublishedWeights) -> None:
        corrected = weights.estimate is not None or weights.provisional
        self.in_service.append(((self.step + self.delay_steps) * self.dt, corrected))

    def fly(self, setting: JammerSetting | None, seconds: float) -> None:
        for _ in range(round(seconds / self.dt)):
            self.step += 1
            self.fleet.fly()
            self.mapper.ingest(self.fleet.uploads(jammer_params(self.scenario, setting),
                                                  self.now(), self.step))

    def corrected_until(self) -> float | None:
        """When the last corrected map left service (inf: it is still in service); None if
        none ever entered."""
        last = None
        for entered, corrected in self.in_service:
            if corrected:
                last = math.inf
            elif last is not None and last == math.inf:
                last = entered
        return last

    def close(self) -> None:
        self.mapper.close()


def _blip(scenario: Scenario, seed: int, on_s: float) -> dict:
    """No jammer for WARM_UP_S, a random jammer for ``on_s``, none for AFTER_S."""
    setting = random_jammer(scenario, np.random.default_rng([seed, 0xB11B]))
    flight = _Flight(scenario, seed)
    flight.fly(None, WARM_UP_S)
    flight.fly(setting, on_s)
    ended = flight.now()
    flight.fly(None, AFTER_S)
    until = flight.corrected_until()
    events = flight.mapper.events
    flight.close()
    return {"served_after_s": 0.0 if until is None else max(0.0, until - ended),
            "corrected": until is not None,
            "withdrawn": sum(e["type"] == "estimate_withdrawn" for e in events),
            "detected": sum(e["type"] == "change_detected" for e in events)}


def blip_figures(scenario: Scenario, on_s: float, target_s: float | None) -> list[Figure]:
    trials = [_blip(scenario, 200 + k, on_s) for k in range(BLIPS)]
    served = np.array([t["served_after_s"] for t in trials])
    name = f"{scenario.name}, {UAVS} UAVs, {BLIPS} jammers on for {on_s:g} s"
    return [
        Figure(f"{name}: corrected map in service after it is off, median s",
               float(np.median(served)), "s", target_s, lower_is_better=True),
        Figure(f"{name}: the same, worst s (inf: past {AFTER_S:.0f} s)", float(served.max()),
               "s", target_s, lower_is_better=True),
        Figure(f"{name}: that put a corrected map in service",
               sum(t["corrected"] for t in trials), "count"),
        Figure(f"{name}: changes detected", sum(t["detected"] for t in trials), "count"),
        Figure(f"{name}: estimates withdrawn", sum(t["withdrawn"] for t in trials), "count"),
    ]


def still_figures(scenario: Scenario) -> list[Figure]:
    """Withdrawals over STILL_S of flight with each Table I jammer standing from the start,
    and the most evidence the reports held against a corrected map: the margin below
    ``online_map.withdrawal_threshold``."""
    withdrawn, corrected, most = 0, 0, 0.0
    for k, setting in enumerate(TABLE_I_JAMMERS):
        flight = _Flight(scenario, 300 + k)
        for _ in range(round(STILL_S / flight.dt)):
            flight.fly(setting, flight.dt)
            most = max(most, flight.mapper.state()["withdrawal_evidence"] or 0.0)
        withdrawn += sum(e["type"] == "estimate_withdrawn" for e in flight.mapper.events)
        corrected += flight.corrected_until() == math.inf
        flight.close()
    name = (f"{scenario.name}, {UAVS} UAVs, Table I's {len(TABLE_I_JAMMERS)} jammers still for "
            f"{STILL_S / 60:.0f} min each")
    return [
        Figure(f"{name}: estimates withdrawn", withdrawn, "count", 0, lower_is_better=True),
        Figure(f"{name}: most evidence against a corrected map, nats", most, "nats"),
        Figure(f"{name}: ending with a corrected map in service", corrected, "count"),
    ]
