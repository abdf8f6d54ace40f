"""The cloud: the measurement memory, the online SINR map and value-network training."""

import shared  # noqa: F401  (pins the BLAS threads before numpy loads)
