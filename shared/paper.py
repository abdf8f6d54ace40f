"""Figures quoted from the paper, for comparison only: Table I's settings and results."""

from __future__ import annotations

from typing import NamedTuple

from shared.radio import JammerParams
from shared.scenario import Scenario


class JammerSetting(NamedTuple):
    x: float
    y: float
    power_w: float

    @property
    def label(self) -> str:
        return f"({self.x:g},{self.y:g}) {self.power_w:g} W"


def jammer_params(scenario: Scenario, setting: JammerSetting | None) -> JammerParams | None:
    """A setting as the radio model takes it, at the scenario's jammer height."""
    if setting is None:
        return None
    return JammerParams(setting.x, setting.y, setting.power_w, scenario.jammer.height_m)


TABLE_I_JAMMERS = (
    JammerSetting(0.0, 0.0, 1.0),
    JammerSetting(25.0, -10.0, 1.0),
    JammerSetting(-30.0, 10.0, 1.0),
    JammerSetting(0.0, 0.0, 0.5),
)

# Table I (percent): method -> one (success, disconnection, collision) row per setting above.
TABLE_I_RESULTS = {
    "proposed": ((92.3, 5.6, 1.8), (94.5, 4.0, 1.5), (95.75, 3.75, 0.5), (92.3, 6.2, 1.2)),
    "outdated": ((65.3, 33.7, 1.0), (71.1, 27.5, 1.4), (78.4, 21.2, 0.4), (73.3, 25.5, 1.2)),
    "perfect": ((94.6, 3.2, 1.9), (94.5, 3.3, 2.2), (96.6, 2.7, 0.6), (95.8, 1.9, 1.6)),
}
