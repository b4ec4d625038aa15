"""Pure core of ppe_ros: scan model, plane fitting, PPE extraction, synthetic scans, evaluation.

Only numpy and numba are needed here; nothing in ``ppe_ros.core`` imports ROS.

Importing it sets ``OMP_WAIT_POLICY=PASSIVE`` for the process unless ``OMP_WAIT_POLICY`` or
``GOMP_SPINCOUNT`` is already set (see :data:`OMP_WAIT_POLICY_DEFAULT`).
"""

from __future__ import annotations

import os

#: The OpenMP wait policy the extractor asks for. numba runs its parallel loops on an OpenMP runtime
#: whose threads, by default, keep spinning for a few milliseconds after each loop. The extractor
#: runs its tiles and candidate pairs on threads of its own right after such loops, and on a machine
#: with as many cores as threads a spinning OpenMP thread holds the core that the next task needs
#: (the second tile thread of a 128 x 1024 sweep started about 4 ms late). PASSIVE threads sleep when
#: a loop ends. The runtime reads the variable when it loads (at the first parallel loop of the
#: process): a runtime that another library loaded earlier keeps its setting, and a user's own
#: OMP_WAIT_POLICY or GOMP_SPINCOUNT is left as it is.
OMP_WAIT_POLICY_DEFAULT = 'PASSIVE'

if 'OMP_WAIT_POLICY' not in os.environ and 'GOMP_SPINCOUNT' not in os.environ:
    os.environ['OMP_WAIT_POLICY'] = OMP_WAIT_POLICY_DEFAULT
