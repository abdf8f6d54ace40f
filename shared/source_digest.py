"""Which source the compiled core was built from: the build stamps each module with this digest,
and a module whose stamp differs from the source beside it is refused (``shared.compiled_core``)."""

from __future__ import annotations

import hashlib
from pathlib import Path

# Relative to the project's root: a change to any of them makes every module stale.
COMPILED_SOURCES = ("planning/_lookahead.pyx", "planning/_routes.pyx", "planning/_regression.pyx",
                    "planning/_evidence.pyx", "planning/_measuring.pyx", "planning/_dense.h",
                    "planning/_regression.h", "shared/_radio.pyx", "shared/_vector_math.h")


def source_digest(root: Path) -> str | None:
    """sha256 of the compiled core's sources under the project's ``root``; None where they are
    not (an installed wheel carries the modules alone)."""
    digest = hashlib.sha256()
    for name in COMPILED_SOURCES:
        path = Path(root) / name
        if not path.is_file():
            return None
        digest.update(path.read_bytes())
    return digest.hexdigest()
