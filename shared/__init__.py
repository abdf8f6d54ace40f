"""What every process of the system shares: scenario, radio model, kinematics, features,
networks, messages and topics."""

import os

# The networks are small: numpy's BLAS (and torch) spreading one forward over several threads
# costs more CPU than it saves (a lookahead forward: 6.3 ms of CPU on two threads, 2.7 ms on
# one), and a system's processes already share the cores. Set before numpy loads; a setting of
# the user's own wins.
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
