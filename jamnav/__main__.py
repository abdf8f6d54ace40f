"""Where the ``jamnav`` command starts (the console script, and ``python -m jamnav``): it sizes
the BLAS pools (``shared.threads``) before the command line loads numpy."""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

from shared.threads import one_blas_thread


def main(argv: Sequence[str] | None = None) -> int:
    one_blas_thread(os.environ)
    from jamnav.cli import main as run_command

    return run_command(argv)


if __name__ == "__main__":
    sys.exit(main())
