"""The :class:`PoseGraph`: nodes, priors and edges, their GTSAM factor graph, and :meth:`PoseGraph.optimize`,
which runs one of the optimisers of :mod:`driftmap.posegraph.solvers` and reports a :class:`PoseGraphResult`."""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from driftmap.errors import PoseGraphError
from driftmap.posegraph.factors import between_factor, gtsam_call, poses_from_values, prior_factor, values_from_poses
from driftmap.posegraph.g2o import read_g2o_into, write_g2o
from driftmap.posegraph.measurements import (
    Edge,
    EdgeKind,
    Prior,
    check_key,
    checked_pose,
    default_prior_information,
)
from driftmap.posegraph.result import Initialization, Optimizer, PoseGraphResult, ProgressCallback
from driftmap.posegraph.robust import CHI2_6DOF_99, RobustKernel
from driftmap.posegraph.solvers import diagnose_loops, lm_params, run_gnc, run_isam2, run_lm
from driftmap.posegraph.tangent import TangentOrder, reorder_6x6

__all__ = ["PoseGraph", "optimize_g2o"]

# The package's name, not this module's: log records keep the name "driftmap.posegraph" they had when the
# package was one module (the CLI prints it), and driftmap.posegraph.logger is this same logger.
logger = logging.getLogger(__package__)


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
        key = check_key(key, "add_node")
        if key in self._nodes:
            raise PoseGraphError(f"node {key} already exists")
        self._nodes[key] = checked_pose(T_world_x, f"node {key}: T_world_x")

    def add_prior(self, key: int, T_world_x: ArrayLike | None = None, information_6x6: ArrayLike | None = None) -> Prior:
        """Anchor node ``key`` at ``T_world_x`` (default: its initial estimate) with ``information_6x6``
        (``[translation, rotation]`` order; default: the tight prior of :data:`DEFAULT_PRIOR_SIGMA_M` /
        :data:`DEFAULT_PRIOR_SIGMA_RAD`). A graph without any prior gets that default prior on its lowest key."""
        key = self._require_node(key, "add_prior")
        prior = Prior(
            key,
            self._nodes[key] if T_world_x is None else T_world_x,
            default_prior_information() if information_6x6 is None else information_6x6,
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
        key = check_key(key, what)
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
        return (Prior(key, self._nodes[key], default_prior_information()),)

    # -- GTSAM ---------------------------------------------------------------------------------------------

    def to_gtsam(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The factor graph (effective priors first, then the edges in order) and the initial values."""
        graph = gtsam.NonlinearFactorGraph()
        for prior in self.effective_priors():
            graph.add(prior_factor(prior))
        for edge in self._edges:
            graph.add(between_factor(edge))
        return graph, values_from_poses(self._nodes)

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
        return values_from_poses({k: np.asarray(poses[k], dtype=np.float64) for k in self._nodes})

    def marginal_covariances(self, poses: Mapping[int, ArrayLike], *, dense: bool | None = None
                             ) -> dict[int, NDArray[np.float64]]:
        """Each node's marginal covariance at ``poses`` (an optimum), of the graph linearised there: 6x6 in
        driftmap order ``[translation, rotation]`` (m^2, rad^2), in the node's own frame (GTSAM's right perturbation
        ``T Exp(xi)``), relative to the priors (the gauge). Raises :class:`PoseGraphError` when the system cannot be
        factored (an under-constrained graph).

        ``dense`` (default: when the system has at most :data:`DENSE_MARGINALS_MAX_DIM` unknowns): the diagonal
        blocks of the inverse of GTSAM's Hessian at ``poses`` (its Cholesky factor inverted once), instead of
        ``gtsam.Marginals.marginalCovariance`` per node. Equal to it to 1e-9 relative (tested; ~1e-15 seen); on a
        graph whose loops tie many visits of one place together GTSAM's per-node marginals grew 40 s -> 272 s from
        167 to 334 nodes, most of a long log's build (docs/scaling.md)."""
        graph, _ = self.to_gtsam()
        values = self._values_for(poses)
        keys = list(self._nodes)
        held = {p.key for p in self.effective_priors()} | {k for e in self._edges for k in (e.key_from, e.key_to)}
        free = [k for k in keys if k not in held]
        if free:
            raise PoseGraphError(f"marginal covariances: node(s) {free[:5]} have no edge and no prior: their poses "
                                 f"are not constrained (an under-constrained graph)")
        use_dense = 6 * len(keys) <= DENSE_MARGINALS_MAX_DIM if dense is None else dense
        if use_dense:
            return _dense_marginals(graph, values, keys)
        marginals = gtsam_call("marginal covariances", lambda: gtsam.Marginals(graph, values))
        return {k: reorder_6x6(gtsam_call("marginal covariance", lambda k=k: marginals.marginalCovariance(k)),
                               TangentOrder.ROTATION_TRANSLATION, TangentOrder.TRANSLATION_ROTATION)
                for k in self._nodes}

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
        self._check_optimize_args(method, max_iterations, initialization)
        started = time.perf_counter()
        graph, initial = self.to_gtsam()
        if initialization is Initialization.CHORDAL:
            initial = gtsam_call("chordal initialisation", lambda: gtsam.InitializePose3.initialize(graph))
        initial_error = float(graph.error(initial))
        logger.info(
            "pose graph: %d nodes, %d edges (%d loops), %s from %s, initial error %.6g",
            len(self._nodes), len(self._edges), len(self.loop_edges), method.name, initialization.name, initial_error,
        )
        params = lm_params(max_iterations, relative_error_tol, absolute_error_tol)
        warnings: list[str] = []
        values, iterations, converged, gnc_edge_weights = self._solve(
            method, graph, initial, params, initial_error, isam2_relinearize_threshold, started, callback, warnings
        )
        result = PoseGraphResult(
            poses=MappingProxyType(poses_from_values(values, self._nodes)),
            initial_error=initial_error,
            final_error=float(graph.error(values)),
            iterations=iterations,
            converged=converged,
            method=method,
            initialization=initialization,
            loop_residuals=diagnose_loops(self._edges, values, chi2_threshold, gnc_edge_weights),
            chi2_threshold=float(chi2_threshold),
            elapsed_s=time.perf_counter() - started,
            n_nodes=len(self._nodes),
            n_edges=len(self._edges),
            gnc_edge_weights=gnc_edge_weights,
            warnings=tuple(warnings),
        )
        _log_result(result, warn)
        return result

    def _check_optimize_args(self, method: Optimizer, max_iterations: int, initialization: Initialization) -> None:
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

    def _solve(
        self,
        method: Optimizer,
        graph: gtsam.NonlinearFactorGraph,
        initial: gtsam.Values,
        params: gtsam.LevenbergMarquardtParams,
        initial_error: float,
        isam2_relinearize_threshold: float,
        started: float,
        callback: ProgressCallback | None,
        warnings: list[str],
    ) -> tuple[gtsam.Values, int | None, bool, tuple[float, ...] | None]:
        """Run ``method``: ``(values, iterations, converged, GNC edge weights)``."""
        if method is Optimizer.LM:
            values, iterations, converged = run_lm(graph, initial, params, initial_error, started, callback, warnings)
            return values, iterations, converged, None
        if method is Optimizer.GNC:
            values, converged, gnc_edge_weights = run_gnc(
                graph, initial, params, initial_error, started, callback,
                n_priors=len(self.effective_priors()), edges=self._edges,
            )
            if not converged:
                warnings.append("GNC left some loop weights between 0 and 1")
            return values, None, converged, gnc_edge_weights
        values, iterations, converged = run_isam2(
            graph, params, isam2_relinearize_threshold, started, callback, warnings,
            nodes=self._nodes, priors=self.effective_priors(), edges=self._edges,
        )
        return values, iterations, converged, None

    # -- g2o -----------------------------------------------------------------------------------------------

    @classmethod
    def from_g2o(
        cls,
        path: str | Path,
        *,
        loop_robust: RobustKernel = RobustKernel.NONE,
        loop_robust_param: float | None = None,
        non_pd_information: str = "refuse",
    ) -> PoseGraph:
        """Read a g2o file with ``gtsam.readG2o``.

        3D files (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``) are read as they are. 2D files (``VERTEX_SE2`` /
        ``EDGE_SE2``) are lifted into SE(3) in the z = 0 plane: ``(x, y, theta)`` becomes a rotation about z,
        the 3x3 information ``[x, y, theta]`` lands on ``[tx, ty, rz]`` and ``tz, rx, ry`` get the stiff
        :data:`PLANAR_OUT_OF_PLANE_INFORMATION`, so the optimum and error equal the 2D problem's.
        g2o does not label edges: ``key_to == key_from + 1`` becomes :attr:`EdgeKind.ODOMETRY`, any other edge
        :attr:`EdgeKind.LOOP`. Loops get ``loop_robust`` (default none: a g2o benchmark is a least-squares
        problem, and this reproduces it). ``FIX`` lines become priors on their nodes (else the default prior).

        Every line is checked before GTSAM reads the file (:func:`~driftmap.posegraph.g2o.check_g2o_lines`): a
        malformed line, a negative or huge id, NaN / inf, a non-unit quaternion, an edge to a missing vertex and an
        information matrix that is not positive definite are :class:`~driftmap.errors.PoseGraphError` naming
        ``path:line``. ``non_pd_information="gtsam"`` reads such matrices as ``gtsam.readG2o`` does instead (another
        matrix, with a warning; the shared ``cubicle.g2o`` needs it).
        """
        path = Path(path)
        pg = cls()
        is3d = read_g2o_into(pg, path, loop_robust=loop_robust, loop_robust_param=loop_robust_param,
                             non_pd_information=non_pd_information)
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
        write_g2o(Path(path), self._nodes, self._edges)


DENSE_MARGINALS_MAX_DIM = 8000
"""Up to this many unknowns (6 per node: ~1333 nodes, 512 MB a dense matrix) the marginal covariances come from one
dense inversion (:meth:`PoseGraph.marginal_covariances`); beyond, from GTSAM per node."""


def _dense_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keys: list[int]
                     ) -> dict[int, NDArray[np.float64]]:
    """The diagonal 6x6 blocks of ``H^-1`` (``H``: the Hessian of ``graph`` linearised at ``values``, in ``keys``
    order), reordered to driftmap order: ``H = L L^T``, ``H^-1 = L^-T L^-1``, block ``i`` = ``(L^-1)[:, i]^T
    (L^-1)[:, i]`` over the rows from ``i`` down (``L^-1`` is lower triangular)."""
    import scipy.linalg

    ordering = gtsam.Ordering()
    for k in keys:
        ordering.push_back(k)
    H = gtsam_call("marginal covariances", lambda: graph.linearize(values).hessian(ordering)[0])
    if H.shape != (6 * len(keys), 6 * len(keys)):
        raise PoseGraphError(f"marginal covariances: the linearised system has {H.shape[0]} unknowns, not 6 per node "
                             f"({6 * len(keys)})")
    try:  # overwriting H where LAPACK can (a C-ordered H may still be copied once)
        L = scipy.linalg.cholesky(H, lower=True, overwrite_a=True, check_finite=False)
    except np.linalg.LinAlgError:
        raise PoseGraphError("marginal covariances: the linearised system is not positive definite (an "
                             "under-constrained graph)") from None
    L_inv, info = scipy.linalg.lapack.dtrtri(L, lower=1, overwrite_c=1)
    if info != 0:
        raise PoseGraphError(f"marginal covariances: the Cholesky factor is singular (LAPACK dtrtri info {info})")
    out = {}
    for i, k in enumerate(keys):
        col = L_inv[6 * i:, 6 * i:6 * i + 6]
        out[k] = reorder_6x6(col.T @ col, TangentOrder.ROTATION_TRANSLATION, TangentOrder.TRANSLATION_ROTATION)
    return out


def _log_result(result: PoseGraphResult, warn: bool) -> None:
    """The summary at INFO; rejected loops and a failure to converge at WARNING (INFO with ``warn=False``)."""
    rejected = result.rejected_loops
    logger.info(
        "pose graph %s: error %.6g -> %.6g, %s iterations, converged=%s, %d/%d loops rejected, %.3f s",
        result.method.name, result.initial_error, result.final_error, result.iterations, result.converged,
        len(rejected), len(result.loop_residuals), result.elapsed_s,
    )
    report = logger.warning if warn else logger.info
    if rejected:
        report(
            "%d of %d loop edges fail the chi2 gate %.4g after optimisation, e.g. %s",
            len(rejected), len(result.loop_residuals), result.chi2_threshold,
            ", ".join(f"{r.key_from}->{r.key_to} (chi2 {r.chi2:.3g}, weight {r.weight:.3g})" for r in rejected[:5]),
        )
    if not result.converged:
        report("pose graph %s did not converge (%s)", result.method.name, "; ".join(result.warnings) or "see result")


def optimize_g2o(
    path: str | Path,
    method: Optimizer = Optimizer.LM,
    *,
    loop_robust: RobustKernel = RobustKernel.NONE,
    non_pd_information: str = "refuse",
    **optimize_kwargs: object,
) -> PoseGraphResult:
    """Read ``path`` with :meth:`PoseGraph.from_g2o` and optimise it (keywords go to :meth:`PoseGraph.optimize`)."""
    graph = PoseGraph.from_g2o(path, loop_robust=loop_robust, non_pd_information=non_pd_information)
    return graph.optimize(method, **optimize_kwargs)  # type: ignore[arg-type]

