"""Which source the compiled core was built from: the build stamps each module with this digest,
and the planner refuses a module whose stamp differs from the source beside it."""

from __future__ import annotations

import hashlib
from pathlib import Path

COMPILED_SOURCES = ("_lookahead.pyx", "_routes.pyx", "_regression.pyx", "_evidence.pyx",
                    "_measuring.pyx", "_dense.h", "_vector_math.h", "_regression.h")


def source_digest(directory: Path) -> str | None:
    """sha256 of the compiled core's sources in ``directory``; None where they are not (an
    installed wheel carries the module alone)."""
    digest = hashlib.sha256()
    for name in COMPILED_SOURCES:
        path = Path(directory) / name
        if not path.is_file():
            return None
        digest.update(path.read_bytes())
    return digest.hexdigest()
