"""How a UAV plans: the lookahead every UAV flies and all it reads.

The lookahead runs as the compiled core (``planning.lookahead``) by default, or as the numpy
lookahead of ``planning.reference``, its reference, with ``JAMNAV_PLANNER=reference`` in the
environment of any command. Both read the radio maps of ``planning.maps`` (with the route
distance of ``planning.routes``), the joint state of ``planning.features`` and the networks of
``planning.networks`` (their safetensors form and numpy forward, the SINR map's too); the
reciprocal prediction of the others solves ORCA (``planning.orca``).

Agents, evaluation and training build their policy here (``lookahead_policy``). This package
imports ``shared``; ``shared`` and the world (``world_sim``) never import it."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import shared  # noqa: F401  (pins the BLAS threads before numpy loads)

if TYPE_CHECKING:  # the command line imports this package for PlannerError alone
    from planning.networks import ValueNetwork
    from planning.reference import LookaheadPolicy
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
        from planning.reference import LookaheadPolicy  # noqa: PLC0415

        return LookaheadPolicy
    from planning.lookahead import CompiledLookahead  # noqa: PLC0415 (raises PlannerError)

    return CompiledLookahead


def lookahead_policy(scenario: Scenario, value_net: ValueNetwork, **options) -> LookaheadPolicy:
    """The lookahead with ``value_net``, by the planner ``JAMNAV_PLANNER`` names; ``options``
    as ``planning.reference.LookaheadPolicy`` takes them."""
    return require_planner()(scenario, value_net, **options)
