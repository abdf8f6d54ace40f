"""The lookahead planner every UAV flies: the compiled core (``planning.lookahead``) by
default, or the numpy planner of ``shared.policy``, its reference, with
``JAMNAV_PLANNER=reference`` in the environment of any command.

Agents, evaluation and training build their policy here; ``shared`` never imports this
package."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the command line imports this package for PlannerError alone
    from shared.networks import ValueNetwork
    from shared.policy import LookaheadPolicy
    from shared.scenario import Scenario

PLANNER_VARIABLE = "JAMNAV_PLANNER"
PLANNERS = ("compiled", "reference")


class PlannerError(RuntimeError):
    """The planner asked for cannot run (one line, naming the fix)."""


def chosen_planner() -> str:
    choice = os.environ.get(PLANNER_VARIABLE, "compiled")
    if choice not in PLANNERS:
        raise PlannerError(f"{PLANNER_VARIABLE}={choice!r}: expected one of {', '.join(PLANNERS)}")
    return choice


def require_planner() -> type[LookaheadPolicy]:
    """The class of the planner ``JAMNAV_PLANNER`` names: a process checks it as it starts,
    so that a missing or stale compiled core stops it at once, in one line."""
    if chosen_planner() == "reference":
        from shared.policy import LookaheadPolicy  # noqa: PLC0415

        return LookaheadPolicy
    from planning.lookahead import CompiledLookahead  # noqa: PLC0415 (raises PlannerError)

    return CompiledLookahead


def lookahead_policy(scenario: Scenario, value_net: ValueNetwork, **options) -> LookaheadPolicy:
    """The lookahead with ``value_net``, by the planner ``JAMNAV_PLANNER`` names; ``options``
    as ``shared.policy.LookaheadPolicy`` takes them."""
    return require_planner()(scenario, value_net, **options)
