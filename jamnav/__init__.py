"""The ``jamnav`` command line and the supervisor of the distributed system."""

import shared  # noqa: F401  (pins the BLAS threads before numpy loads)
