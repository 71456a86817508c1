"""What an optimisation is asked for and what it answers: the optimiser and initialisation choices, the
progress a callback sees, and :class:`PoseGraphResult` with its per-loop diagnosis."""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "Initialization",
    "LoopResidual",
    "OptimizationProgress",
    "Optimizer",
    "PoseGraphResult",
    "ProgressCallback",
]


class Optimizer(enum.Enum):
    """Which GTSAM optimiser :meth:`PoseGraph.optimize` runs."""

    LM = "lm"
    """Batch Levenberg-Marquardt (``gtsam.LevenbergMarquardtOptimizer``) with the edges' robust kernels."""
    GNC = "gnc"
    """Graduated non-convexity (``gtsam.GncLMOptimizer``, truncated least squares) with the prior and the
    odometry edges as known inliers; loop edges get a weight in [0, 1]. The edges' own robust kernels are
    removed by GTSAM's GNC (it needs Gaussian factors)."""
    ISAM2 = "isam2"
    """Incremental smoothing (``gtsam.ISAM2``): nodes are inserted in key order, each with the edges that
    connect it to nodes already inserted, then the estimate is relinearised until it stops changing."""


class Initialization(enum.Enum):
    """Where the batch optimisers (LM, GNC) start."""

    GIVEN = "given"
    """The nodes' initial ``T_world_x`` estimates (typically chained odometry)."""
    CHORDAL = "chordal"
    """``gtsam.InitializePose3.initialize``: chordal relaxation for the rotations, then a linear solve for
    the translations. Escapes the local minima that odometry chaining leads LM into on noisy graphs; costs
    one extra linear solve. Robust kernels are not used by it, so gross outlier loops distort it."""


@dataclass(frozen=True, slots=True)
class LoopResidual:
    """Diagnosis of one loop edge at the optimised poses.

    ``chi2`` is the squared Mahalanobis norm of the edge residual under its own (Gaussian) information,
    without robust weighting; ``whitened_error = sqrt(chi2)``. ``weight`` is the weight the optimiser gave the
    edge: the robust kernel's IRLS weight at ``whitened_error`` (1.0 for :attr:`RobustKernel.NONE`), or the
    GNC weight with :attr:`Optimizer.GNC`. ``accepted`` is ``chi2 <= chi2_threshold``.
    """

    edge_index: int
    key_from: int
    key_to: int
    chi2: float
    whitened_error: float
    weight: float
    accepted: bool


@dataclass(frozen=True, slots=True)
class OptimizationProgress:
    """What a callback sees after each step (an LM iteration, an ISAM2 update, or GNC's single call)."""

    method: Optimizer
    iteration: int
    error: float
    previous_error: float
    elapsed_s: float
    lm_lambda: float | None = None


#: ``callback(progress)``; returning ``True`` stops the optimisation after this step (``converged=False``).
ProgressCallback = Callable[[OptimizationProgress], "bool | None"]


@dataclass(frozen=True, slots=True)
class PoseGraphResult:
    """Outcome of :meth:`PoseGraph.optimize`.

    ``initial_error`` / ``final_error`` are GTSAM's graph error ``sum_f loss_f`` (``0.5 * chi2`` for a
    Gaussian factor, the kernel's loss of ``sqrt(chi2)`` for a robust one) of the graph as built -- the
    edges' own kernels and the priors included -- at the poses the optimiser started from (the nodes'
    estimates, or the chordal initialisation) and at the optimised poses; the same objective
    for every method, so results of different methods compare. ``iterations`` counts LM iterations, ISAM2
    ``update`` calls (one per node plus the relinearisation passes), or is ``None`` for GNC (GTSAM does not
    expose its count). ``converged`` is GTSAM's convergence test (relative / absolute error decrease) for LM
    and ISAM2 -- ``False`` when the iteration limit was hit, a callback stopped it, or LM gave up without
    decreasing the error -- and, for GNC, "every loop weight settled at 0 or 1".
    ``gnc_edge_weights`` (GNC only) is aligned with :attr:`PoseGraph.edges`.
    """

    poses: Mapping[int, NDArray[np.float64]]
    initial_error: float
    final_error: float
    iterations: int | None
    converged: bool
    method: Optimizer
    initialization: Initialization
    loop_residuals: tuple[LoopResidual, ...]
    chi2_threshold: float
    elapsed_s: float
    n_nodes: int
    n_edges: int
    gnc_edge_weights: tuple[float, ...] | None = None
    warnings: tuple[str, ...] = field(default=())
    covariances: Mapping[int, NDArray[np.float64]] | None = None
    """Each node's marginal covariance at the optimum when asked for (:meth:`PoseGraph.marginal_covariances`)."""

    @property
    def rejected_loops(self) -> tuple[LoopResidual, ...]:
        """Loop edges that fail the chi2 gate after optimisation."""
        return tuple(r for r in self.loop_residuals if not r.accepted)

    @property
    def accepted_loops(self) -> tuple[LoopResidual, ...]:
        return tuple(r for r in self.loop_residuals if r.accepted)
