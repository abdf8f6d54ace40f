"""The jammers an evaluation or a world process flies a run of episodes under: the run's own
(one setting, or a scenario's list), or a fresh random one every few episodes, drawn from the
run's seed alone, so that an in-process evaluation and the world process of ``jamnav up`` fly
the same ones."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from shared.paper import JammerSetting
from shared.scenario import Jammer, Scenario

JammerSet = tuple[Jammer, ...]  # a world's jammers, as a scenario lists them; () = none
JammerSchedule = Callable[[int], JammerSet]  # episode -> its jammers
_SWAP_STREAM = 0x5A4150  # a stream of its own for the swapped jammers of a run


def jammer_set(scenario: Scenario, jammers: JammerSetting | JammerSet | None) -> JammerSet:
    """A setting as one still jammer, always on, at the height and efficiency of the
    scenario's first (None: no jammer); a list of jammers as it is."""
    if jammers is None:
        return ()
    if isinstance(jammers, JammerSetting):
        # Unchecked here: the world refuses a jammer that is not finite where every caller's
        # enters it (VectorWorld.set_jammers), with one line.
        return (Jammer.model_construct(x=jammers.x, y=jammers.y, power_w=jammers.power_w,
                                       height_m=scenario.jammer.height_m,
                                       efficiency_db=scenario.jammer.efficiency_db),)
    return tuple(jammers)


def described_jammers(jammers: JammerSet) -> list[dict]:
    """A report's record of jammers: each one's place, power and height, and its path and
    schedule if it has them."""
    return [jammer.model_dump(mode="json", exclude={"enabled", "efficiency_db"},
                              exclude_none=True) for jammer in jammers]


def swapping_jammers(scenario: Scenario, first: JammerSetting | JammerSet | None,
                     swap_every: int | None, seed: int) -> JammerSchedule:
    """Episode -> jammers: ``first`` for the first ``swap_every`` episodes, then one still
    jammer at a fresh random setting every ``swap_every`` (position uniform over the area,
    power uniform over the scenario's training range), drawn from ``seed`` alone; ``first``
    throughout without swaps."""
    first = jammer_set(scenario, first)

    def at(episode: int) -> JammerSet:
        period = 0 if swap_every is None else episode // swap_every
        if period == 0:
            return first
        x, y, power_w = random_jammer(scenario, np.random.default_rng([seed, _SWAP_STREAM,
                                                                       period]))
        return jammer_set(scenario, JammerSetting(round(x, 1), round(y, 1), round(power_w, 2)))

    return at


def random_jammer(scenario: Scenario, rng: np.random.Generator) -> JammerSetting:
    """A jammer anywhere in the area, its power uniform over the scenario's training range."""
    area, powers = scenario.area, scenario.training.jammer_power_range_w
    x, y = rng.uniform((area.x_min, area.y_min), (area.x_max, area.y_max))
    return JammerSetting(float(x), float(y), float(rng.uniform(*powers)))
