"""The optimisers :meth:`PoseGraph.optimize` dispatches to -- Levenberg-Marquardt, GNC, ISAM2 -- and the
diagnosis of the loop edges at their answer.

Each runner takes the GTSAM graph (effective priors first, then the edges in order, as
:meth:`PoseGraph.to_gtsam` builds it) and the measurements it needs, and returns GTSAM ``Values``; problems
that do not stop it are appended to ``warnings``.
"""

from __future__ import annotations

import functools
import math
import logging
import time
from collections.abc import Mapping, Sequence

import gtsam
import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import PoseGraphError
from driftmap.posegraph.factors import between_factor, gaussian, gtsam_call, pose3, prior_factor
from driftmap.posegraph.measurements import Edge, EdgeKind, Prior
from driftmap.posegraph.result import LoopResidual, OptimizationProgress, Optimizer, ProgressCallback
from driftmap.posegraph.robust import m_estimator

logger = logging.getLogger(__name__)

__all__ = ["diagnose_loops", "lm_params", "run_gnc", "run_isam2", "run_lm"]


def lm_params(max_iterations: int, relative_error_tol: float, absolute_error_tol: float) -> gtsam.LevenbergMarquardtParams:
    """GTSAM's LM parameters (also GNC's inner LM and ISAM2's convergence test)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(float(relative_error_tol))
    params.setAbsoluteErrorTol(float(absolute_error_tol))
    return params


def _noise_level(graph: gtsam.NonlinearFactorGraph) -> float:
    """Half the graph's residual dimensions: the error (0.5 * the sum of whitened squared residuals) a consistent
    graph has at its optimum, on average."""
    return 0.5 * float(sum(graph.at(i).dim() for i in range(graph.size()) if graph.at(i) is not None))


def run_lm(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    params: gtsam.LevenbergMarquardtParams,
    initial_error: float,
    started: float,
    callback: ProgressCallback | None,
    warnings: list[str],
) -> tuple[gtsam.Values, int, bool]:
    """Levenberg-Marquardt: ``(values, iterations, converged)``."""
    # The loop of GTSAM's NonlinearOptimizer::defaultOptimize, unrolled so a callback can watch and stop it.
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    error = initial_error
    converged = error <= params.getErrorTol()
    while not converged and optimizer.iterations() < params.getMaxIterations():
        before_iterations = optimizer.iterations()
        previous = error
        gtsam_call("Levenberg-Marquardt", optimizer.iterate)
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
            noise = _noise_level(graph)
            if error <= noise:
                # a stationary point whose residuals lie within their noise models (hostile trial 17 W10: merging
                # exact ground-truth sessions printed this as non-convergence); not so the INTEL data set's 3.35e6
                logger.debug("Levenberg-Marquardt stopped at maximum lambda with the error %.6g within the noise "
                             "(%.6g): converged", error, noise)
                converged = True
            else:
                warnings.append(f"Levenberg-Marquardt could not decrease the error {error:.6g} (gave up at maximum lambda)")
            break
        converged = gtsam.checkConvergence(params, previous, error)
    if not converged and not warnings:
        warnings.append(f"reached max_iterations={params.getMaxIterations()}")
    return optimizer.values(), int(optimizer.iterations()), bool(converged)


def run_gnc(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    lm_params: gtsam.LevenbergMarquardtParams,
    initial_error: float,
    started: float,
    callback: ProgressCallback | None,
    *,
    n_priors: int,
    edges: Sequence[Edge],
) -> tuple[gtsam.Values, bool, tuple[float, ...]]:
    """Graduated non-convexity with the priors and odometry edges as known inliers:
    ``(values, converged, weights of the edges)``."""
    known_inliers = list(range(n_priors)) + [
        n_priors + i for i, e in enumerate(edges) if e.kind is EdgeKind.ODOMETRY
    ]
    params = gtsam.GncLMParams(lm_params)
    params.setKnownInliers(known_inliers)
    optimizer = gtsam.GncLMOptimizer(graph, initial, params)
    values = gtsam_call("GNC", optimizer.optimize)
    weights = np.asarray(optimizer.getWeights(), dtype=np.float64)
    edge_weights = tuple(float(w) for w in weights[n_priors:])
    loop_weights = [w for w, e in zip(edge_weights, edges) if e.kind is EdgeKind.LOOP]
    converged = all(min(w, 1.0 - w) <= params.weightsTol for w in loop_weights)
    if callback is not None:
        callback(OptimizationProgress(Optimizer.GNC, 1, float(graph.error(values)), initial_error,
                                      time.perf_counter() - started))
    return values, converged, edge_weights


def run_isam2(
    graph: gtsam.NonlinearFactorGraph,
    lm_params: gtsam.LevenbergMarquardtParams,
    relinearize_threshold: float,
    started: float,
    callback: ProgressCallback | None,
    warnings: list[str],
    *,
    nodes: Mapping[int, NDArray[np.float64]],
    priors: Sequence[Prior],
    edges: Sequence[Edge],
) -> tuple[gtsam.Values, int, bool]:
    """ISAM2: nodes inserted in key order, then relinearised until the error settles:
    ``(values, updates, converged)``."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(float(relinearize_threshold))
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    updates, stopped = _isam2_insert_nodes(isam, nodes, priors, edges, started, callback, warnings)
    if stopped:
        return isam.calculateEstimate(), updates, False
    updates, converged = _isam2_relinearise(isam, graph, lm_params, updates, started, callback, warnings)
    return isam.calculateEstimate(), updates, converged


def _isam2_insert_nodes(
    isam: gtsam.ISAM2,
    nodes: Mapping[int, NDArray[np.float64]],
    priors: Sequence[Prior],
    edges: Sequence[Edge],
    started: float,
    callback: ProgressCallback | None,
    warnings: list[str],
) -> tuple[int, bool]:
    """One ISAM2 update per node, in key order, with its priors and the edges that join it to earlier nodes:
    ``(updates, stopped by the callback)``."""
    priors_by_key: dict[int, list[Prior]] = {}
    for prior in priors:
        priors_by_key.setdefault(prior.key, []).append(prior)
    edges_by_key: dict[int, list[Edge]] = {}
    for edge in edges:  # an edge enters with the later of its two nodes
        edges_by_key.setdefault(max(edge.key_from, edge.key_to), []).append(edge)
    inserted: set[int] = set()
    added = gtsam.NonlinearFactorGraph()
    error = previous = math.nan
    updates = 0
    for key in sorted(nodes):
        factors = gtsam.NonlinearFactorGraph()
        for prior in priors_by_key.get(key, ()):
            factors.add(prior_factor(prior))
        key_edges = edges_by_key.get(key, [])
        for edge in key_edges:
            factors.add(between_factor(edge))
        values = gtsam.Values()
        values.insert(key, pose3(_incremental_initial(key, nodes, key_edges, inserted, isam)))
        if factors.size() == 0:
            raise PoseGraphError(
                f"ISAM2: node {key} has no prior and no edge to a node with a lower key; "
                "insert nodes so that each one is connected to earlier ones"
            )
        gtsam_call(f"ISAM2 update at node {key}", functools.partial(isam.update, factors, values))
        inserted.add(key)
        updates += 1
        if callback is not None:
            for i in range(factors.size()):
                added.add(factors.at(i))
            previous, error = error, float(added.error(isam.calculateEstimate()))
            if callback(OptimizationProgress(Optimizer.ISAM2, updates, error, previous, time.perf_counter() - started)):
                warnings.append(f"stopped by the callback at node {key}")
                return updates, True
    return updates, False


def _isam2_relinearise(
    isam: gtsam.ISAM2,
    graph: gtsam.NonlinearFactorGraph,
    lm_params: gtsam.LevenbergMarquardtParams,
    updates: int,
    started: float,
    callback: ProgressCallback | None,
    warnings: list[str],
) -> tuple[int, bool]:
    """Relinearise the whole graph until the error stops changing (GTSAM's batch convergence test):
    ``(updates, converged)``."""
    error = float(graph.error(isam.calculateEstimate()))
    for _ in range(int(lm_params.getMaxIterations())):
        gtsam_call("ISAM2 relinearisation", isam.update)
        updates += 1
        previous, error = error, float(graph.error(isam.calculateEstimate()))
        if callback is not None and callback(
            OptimizationProgress(Optimizer.ISAM2, updates, error, previous, time.perf_counter() - started)
        ):
            warnings.append("stopped by the callback while relinearising")
            return updates, False
        if gtsam.checkConvergence(lm_params, previous, error):
            return updates, True
    warnings.append(f"ISAM2 still changing after {lm_params.getMaxIterations()} relinearisation passes")
    return updates, False


def _incremental_initial(
    key: int, nodes: Mapping[int, NDArray[np.float64]], edges: Sequence[Edge], inserted: set[int], isam: gtsam.ISAM2
) -> NDArray[np.float64]:
    """Initial value of a node entering ISAM2: chained from the current estimate of an earlier node
    through an odometry edge (what an online system does), else its stored initial estimate."""
    for edge in edges:
        if edge.kind is not EdgeKind.ODOMETRY:
            continue
        if edge.key_to == key and edge.key_from in inserted:
            return isam.calculateEstimatePose3(edge.key_from).matrix() @ edge.T_from_to
        if edge.key_from == key and edge.key_to in inserted:
            return isam.calculateEstimatePose3(edge.key_to).matrix() @ geometry.invert(edge.T_from_to)
    return nodes[key]


def diagnose_loops(
    edges: Sequence[Edge], values: gtsam.Values, chi2_threshold: float, gnc_edge_weights: tuple[float, ...] | None
) -> tuple[LoopResidual, ...]:
    """One :class:`LoopResidual` per loop edge at ``values``: chi2 under the edge's Gaussian information, the
    weight the optimiser gave it (GNC weight, else the kernel's IRLS weight) and the chi2 gate."""
    out = []
    for index, edge in enumerate(edges):
        if edge.kind is not EdgeKind.LOOP:
            continue
        factor = gtsam.BetweenFactorPose3(edge.key_from, edge.key_to, pose3(edge.T_from_to), gaussian(edge.information_6x6))
        chi2 = 2.0 * float(factor.error(values))
        whitened = math.sqrt(max(chi2, 0.0))
        if gnc_edge_weights is not None:
            weight = gnc_edge_weights[index]
        else:
            estimator = m_estimator(edge.robust, edge.robust_param)
            weight = 1.0 if estimator is None else float(estimator.weight(whitened))
        out.append(LoopResidual(index, edge.key_from, edge.key_to, chi2, whitened, weight, chi2 <= chi2_threshold))
    return tuple(out)
