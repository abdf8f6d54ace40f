"""The jammers an evaluation or a world process flies a run of episodes under: one setting, or
a fresh random one every few episodes, drawn from the run's seed alone, so that an in-process
evaluation and the world process of ``jamnav up`` fly the same ones."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from shared.paper import JammerSetting
from shared.scenario import Scenario

JammerSchedule = Callable[[int], JammerSetting | None]  # episode -> its jammer
_SWAP_STREAM = 0x5A4150  # a stream of its own for the swapped jammers of a run


def swapping_jammers(scenario: Scenario, first: JammerSetting | None, swap_every: int | None,
                     seed: int) -> JammerSchedule:
    """Episode -> jammer: ``first`` for the first ``swap_every`` episodes, then a fresh random
    setting every ``swap_every`` (position uniform over the area, power uniform over the
    scenario's training range), drawn from ``seed`` alone; ``first`` throughout without swaps."""

    def at(episode: int) -> JammerSetting | None:
        period = 0 if swap_every is None else episode // swap_every
        if period == 0:
            return first
        x, y, power_w = random_jammer(scenario, np.random.default_rng([seed, _SWAP_STREAM,
                                                                       period]))
        return JammerSetting(round(x, 1), round(y, 1), round(power_w, 2))

    return at


def random_jammer(scenario: Scenario, rng: np.random.Generator) -> JammerSetting:
    """A jammer anywhere in the area, its power uniform over the scenario's training range."""
    area, powers = scenario.area, scenario.training.jammer_power_range_w
    x, y = rng.uniform((area.x_min, area.y_min), (area.x_max, area.y_max))
    return JammerSetting(float(x), float(y), float(rng.uniform(*powers)))
