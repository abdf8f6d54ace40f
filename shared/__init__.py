"""What every process of the system shares: the scenario, the world's physics (radio model,
shadowing, kinematics, rewards, outcomes), what a UAV observes and measures, and the transport
(messages, topics, the bus and its access control). How a UAV plans is in ``planning``, which
this package never imports."""

import os

# The networks are small: numpy's BLAS (and torch) spreading one forward over several threads
# costs more CPU than it saves (a lookahead forward: 6.3 ms of CPU on two threads, 2.7 ms on
# one), and a system's processes already share the cores. Set before numpy loads; a setting of
# the user's own wins.
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
