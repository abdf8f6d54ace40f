"""Which implementation the environment chooses for the project's compiled core
(``JAMNAV_PLANNER``: ``compiled``, the default, or ``reference``, the numpy code each compiled
module is held to), and the core's modules, each refused in one line naming the fix where it is
not built or was built from other source than is beside it: never a silent fall back to the
numpy reference. The planner's parts are in ``planning``; the radio's is ``shared._radio``."""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from types import ModuleType

from shared.source_digest import source_digest

CORE_VARIABLE = "JAMNAV_PLANNER"
CHOICES = ("compiled", "reference")
REMEDY = f"run `make install`, or set {CORE_VARIABLE}=reference for the numpy reference"
_ROOT = Path(__file__).resolve().parent.parent


class CompiledCoreError(RuntimeError):
    """The compiled core asked for cannot run (one line, naming the fix)."""


def chosen_core() -> str:
    choice = os.environ.get(CORE_VARIABLE, "compiled")
    if choice not in CHOICES:
        raise CompiledCoreError(f"{CORE_VARIABLE}={choice!r}: expected one of "
                                f"{', '.join(CHOICES)}")
    return choice


def compiled_module(name: str) -> ModuleType:
    """The compiled core's module ``name`` (``planning._lookahead``, ``shared._radio``)."""
    try:
        module = importlib.import_module(name)
    except ImportError as exc:
        raise CompiledCoreError(f"the compiled core is not built ({exc}): {REMEDY}") from None
    if source_digest(_ROOT) not in (None, module.SOURCE_DIGEST):
        raise CompiledCoreError(f"the compiled core ({name}) was built from other source than "
                                f"is beside it: {REMEDY}")
    return module
