"""Declaring a jammer change (paper Sec. III-C): the rule that fires when one UAV's uploads
keep contradicting the map in service (``ChangeDetector``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from shared.scenario import Scenario


class DetectorCheck(NamedTuple):
    t: float  # time of the last measurement fed
    source: str  # the UAV whose statistic is the highest
    statistic: float  # that UAV's CUSUM after this batch
    fired: bool


@dataclass
class ChangeDetector:
    """Declares a jammer change when one UAV's reports keep contradicting the map.

    Rule, a CUSUM per UAV over its reports in the order taken: S <- max(0, S + log(u / p)),
    with p the map's own probability of the reported level (its softmax; at least ``floor``)
    and u = 1 / levels, the probability a map that knows nothing would give. A report the
    map expected (p > u) pulls S down; one it ruled out pushes it up. A change is declared
    when one UAV's S reaches ``threshold``; the time its excursion began (S last at 0) is
    the estimate of when the change happened.

    Why per UAV: a jammed zone is local. With four UAVs only one may cross it, and pooled
    its reports would be diluted by the others'. Why the map's probabilities: where the map
    is unsure (a cell edge, a patch of shadowing it could not learn) a contradiction is weak
    evidence, and where it is sure it is strong. The map's errors are not independent from
    one report to the next (reports lie 0.25 m apart, shadowing decorrelates over 10 m), so
    the threshold must outlast the runs of contradictions a still jammer produces: it is a
    scenario value (``online_map.change_threshold``, measured there). After firing, the
    detector is disarmed until ``reset``.
    """

    levels: int
    threshold: float
    floor: float
    armed: bool = True
    change_start: float | None = None
    _statistic: dict[str, float] = field(default_factory=dict, repr=False)
    _excursion_start: dict[str, float] = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, scenario: Scenario) -> ChangeDetector:
        online = scenario.online_map
        return cls(scenario.channel.level_count, online.change_threshold,
                   online.probability_floor)

    def reset(self) -> None:
        """A new map is in service: statistics cleared, detector armed."""
        self.armed = True
        self.change_start = None
        self._statistic.clear()
        self._excursion_start.clear()

    def update(self, probability: np.ndarray, sources: list[str], times: np.ndarray,
               evidence_db: np.ndarray | None = None) -> DetectorCheck | None:
        """Feed the new uploads (the map's probability of each reported level, who took it,
        when, and where finite the nats a dB report weighs instead, ``shift_evidence``);
        returns the state after them (``fired`` set when a change is declared), None when
        disarmed or given nothing."""
        if not self.armed or len(probability) == 0:
            return None
        evidence = np.log(1.0 / self.levels) - np.log(np.maximum(probability, self.floor))
        if evidence_db is not None:
            evidence = np.where(np.isfinite(evidence_db), evidence_db, evidence)
        for step, source, t in zip(evidence.tolist(), sources, np.asarray(times).tolist(),
                                   strict=True):
            statistic = self._statistic.get(source, 0.0)
            if statistic == 0.0:
                self._excursion_start[source] = t
            statistic = max(0.0, statistic + step)
            self._statistic[source] = statistic
            if statistic >= self.threshold:
                self.armed = False
                self.change_start = self._excursion_start[source]
                return DetectorCheck(t, source, statistic, True)
        source = max(self._statistic, key=self._statistic.get)
        return DetectorCheck(float(times[-1]), source, self._statistic[source], False)
