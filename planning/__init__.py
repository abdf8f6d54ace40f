"""How a UAV plans: the lookahead every UAV flies and all it reads.

The lookahead runs as the compiled core (``planning.lookahead``) by default, or as the numpy
lookahead of ``planning.reference``, its reference, with ``JAMNAV_PLANNER=reference`` in the
environment of any command. Both read the radio maps of ``planning.maps`` (with the route
distance of ``planning.routes``), the joint state of ``planning.features`` and the networks of
``planning.networks`` (their safetensors form and numpy forward, the SINR map's too); the
reciprocal prediction of the others solves ORCA (``planning.orca``).

Agents, evaluation and training build their policy with ``planning.chosen.lookahead_policy``.
This package imports ``shared``; ``shared`` and the world (``world_sim``) never import it."""

from __future__ import annotations

from shared.compiled_core import CHOICES as PLANNERS
from shared.compiled_core import CORE_VARIABLE as PLANNER_VARIABLE
from shared.compiled_core import CompiledCoreError as PlannerError

__all__ = ["PLANNERS", "PLANNER_VARIABLE", "PlannerError"]
