"""Pose-graph optimisation: a thin, typed layer over GTSAM.

A :class:`PoseGraph` holds nodes (integer keys, the frame ids) with their initial ``T_world_x`` estimates,
priors, odometry edges and loop edges. :meth:`PoseGraph.optimize` builds a GTSAM
``NonlinearFactorGraph`` (``PriorFactorPose3`` / ``BetweenFactorPose3``, robust edges wrapped in
``noiseModel.Robust``) and runs Levenberg-Marquardt, graduated non-convexity (``GncLMOptimizer``) or
ISAM2 on it; the answer is a :class:`PoseGraphResult` that carries its own quality (errors, iterations,
convergence, per-loop chi2 / weight / accepted).

Tangent ordering -- read this before passing an information matrix:

* driftmap (and the g2o file format, and :func:`driftmap.geometry.se3_log`) orders a 6-vector on SE(3) as
  ``[translation(3), rotation(3)]`` = ``[tx, ty, tz, rx, ry, rz]``.
* GTSAM's ``Pose3`` orders its tangent space (and therefore every ``Pose3`` noise model) as
  ``[rotation(3), translation(3)]``.

Every ``information_6x6`` / covariance in this module's API is in the driftmap order
``[translation, rotation]``; the module permutes it (:func:`reorder_6x6`) when it builds GTSAM noise models
and permutes back when it reads them. Both orders describe the same right-perturbation
``T_meas^-1 @ T_from^-1 @ T_to = exp(xi)`` (GTSAM's ``Pose3`` chart is the SE(3) exponential map, the same
as :func:`driftmap.geometry.se3_exp`), so the permutation is the whole conversion.

Modules (one concept each; import from the package, which re-exports every public name):

* :class:`PoseGraphError` lives in :mod:`driftmap.errors` with every other error (:mod:`~driftmap.posegraph.errors`
  re-exports it);
* :mod:`~driftmap.posegraph.tangent` -- :class:`TangentOrder`, :func:`reorder_6x6`, information checks;
* :mod:`~driftmap.posegraph.robust` -- :class:`RobustKernel`, kernel widths, the chi2 gate;
* :mod:`~driftmap.posegraph.measurements` -- :class:`Edge`, :class:`EdgeKind`, :class:`Prior`, the default prior;
* :mod:`~driftmap.posegraph.result` -- :class:`Optimizer`, :class:`Initialization`, progress and result types;
* :mod:`~driftmap.posegraph.factors` -- conversion to and from GTSAM factors, noise models and values;
* :mod:`~driftmap.posegraph.solvers` -- the LM, GNC and ISAM2 runs and the loop diagnosis;
* :mod:`~driftmap.posegraph.g2o` -- reading and writing g2o files;
* :mod:`~driftmap.posegraph.graph` -- :class:`PoseGraph` and :func:`optimize_g2o`.
"""

from __future__ import annotations

from driftmap.errors import PoseGraphError
from driftmap.posegraph.g2o import PLANAR_OUT_OF_PLANE_INFORMATION
from driftmap.posegraph.graph import PoseGraph, optimize_g2o
from driftmap.posegraph.graph import logger as logger  # not in __all__, importable as before
from driftmap.posegraph.measurements import DEFAULT_PRIOR_SIGMA_M, DEFAULT_PRIOR_SIGMA_RAD, Edge, EdgeKind, Prior
from driftmap.posegraph.result import (
    Initialization,
    LoopResidual,
    OptimizationProgress,
    Optimizer,
    PoseGraphResult,
)
from driftmap.posegraph.result import (
    ProgressCallback as ProgressCallback,  # not in __all__, importable as before
)
from driftmap.posegraph.robust import CHI2_6DOF_99, RobustKernel, default_robust_param
from driftmap.posegraph.tangent import TangentOrder, information_from_gtsam, information_to_gtsam, reorder_6x6

__all__ = [
    "CHI2_6DOF_99",
    "DEFAULT_PRIOR_SIGMA_M",
    "DEFAULT_PRIOR_SIGMA_RAD",
    "PLANAR_OUT_OF_PLANE_INFORMATION",
    "Edge",
    "EdgeKind",
    "Initialization",
    "LoopResidual",
    "OptimizationProgress",
    "Optimizer",
    "PoseGraph",
    "PoseGraphError",
    "PoseGraphResult",
    "Prior",
    "RobustKernel",
    "TangentOrder",
    "default_robust_param",
    "information_from_gtsam",
    "information_to_gtsam",
    "optimize_g2o",
    "reorder_6x6",
]
