"""The lookahead the environment chooses: ``JAMNAV_PLANNER``, ``compiled`` (the default) or
``reference``."""

from __future__ import annotations

import os

from planning import PLANNER_VARIABLE, PLANNERS, PlannerError
from planning.networks import ValueNetwork
from planning.reference import LookaheadPolicy
from shared.scenario import Scenario


def chosen_planner() -> str:
    choice = os.environ.get(PLANNER_VARIABLE, "compiled")
    if choice not in PLANNERS:
        raise PlannerError(f"{PLANNER_VARIABLE}={choice!r}: expected one of {', '.join(PLANNERS)}")
    return choice


def require_planner() -> type[LookaheadPolicy]:
    """The class of the planner ``JAMNAV_PLANNER`` names: a process checks it as it starts,
    so that a missing or stale compiled core stops it at once, in one line."""
    if chosen_planner() == "reference":
        return LookaheadPolicy
    # Imported only when chosen: without its compiled core, this module raises PlannerError,
    # and the reference flies without it.
    from planning.lookahead import CompiledLookahead  # noqa: PLC0415

    return CompiledLookahead


def lookahead_policy(scenario: Scenario, value_net: ValueNetwork, **options) -> LookaheadPolicy:
    """The lookahead with ``value_net``, by the planner ``JAMNAV_PLANNER`` names; ``options``
    as ``planning.reference.LookaheadPolicy`` takes them."""
    return require_planner()(scenario, value_net, **options)
