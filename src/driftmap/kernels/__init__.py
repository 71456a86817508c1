"""The compiled hot loops (numba), below every layer that uses them: :mod:`~driftmap.kernels.points` (depth
back-projection, the map view's transforms and queries) and :mod:`~driftmap.kernels.volume` (the volumetric
layers' ray traversal and TSDF), :mod:`~driftmap.kernels.groups` (the double-wall detector's group sums) and
:mod:`~driftmap.kernels.queries` (the decisions' per-query loops). Importing this package picks numba's threading layer once for all of them.

Only code that needs them imports these modules (they pull in numba and llvmlite): ``import driftmap`` and
``import driftmap.store`` stay light.
"""

import os

import numba

if "NUMBA_THREADING_LAYER" not in os.environ:
    # numba's own work queue is always available (the TBB layer warns about old TBB builds)
    numba.config.THREADING_LAYER = "workqueue"
