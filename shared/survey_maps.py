"""Which shipped survey map (the SINR map of no jammer) was learned in a scenario's radio
world, and the fingerprint of that world a map's card records."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from shared.scenario import Scenario, load_scenario
from shared.shipped import SINR_MAP_NO_JAMMER, SINR_MAP_NO_JAMMER_CITY, SINR_MAP_NO_JAMMER_SHADOWED

# The survey map (no jammer) shipped for each shipped scenario's radio world.
_SURVEY_MAPS = {"icc2021": SINR_MAP_NO_JAMMER, "icc2021-shadowed": SINR_MAP_NO_JAMMER_SHADOWED,
                "city": SINR_MAP_NO_JAMMER_CITY}


class NoSurveyMapError(ValueError):
    """No shipped survey map was learned in a scenario's radio world."""


def sinr_map_for(scenario: Scenario) -> Path:
    """The shipped no-jammer SINR map learned from a survey in ``scenario``'s radio world
    (``Scenario.survey_world``), whatever the scenario is called: a copy of a shipped scenario
    with other missions or planning values shares its map. A world no shipped map was learned
    in raises ``NoSurveyMapError``: a map of another world would be flown as if it were
    right (README: icc2021's map in icc2021-shadowed's world cost 14 points of success)."""
    world = scenario.survey_world()
    differences = {}
    for name, path in _SURVEY_MAPS.items():
        shipped = load_scenario(name).survey_world()
        if shipped == world:
            return path
        differences[name] = [key for key in world if world[key] != shipped[key]]
    closest = min(differences, key=lambda name: len(differences[name]))
    raise NoSurveyMapError(
        f"no shipped survey map was learned in the radio world of scenario {scenario.name!r} "
        f"(it differs from {closest}'s in {', '.join(differences[closest])}): fit one with "
        f"`jamnav fit-sinr --scenario FILE --no-jammer --out MAP.safetensors` and pass it "
        f"with --sinr-map MAP.safetensors")


def survey_world_digest(scenario: Scenario) -> str:
    """A fingerprint of ``Scenario.survey_world``: what a survey map's card records of the
    radio world it was learned in (``jamnav fit-sinr`` writes it)."""
    text = json.dumps(scenario.survey_world(), sort_keys=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def foreign_survey_map(card: dict[str, Any], scenario: Scenario) -> str | None:
    """One line of warning when a survey map's ``card`` says it was learned in another radio
    world than ``scenario``'s; None when it was learned there, or its card does not say."""
    learned_in = card.get("survey_world")
    if learned_in is None or learned_in == survey_world_digest(scenario):
        return None
    return (f"the survey map was learned in the radio world of {card.get('scenario')!r}, "
            f"not in scenario {scenario.name!r}'s: it will be flown as if it were right there")
