"""An agent process: one per UAV."""

import shared  # noqa: F401  (pins the BLAS threads before numpy loads)
