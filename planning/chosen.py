"""The lookahead the environment chooses: ``JAMNAV_PLANNER``, ``compiled`` (the default) or
``reference``."""

from __future__ import annotations

from planning.compiled import chosen_planner, compiled_module
from planning.networks import ValueNetwork
from planning.reference import LookaheadPolicy
from shared.scenario import Scenario


def require_planner() -> type[LookaheadPolicy]:
    """The class of the planner ``JAMNAV_PLANNER`` names: a process checks it as it starts,
    so that a missing or stale compiled core stops it at once, in one line."""
    if chosen_planner() == "reference":
        return LookaheadPolicy
    # Imported only when chosen: without its compiled core, this module raises PlannerError,
    # and the reference flies without it.
    from planning.lookahead import CompiledLookahead  # noqa: PLC0415

    # The route fields' and the reports' parts of the core, checked as early.
    compiled_module("_routes")
    compiled_module("_measuring")
    return CompiledLookahead


def lookahead_policy(scenario: Scenario, value_net: ValueNetwork, **options) -> LookaheadPolicy:
    """The lookahead with ``value_net``, by the planner ``JAMNAV_PLANNER`` names; ``options``
    as ``planning.reference.LookaheadPolicy`` takes them."""
    return require_planner()(scenario, value_net, **options)
