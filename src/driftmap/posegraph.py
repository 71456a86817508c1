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
"""

from __future__ import annotations

import enum
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.errors import DriftmapError

logger = logging.getLogger(__name__)

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

#: 99 % quantile of the chi-square distribution with 6 degrees of freedom (``scipy.stats.chi2.ppf(0.99, 6)``).
#: A loop edge whose chi2 after optimisation exceeds it is reported as not accepted. GTSAM's GNC uses the
#: same gate by default (inlier cost threshold ``0.5 * chi2inv(0.99, dim)`` on the factor error).
CHI2_6DOF_99 = 16.811893829770927

#: Standard deviations of the default prior that fixes the gauge on the lowest node key (see
#: :meth:`PoseGraph.optimize`). The prior is the only absolute constraint, so its residual is zero at the
#: optimum whatever its strength; "tight" only has to beat the rest of the graph, not be infinite.
DEFAULT_PRIOR_SIGMA_M = 1e-4
DEFAULT_PRIOR_SIGMA_RAD = 1e-4

#: Information (1 / variance) given to the out-of-plane components ``tz, rx, ry`` when a 2D (SE2) g2o file is
#: lifted into SE(3): a stiff constraint that keeps the graph in the plane (sigma 1 mm / 1 mrad), so the lifted
#: problem has the same optimum and the same error as the 2D one.
PLANAR_OUT_OF_PLANE_INFORMATION = 1e6


class PoseGraphError(DriftmapError):
    """A pose graph is malformed (unknown key, bad information matrix, unreadable g2o file) or GTSAM failed
    on it (indeterminate linear system, an ISAM2 node with no constraint to the graph)."""


class EdgeKind(enum.Enum):
    """What an edge measures."""

    ODOMETRY = "odometry"
    """Consecutive-frame odometry: trusted, never down-weighted by GNC (a known inlier)."""
    LOOP = "loop"
    """A loop closure: may be wrong, robust by default, diagnosed in :attr:`PoseGraphResult.loop_residuals`."""


class RobustKernel(enum.Enum):
    """M-estimator applied to an edge's whitened residual norm ``r = sqrt(chi2)`` (GTSAM ``noiseModel.Robust``)."""

    NONE = "none"
    """Plain least squares: weight 1, loss ``r^2 / 2``."""
    HUBER = "huber"
    """Quadratic up to ``k``, linear beyond: weight ``min(1, k / r)``; a wrong edge keeps a bounded pull."""
    CAUCHY = "cauchy"
    """Weight ``1 / (1 + (r / k)^2)``: a far-off edge is almost switched off (redescending influence)."""


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


class TangentOrder(enum.Enum):
    """Order of the six components of an SE(3) tangent vector, covariance or information matrix."""

    TRANSLATION_ROTATION = "translation_rotation"
    """``[tx, ty, tz, rx, ry, rz]``: driftmap, g2o files, :func:`driftmap.geometry.se3_log`."""
    ROTATION_TRANSLATION = "rotation_translation"
    """``[rx, ry, rz, tx, ty, tz]``: GTSAM ``Pose3`` (``Pose3.Logmap``, ``Pose3`` noise models)."""


_SWAP_HALVES = np.array([3, 4, 5, 0, 1, 2])


def reorder_6x6(matrix: ArrayLike, from_order: TangentOrder, to_order: TangentOrder) -> NDArray[np.float64]:
    """Re-express a 6x6 covariance **or** information matrix in another tangent ordering.

    The orders differ by swapping the translation and rotation halves, i.e. ``M' = P M P^T`` with a
    permutation ``P``; since ``(P M P^T)^-1 = P M^-1 P^T`` the same function serves covariances and
    information matrices. Returns a new float64 array.
    """
    M = np.array(matrix, dtype=np.float64, copy=True)
    if M.shape != (6, 6):
        raise PoseGraphError(f"reorder_6x6: expected a 6x6 matrix, got shape {M.shape}")
    if not isinstance(from_order, TangentOrder) or not isinstance(to_order, TangentOrder):
        raise PoseGraphError("reorder_6x6: from_order and to_order must be TangentOrder members")
    if from_order is to_order:
        return M
    return M[np.ix_(_SWAP_HALVES, _SWAP_HALVES)]


def information_to_gtsam(information_6x6: ArrayLike) -> NDArray[np.float64]:
    """Information in driftmap order ``[translation, rotation]`` -> GTSAM ``Pose3`` order ``[rotation, translation]``."""
    return reorder_6x6(information_6x6, TangentOrder.TRANSLATION_ROTATION, TangentOrder.ROTATION_TRANSLATION)


def information_from_gtsam(information_6x6_gtsam: ArrayLike) -> NDArray[np.float64]:
    """Information in GTSAM ``Pose3`` order ``[rotation, translation]`` -> driftmap order ``[translation, rotation]``."""
    return reorder_6x6(information_6x6_gtsam, TangentOrder.ROTATION_TRANSLATION, TangentOrder.TRANSLATION_ROTATION)


def default_robust_param(kernel: RobustKernel) -> float | None:
    """Default kernel width ``k`` in whitened units (a threshold on ``sqrt(chi2)``).

    ``sqrt(CHI2_6DOF_99)`` (about 4.1) for Huber and Cauchy: a 6-dof residual inside the 99 % acceptance gate
    keeps (almost) full weight, one outside it is down-weighted. (The textbook Huber ``k = 1.345`` is for a
    scalar residual; applied to the norm of a 6-vector it would down-weight most correct edges.)
    """
    if kernel is RobustKernel.NONE:
        return None
    return math.sqrt(CHI2_6DOF_99)


def _check_information(information: ArrayLike, what: str) -> NDArray[np.float64]:
    info = np.array(information, dtype=np.float64, copy=True)
    if info.shape != (6, 6):
        raise PoseGraphError(f"{what}: information must be 6x6 ([translation, rotation] order), got shape {info.shape}")
    if not np.all(np.isfinite(info)):
        raise PoseGraphError(f"{what}: information contains NaN or inf")
    scale = float(np.abs(info).max())
    if float(np.abs(info - info.T).max()) > 1e-9 * max(scale, 1.0):
        raise PoseGraphError(f"{what}: information matrix is not symmetric")
    info = 0.5 * (info + info.T)
    try:
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        raise PoseGraphError(f"{what}: information matrix is not positive definite") from None
    info.setflags(write=False)
    return info


def _check_key(key: object, what: str) -> int:
    if isinstance(key, bool) or not isinstance(key, (int, np.integer)) or key < 0:
        raise PoseGraphError(f"{what}: node keys must be non-negative integers (frame ids), got {key!r}")
    return int(key)


def _default_prior_information() -> NDArray[np.float64]:
    sigmas = np.array([DEFAULT_PRIOR_SIGMA_M] * 3 + [DEFAULT_PRIOR_SIGMA_RAD] * 3)
    return np.diag(1.0 / sigmas**2)


@dataclass(frozen=True, slots=True)
class Edge:
    """A relative-pose measurement between two nodes.

    ``T_from_to`` is the measured ``inv(T_world_from) @ T_world_to``. ``information_6x6`` is its inverse
    covariance in **driftmap order** ``[translation(3), rotation(3)]`` (metres, radians), expressed in the
    ``to`` frame's tangent space (right perturbation: ``T_from_to_true = T_from_to @ exp(xi)``), exactly as
    a g2o ``EDGE_SE3:QUAT`` line stores it. ``robust_param`` is the kernel width ``k`` in whitened units
    (``None`` -> :func:`default_robust_param`); it must be ``None`` for :attr:`RobustKernel.NONE`.
    """

    key_from: int
    key_to: int
    T_from_to: NDArray[np.float64]
    information_6x6: NDArray[np.float64]
    kind: EdgeKind
    robust: RobustKernel = RobustKernel.NONE
    robust_param: float | None = None

    def __post_init__(self) -> None:
        key_from = _check_key(self.key_from, "Edge.key_from")
        key_to = _check_key(self.key_to, "Edge.key_to")
        what = f"edge {key_from}->{key_to}"
        if key_from == key_to:
            raise PoseGraphError(f"{what}: an edge must join two different nodes")
        object.__setattr__(self, "key_from", key_from)
        object.__setattr__(self, "key_to", key_to)
        try:
            T = geometry.as_rigid(self.T_from_to, f"{what}: T_from_to")
        except DriftmapError as exc:
            raise PoseGraphError(str(exc)) from exc
        object.__setattr__(self, "T_from_to", T)
        object.__setattr__(self, "information_6x6", _check_information(self.information_6x6, what))
        if not isinstance(self.kind, EdgeKind):
            raise PoseGraphError(f"{what}: kind must be an EdgeKind, got {self.kind!r}")
        if not isinstance(self.robust, RobustKernel):
            raise PoseGraphError(f"{what}: robust must be a RobustKernel, got {self.robust!r}")
        param = self.robust_param
        if self.robust is RobustKernel.NONE:
            if param is not None:
                raise PoseGraphError(f"{what}: robust_param given without a robust kernel")
        else:
            param = default_robust_param(self.robust) if param is None else float(param)
            if not (math.isfinite(param) and param > 0.0):
                raise PoseGraphError(f"{what}: robust_param must be a positive number, got {self.robust_param!r}")
        object.__setattr__(self, "robust_param", param)


@dataclass(frozen=True, slots=True)
class Prior:
    """An absolute pose measurement ``T_world_x`` of node ``key``; information in ``[translation, rotation]`` order."""

    key: int
    T_world_x: NDArray[np.float64]
    information_6x6: NDArray[np.float64]

    def __post_init__(self) -> None:
        key = _check_key(self.key, "Prior.key")
        object.__setattr__(self, "key", key)
        try:
            T = geometry.as_rigid(self.T_world_x, f"prior on node {key}: T_world_x")
        except DriftmapError as exc:
            raise PoseGraphError(str(exc)) from exc
        object.__setattr__(self, "T_world_x", T)
        object.__setattr__(self, "information_6x6", _check_information(self.information_6x6, f"prior on node {key}"))


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

    @property
    def rejected_loops(self) -> tuple[LoopResidual, ...]:
        """Loop edges that fail the chi2 gate after optimisation."""
        return tuple(r for r in self.loop_residuals if not r.accepted)

    @property
    def accepted_loops(self) -> tuple[LoopResidual, ...]:
        return tuple(r for r in self.loop_residuals if r.accepted)


# ----------------------------------------------------------------------------------------------------------
# GTSAM conversion
# ----------------------------------------------------------------------------------------------------------


def _pose3(T: NDArray[np.float64]) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


def _gaussian(information_6x6: NDArray[np.float64]) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Gaussian.Information(information_to_gtsam(information_6x6))


def _m_estimator(kernel: RobustKernel, param: float | None) -> gtsam.noiseModel.mEstimator.Base | None:
    if kernel is RobustKernel.HUBER:
        return gtsam.noiseModel.mEstimator.Huber.Create(param)
    if kernel is RobustKernel.CAUCHY:
        return gtsam.noiseModel.mEstimator.Cauchy.Create(param)
    return None


def _noise_model(edge: Edge) -> gtsam.noiseModel.Base:
    gaussian = _gaussian(edge.information_6x6)
    estimator = _m_estimator(edge.robust, edge.robust_param)
    return gaussian if estimator is None else gtsam.noiseModel.Robust.Create(estimator, gaussian)


def _values(poses: Mapping[int, NDArray[np.float64]]) -> gtsam.Values:
    values = gtsam.Values()
    for key, T in poses.items():
        values.insert(key, _pose3(T))
    return values


def _poses(values: gtsam.Values, keys: Iterable[int]) -> dict[int, NDArray[np.float64]]:
    out = {}
    for key in keys:
        T = np.array(values.atPose3(key).matrix(), dtype=np.float64)
        T.setflags(write=False)
        out[key] = T
    return out


def _gtsam_call(what: str, fn: Callable[[], object]) -> object:
    try:
        return fn()
    except RuntimeError as exc:  # GTSAM's C++ exceptions (IndeterminantLinearSystem, ...) arrive as RuntimeError
        raise PoseGraphError(f"{what}: GTSAM failed: {exc}") from exc


# ----------------------------------------------------------------------------------------------------------
# The graph
# ----------------------------------------------------------------------------------------------------------


class PoseGraph:
    """Nodes with initial ``T_world_x`` estimates, priors, odometry and loop edges; see the module docstring
    for the tangent ordering of every information matrix."""

    def __init__(self) -> None:
        self._nodes: dict[int, NDArray[np.float64]] = {}
        self._edges: list[Edge] = []
        self._priors: list[Prior] = []

    # -- building ------------------------------------------------------------------------------------------

    def add_node(self, key: int, T_world_x: ArrayLike) -> None:
        """Add node ``key`` (a frame id) with its initial pose estimate."""
        key = _check_key(key, "add_node")
        if key in self._nodes:
            raise PoseGraphError(f"node {key} already exists")
        try:
            self._nodes[key] = geometry.as_rigid(T_world_x, f"node {key}: T_world_x")
        except DriftmapError as exc:
            raise PoseGraphError(str(exc)) from exc

    def add_prior(self, key: int, T_world_x: ArrayLike | None = None, information_6x6: ArrayLike | None = None) -> Prior:
        """Anchor node ``key`` at ``T_world_x`` (default: its initial estimate) with ``information_6x6``
        (``[translation, rotation]`` order; default: the tight prior of :data:`DEFAULT_PRIOR_SIGMA_M` /
        :data:`DEFAULT_PRIOR_SIGMA_RAD`). A graph without any prior gets that default prior on its lowest key."""
        key = self._require_node(key, "add_prior")
        prior = Prior(
            key,
            self._nodes[key] if T_world_x is None else T_world_x,
            _default_prior_information() if information_6x6 is None else information_6x6,
        )
        self._priors.append(prior)
        return prior

    def add_odometry(
        self,
        key_from: int,
        key_to: int,
        T_from_to: ArrayLike,
        information_6x6: ArrayLike,
        *,
        robust: RobustKernel = RobustKernel.NONE,
        robust_param: float | None = None,
    ) -> Edge:
        """Add an odometry edge (a known inlier for GNC); no robust kernel by default."""
        return self.add_edge(Edge(key_from, key_to, T_from_to, information_6x6, EdgeKind.ODOMETRY, robust, robust_param))

    def add_loop(
        self,
        key_from: int,
        key_to: int,
        T_from_to: ArrayLike,
        information_6x6: ArrayLike,
        *,
        robust: RobustKernel = RobustKernel.HUBER,
        robust_param: float | None = None,
    ) -> Edge:
        """Add a loop-closure edge; Huber with ``k = sqrt(CHI2_6DOF_99)`` by default."""
        return self.add_edge(Edge(key_from, key_to, T_from_to, information_6x6, EdgeKind.LOOP, robust, robust_param))

    def add_edge(self, edge: Edge) -> Edge:
        """Add a ready-made :class:`Edge`; both nodes must exist."""
        if not isinstance(edge, Edge):
            raise PoseGraphError(f"add_edge: expected an Edge, got {type(edge).__name__}")
        self._require_node(edge.key_from, f"edge {edge.key_from}->{edge.key_to}")
        self._require_node(edge.key_to, f"edge {edge.key_from}->{edge.key_to}")
        self._edges.append(edge)
        return edge

    def _require_node(self, key: int, what: str) -> int:
        key = _check_key(key, what)
        if key not in self._nodes:
            raise PoseGraphError(f"{what}: node {key} does not exist (add_node it first)")
        return key

    # -- reading -------------------------------------------------------------------------------------------

    @property
    def nodes(self) -> Mapping[int, NDArray[np.float64]]:
        """Read-only view: key -> initial ``T_world_x``."""
        return MappingProxyType(self._nodes)

    @property
    def edges(self) -> tuple[Edge, ...]:
        return tuple(self._edges)

    @property
    def priors(self) -> tuple[Prior, ...]:
        return tuple(self._priors)

    @property
    def loop_edges(self) -> tuple[Edge, ...]:
        return tuple(e for e in self._edges if e.kind is EdgeKind.LOOP)

    def effective_priors(self) -> tuple[Prior, ...]:
        """The priors the optimiser uses: the ones added, or the default prior on the lowest key."""
        if self._priors:
            return tuple(self._priors)
        if not self._nodes:
            return ()
        key = min(self._nodes)
        return (Prior(key, self._nodes[key], _default_prior_information()),)

    # -- GTSAM ---------------------------------------------------------------------------------------------

    def to_gtsam(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The factor graph (effective priors first, then the edges in order) and the initial values."""
        graph = gtsam.NonlinearFactorGraph()
        for prior in self.effective_priors():
            graph.add(gtsam.PriorFactorPose3(prior.key, _pose3(prior.T_world_x), _gaussian(prior.information_6x6)))
        for edge in self._edges:
            graph.add(gtsam.BetweenFactorPose3(edge.key_from, edge.key_to, _pose3(edge.T_from_to), _noise_model(edge)))
        return graph, _values(self._nodes)

    def error(self, poses: Mapping[int, ArrayLike] | None = None) -> float:
        """GTSAM's graph error (see :class:`PoseGraphResult`) at ``poses`` (default: the initial estimates)."""
        graph, values = self.to_gtsam()
        if poses is not None:
            values = self._values_for(poses)
        return float(graph.error(values))

    def _values_for(self, poses: Mapping[int, ArrayLike]) -> gtsam.Values:
        missing = set(self._nodes) - set(poses)
        if missing:
            raise PoseGraphError(f"poses are missing {len(missing)} node(s), e.g. {sorted(missing)[:5]}")
        return _values({k: np.asarray(poses[k], dtype=np.float64) for k in self._nodes})

    # -- optimisation --------------------------------------------------------------------------------------

    def optimize(
        self,
        method: Optimizer = Optimizer.LM,
        *,
        max_iterations: int = 100,
        relative_error_tol: float = 1e-5,
        absolute_error_tol: float = 1e-5,
        chi2_threshold: float = CHI2_6DOF_99,
        isam2_relinearize_threshold: float = 0.01,
        initialization: Initialization = Initialization.GIVEN,
        callback: ProgressCallback | None = None,
        warn: bool = True,
    ) -> PoseGraphResult:
        """Optimise the graph and diagnose its loop edges.

        ``max_iterations`` bounds LM iterations (also GNC's inner LM) and ISAM2's final relinearisation
        passes; the tolerances are GTSAM's ``relativeErrorTol`` / ``absoluteErrorTol`` (defaults equal GTSAM's).
        ``isam2_relinearize_threshold`` is ISAM2's relinearisation threshold (tangent-space step size;
        ISAM2 relinearises on every update). ``initialization`` picks the start of LM / GNC
        (:attr:`Initialization.CHORDAL` is not available for ISAM2, which chains odometry as it goes).
        ``callback(progress)`` is called after every LM iteration / ISAM2
        update and once after GNC; returning ``True`` stops the optimisation. ``warn=False`` logs loops that fail
        the chi2 gate and a failure to converge at INFO instead of WARNING (for intermediate rounds of a caller
        that re-optimises, e.g. an information calibration); the result carries them either way.
        Raises :class:`PoseGraphError` for an empty graph or when GTSAM fails.
        """
        if not isinstance(method, Optimizer):
            raise PoseGraphError(f"optimize: method must be an Optimizer, got {method!r}")
        if not self._nodes:
            raise PoseGraphError("optimize: the graph has no nodes")
        if max_iterations < 1:
            raise PoseGraphError(f"optimize: max_iterations must be >= 1, got {max_iterations}")
        if not isinstance(initialization, Initialization):
            raise PoseGraphError(f"optimize: initialization must be an Initialization, got {initialization!r}")
        if initialization is Initialization.CHORDAL and method is Optimizer.ISAM2:
            raise PoseGraphError("optimize: Initialization.CHORDAL is a batch initialisation; ISAM2 cannot use it")
        started = time.perf_counter()
        graph, initial = self.to_gtsam()
        if initialization is Initialization.CHORDAL:
            initial = _gtsam_call("chordal initialisation", lambda: gtsam.InitializePose3.initialize(graph))
        initial_error = float(graph.error(initial))
        logger.info(
            "pose graph: %d nodes, %d edges (%d loops), %s from %s, initial error %.6g",
            len(self._nodes), len(self._edges), len(self.loop_edges), method.name, initialization.name, initial_error,
        )
        lm_params = gtsam.LevenbergMarquardtParams()
        lm_params.setMaxIterations(int(max_iterations))
        lm_params.setRelativeErrorTol(float(relative_error_tol))
        lm_params.setAbsoluteErrorTol(float(absolute_error_tol))
        warnings: list[str] = []
        gnc_edge_weights: tuple[float, ...] | None = None
        if method is Optimizer.LM:
            values, iterations, converged = self._run_lm(graph, initial, lm_params, initial_error, started, callback, warnings)
        elif method is Optimizer.GNC:
            values, converged, gnc_edge_weights = self._run_gnc(graph, initial, lm_params, initial_error, started, callback)
            iterations = None
            if not converged:
                warnings.append("GNC left some loop weights between 0 and 1")
        else:
            values, iterations, converged = self._run_isam2(
                graph, lm_params, isam2_relinearize_threshold, started, callback, warnings
            )
        final_error = float(graph.error(values))
        loop_residuals = self._loop_residuals(values, chi2_threshold, gnc_edge_weights)
        elapsed_s = time.perf_counter() - started
        result = PoseGraphResult(
            poses=MappingProxyType(_poses(values, self._nodes)),
            initial_error=initial_error,
            final_error=final_error,
            iterations=iterations,
            converged=converged,
            method=method,
            initialization=initialization,
            loop_residuals=loop_residuals,
            chi2_threshold=float(chi2_threshold),
            elapsed_s=elapsed_s,
            n_nodes=len(self._nodes),
            n_edges=len(self._edges),
            gnc_edge_weights=gnc_edge_weights,
            warnings=tuple(warnings),
        )
        logger.info(
            "pose graph %s: error %.6g -> %.6g, %s iterations, converged=%s, %d/%d loops rejected, %.3f s",
            method.name, initial_error, final_error, iterations, converged,
            len(result.rejected_loops), len(loop_residuals), elapsed_s,
        )
        rejected = result.rejected_loops
        report = logger.warning if warn else logger.info
        if rejected:
            report(
                "%d of %d loop edges fail the chi2 gate %.4g after optimisation, e.g. %s",
                len(rejected), len(loop_residuals), chi2_threshold,
                ", ".join(f"{r.key_from}->{r.key_to} (chi2 {r.chi2:.3g}, weight {r.weight:.3g})" for r in rejected[:5]),
            )
        if not converged:
            report("pose graph %s did not converge (%s)", method.name, "; ".join(warnings) or "see result")
        return result

    def _run_lm(
        self,
        graph: gtsam.NonlinearFactorGraph,
        initial: gtsam.Values,
        params: gtsam.LevenbergMarquardtParams,
        initial_error: float,
        started: float,
        callback: ProgressCallback | None,
        warnings: list[str],
    ) -> tuple[gtsam.Values, int, bool]:
        # The loop of GTSAM's NonlinearOptimizer::defaultOptimize, unrolled so a callback can watch and stop it.
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        error = initial_error
        converged = error <= params.getErrorTol()
        while not converged and optimizer.iterations() < params.getMaxIterations():
            before_iterations = optimizer.iterations()
            previous = error
            _gtsam_call("Levenberg-Marquardt", optimizer.iterate)
            error = float(optimizer.error())
            if callback is not None and callback(
                OptimizationProgress(Optimizer.LM, optimizer.iterations(), error, previous,
                                     time.perf_counter() - started, float(optimizer.lambda_()))
            ):
                warnings.append(f"stopped by the callback after {optimizer.iterations()} iterations")
                break
            if not math.isfinite(error):
                warnings.append("the error became non-finite")
                break
            if optimizer.iterations() == before_iterations:
                warnings.append(f"Levenberg-Marquardt could not decrease the error {error:.6g} (gave up at maximum lambda)")
                break
            converged = gtsam.checkConvergence(params, previous, error)
        if not converged and not warnings:
            warnings.append(f"reached max_iterations={params.getMaxIterations()}")
        return optimizer.values(), int(optimizer.iterations()), bool(converged)

    def _run_gnc(
        self,
        graph: gtsam.NonlinearFactorGraph,
        initial: gtsam.Values,
        lm_params: gtsam.LevenbergMarquardtParams,
        initial_error: float,
        started: float,
        callback: ProgressCallback | None,
    ) -> tuple[gtsam.Values, bool, tuple[float, ...]]:
        n_priors = len(self.effective_priors())
        known_inliers = list(range(n_priors)) + [
            n_priors + i for i, e in enumerate(self._edges) if e.kind is EdgeKind.ODOMETRY
        ]
        params = gtsam.GncLMParams(lm_params)
        params.setKnownInliers(known_inliers)
        optimizer = gtsam.GncLMOptimizer(graph, initial, params)
        values = _gtsam_call("GNC", optimizer.optimize)
        weights = np.asarray(optimizer.getWeights(), dtype=np.float64)
        edge_weights = tuple(float(w) for w in weights[n_priors:])
        loop_weights = [w for w, e in zip(edge_weights, self._edges) if e.kind is EdgeKind.LOOP]
        converged = all(min(w, 1.0 - w) <= params.weightsTol for w in loop_weights)
        if callback is not None:
            callback(OptimizationProgress(Optimizer.GNC, 1, float(graph.error(values)), initial_error,
                                          time.perf_counter() - started))
        return values, converged, edge_weights

    def _run_isam2(
        self,
        graph: gtsam.NonlinearFactorGraph,
        lm_params: gtsam.LevenbergMarquardtParams,
        relinearize_threshold: float,
        started: float,
        callback: ProgressCallback | None,
        warnings: list[str],
    ) -> tuple[gtsam.Values, int, bool]:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(float(relinearize_threshold))
        params.relinearizeSkip = 1
        isam = gtsam.ISAM2(params)
        priors_by_key: dict[int, list[Prior]] = {}
        for prior in self.effective_priors():
            priors_by_key.setdefault(prior.key, []).append(prior)
        edges_by_key: dict[int, list[Edge]] = {}
        for edge in self._edges:  # an edge enters with the later of its two nodes
            edges_by_key.setdefault(max(edge.key_from, edge.key_to), []).append(edge)
        inserted: set[int] = set()
        added = gtsam.NonlinearFactorGraph()
        error = previous = math.nan
        updates = 0
        for key in sorted(self._nodes):
            factors = gtsam.NonlinearFactorGraph()
            for prior in priors_by_key.get(key, ()):
                factors.add(gtsam.PriorFactorPose3(key, _pose3(prior.T_world_x), _gaussian(prior.information_6x6)))
            edges = edges_by_key.get(key, [])
            for edge in edges:
                factors.add(gtsam.BetweenFactorPose3(edge.key_from, edge.key_to, _pose3(edge.T_from_to), _noise_model(edge)))
            values = gtsam.Values()
            values.insert(key, _pose3(self._incremental_initial(key, edges, inserted, isam)))
            if factors.size() == 0:
                raise PoseGraphError(
                    f"ISAM2: node {key} has no prior and no edge to a node with a lower key; "
                    "insert nodes so that each one is connected to earlier ones"
                )
            _gtsam_call(f"ISAM2 update at node {key}", lambda: isam.update(factors, values))
            inserted.add(key)
            updates += 1
            if callback is not None:
                for i in range(factors.size()):
                    added.add(factors.at(i))
                previous, error = error, float(added.error(isam.calculateEstimate()))
                if callback(OptimizationProgress(Optimizer.ISAM2, updates, error, previous, time.perf_counter() - started)):
                    warnings.append(f"stopped by the callback at node {key}")
                    return isam.calculateEstimate(), updates, False
        # relinearise the whole graph until the error stops changing (GTSAM's batch convergence test)
        error = float(graph.error(isam.calculateEstimate()))
        converged = False
        for _ in range(int(lm_params.getMaxIterations())):
            _gtsam_call("ISAM2 relinearisation", isam.update)
            updates += 1
            previous, error = error, float(graph.error(isam.calculateEstimate()))
            if callback is not None and callback(
                OptimizationProgress(Optimizer.ISAM2, updates, error, previous, time.perf_counter() - started)
            ):
                warnings.append("stopped by the callback while relinearising")
                break
            if gtsam.checkConvergence(lm_params, previous, error):
                converged = True
                break
        else:
            warnings.append(f"ISAM2 still changing after {lm_params.getMaxIterations()} relinearisation passes")
        return isam.calculateEstimate(), updates, converged

    def _incremental_initial(self, key: int, edges: list[Edge], inserted: set[int], isam: gtsam.ISAM2) -> NDArray[np.float64]:
        """Initial value of a node entering ISAM2: chained from the current estimate of an earlier node
        through an odometry edge (what an online system does), else its stored initial estimate."""
        for edge in edges:
            if edge.kind is not EdgeKind.ODOMETRY:
                continue
            if edge.key_to == key and edge.key_from in inserted:
                return isam.calculateEstimatePose3(edge.key_from).matrix() @ edge.T_from_to
            if edge.key_from == key and edge.key_to in inserted:
                return isam.calculateEstimatePose3(edge.key_to).matrix() @ geometry.invert(edge.T_from_to)
        return self._nodes[key]

    def _loop_residuals(
        self, values: gtsam.Values, chi2_threshold: float, gnc_edge_weights: tuple[float, ...] | None
    ) -> tuple[LoopResidual, ...]:
        out = []
        for index, edge in enumerate(self._edges):
            if edge.kind is not EdgeKind.LOOP:
                continue
            gaussian = gtsam.BetweenFactorPose3(edge.key_from, edge.key_to, _pose3(edge.T_from_to), _gaussian(edge.information_6x6))
            chi2 = 2.0 * float(gaussian.error(values))
            whitened = math.sqrt(max(chi2, 0.0))
            if gnc_edge_weights is not None:
                weight = gnc_edge_weights[index]
            else:
                estimator = _m_estimator(edge.robust, edge.robust_param)
                weight = 1.0 if estimator is None else float(estimator.weight(whitened))
            out.append(LoopResidual(index, edge.key_from, edge.key_to, chi2, whitened, weight, chi2 <= chi2_threshold))
        return tuple(out)

    # -- g2o -----------------------------------------------------------------------------------------------

    @classmethod
    def from_g2o(
        cls,
        path: str | Path,
        *,
        loop_robust: RobustKernel = RobustKernel.NONE,
        loop_robust_param: float | None = None,
    ) -> PoseGraph:
        """Read a g2o file with ``gtsam.readG2o``.

        3D files (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``) are read as they are. 2D files (``VERTEX_SE2`` /
        ``EDGE_SE2``) are lifted into SE(3) in the z = 0 plane: ``(x, y, theta)`` becomes a rotation about z,
        the 3x3 information ``[x, y, theta]`` lands on ``[tx, ty, rz]`` and ``tz, rx, ry`` get the stiff
        :data:`PLANAR_OUT_OF_PLANE_INFORMATION`, so the optimum and error equal the 2D problem's.
        g2o does not label edges: ``key_to == key_from + 1`` becomes :attr:`EdgeKind.ODOMETRY`, any other edge
        :attr:`EdgeKind.LOOP`. Loops get ``loop_robust`` (default none: a g2o benchmark is a least-squares
        problem, and this reproduces it). No prior is read; the default prior applies.
        """
        path = Path(path)
        is3d = _g2o_is_3d(path)
        graph_in, values_in = _gtsam_call(f"reading {path}", lambda: gtsam.readG2o(str(path), is3d))
        pg = cls()
        keys = sorted(int(k) for k in values_in.keys())
        for key in keys:
            T = values_in.atPose3(key).matrix() if is3d else _lift_pose2(values_in.atPose2(key))
            pg.add_node(key, T)
        between = gtsam.BetweenFactorPose3 if is3d else gtsam.BetweenFactorPose2
        for i in range(graph_in.size()):
            factor = graph_in.at(i)
            if not isinstance(factor, between):
                raise PoseGraphError(f"{path}: factor {i} is a {type(factor).__name__}, expected {between.__name__}")
            key_from, key_to = (int(k) for k in factor.keys())
            info_gtsam = np.asarray(factor.noiseModel().information(), dtype=np.float64)
            if is3d:
                T_from_to = factor.measured().matrix()
                information = information_from_gtsam(info_gtsam)
            else:
                T_from_to = _lift_pose2(factor.measured())
                information = _lift_information_2d(info_gtsam)
            if key_to == key_from + 1:
                pg.add_odometry(key_from, key_to, T_from_to, information)
            else:
                pg.add_loop(key_from, key_to, T_from_to, information, robust=loop_robust,
                            robust_param=None if loop_robust is RobustKernel.NONE else loop_robust_param)
        logger.info("read %s (%s): %d nodes, %d edges (%d loops)", path, "3D" if is3d else "2D lifted to 3D",
                    len(pg._nodes), len(pg._edges), len(pg.loop_edges))
        return pg

    def to_g2o(self, path: str | Path) -> None:
        """Write nodes (initial estimates) and edges as a 3D g2o file that ``gtsam.readG2o`` and g2o read.

        Full double precision (``%.17g``) is written -- ``gtsam.writeG2o`` prints 6 significant digits, which
        moves a node 123.456789 m from the origin by 0.2 mm. The information is written in g2o order,
        which is driftmap order. Priors, edge kinds and robust kernels have no place in the format and are not
        written (:meth:`from_g2o` re-derives the kinds from the keys).
        """
        path = Path(path)
        iu = np.triu_indices(6)
        lines = []
        for key in sorted(self._nodes):
            lines.append(f"VERTEX_SE3:QUAT {key} " + _g2o_pose(self._nodes[key]))
        for edge in self._edges:
            info = " ".join(f"{v:.17g}" for v in edge.information_6x6[iu])
            lines.append(f"EDGE_SE3:QUAT {edge.key_from} {edge.key_to} {_g2o_pose(edge.T_from_to)} {info}")
        try:
            path.write_text("\n".join(lines) + "\n")
        except OSError as exc:
            raise PoseGraphError(f"cannot write {path}: {exc}") from exc


def _g2o_pose(T: NDArray[np.float64]) -> str:
    t = T[:3, 3]
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w as g2o wants
    return " ".join(f"{v:.17g}" for v in (*t, *q))


def _g2o_is_3d(path: Path) -> bool:
    kinds = set()
    try:
        with path.open() as fh:
            for line in fh:
                tag = line.split(maxsplit=1)[0] if line.strip() else ""
                if tag.startswith(("VERTEX_SE3", "EDGE_SE3")):
                    kinds.add("3d")
                elif tag.startswith(("VERTEX_SE2", "EDGE_SE2")):
                    kinds.add("2d")
    except OSError as exc:
        raise PoseGraphError(f"cannot read g2o file {path}: {exc}") from exc
    if not kinds:
        raise PoseGraphError(f"{path}: no VERTEX_SE2/SE3 or EDGE_SE2/SE3 lines, not a g2o pose graph")
    if len(kinds) > 1:
        raise PoseGraphError(f"{path}: mixes 2D (SE2) and 3D (SE3) lines")
    return "3d" in kinds


def _lift_pose2(pose: gtsam.Pose2) -> NDArray[np.float64]:
    return geometry.make_transform(Rotation.from_euler("z", pose.theta()), [pose.x(), pose.y(), 0.0])


def _lift_information_2d(info_xyt: NDArray[np.float64]) -> NDArray[np.float64]:
    """3x3 information in GTSAM ``Pose2`` order ``[x, y, theta]`` -> 6x6 driftmap order, stiff out of plane."""
    info = np.diag([0.0, 0.0, PLANAR_OUT_OF_PLANE_INFORMATION, PLANAR_OUT_OF_PLANE_INFORMATION,
                    PLANAR_OUT_OF_PLANE_INFORMATION, 0.0])
    idx = np.array([0, 1, 5])  # tx, ty, rz
    info[np.ix_(idx, idx)] = info_xyt
    return info


def optimize_g2o(
    path: str | Path,
    method: Optimizer = Optimizer.LM,
    *,
    loop_robust: RobustKernel = RobustKernel.NONE,
    **optimize_kwargs: object,
) -> PoseGraphResult:
    """Read ``path`` with :meth:`PoseGraph.from_g2o` and optimise it (keywords go to :meth:`PoseGraph.optimize`)."""
    graph = PoseGraph.from_g2o(path, loop_robust=loop_robust)
    return graph.optimize(method, **optimize_kwargs)  # type: ignore[arg-type]
