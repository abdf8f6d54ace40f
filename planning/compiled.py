"""Which planner the environment chooses (``JAMNAV_PLANNER``: ``compiled``, the default, or
``reference``), and the modules of the compiled core it flies, each refused in one line naming
the fix where it is not built or was built from other source than is beside it: never a silent
fall back to the numpy reference."""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from types import ModuleType

from planning import PLANNER_VARIABLE, PLANNERS, PlannerError
from planning.source_digest import source_digest

REMEDY = "run `make install`, or set JAMNAV_PLANNER=reference for the numpy planner"


def chosen_planner() -> str:
    choice = os.environ.get(PLANNER_VARIABLE, "compiled")
    if choice not in PLANNERS:
        raise PlannerError(f"{PLANNER_VARIABLE}={choice!r}: expected one of {', '.join(PLANNERS)}")
    return choice


def compiled_module(name: str) -> ModuleType:
    """The compiled core's module ``planning.<name>`` (``_lookahead``, ``_routes``)."""
    try:
        module = importlib.import_module(f"planning.{name}")
    except ImportError as exc:
        raise PlannerError(f"the planner's compiled core is not built ({exc}): {REMEDY}") from None
    if source_digest(Path(__file__).parent) not in (None, module.SOURCE_DIGEST):
        raise PlannerError(f"the planner's compiled core ({name}) was built from other source "
                           f"than is beside it: {REMEDY}")
    return module
