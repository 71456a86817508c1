"""The loop-closure stage of ``build``: keyframes of the stored trajectory, candidate loops verified by
registration, a GTSAM pose graph with calibrated information, and the correction stored as a new revision."""

from __future__ import annotations

import dataclasses
import enum
import logging
import time
from types import MappingProxyType

import numpy as np

from driftmap import geometry
from driftmap.errors import ConfigError, PoseGraphError
from driftmap.frame import Frame, PoseSource, SensorKind
from driftmap.map.view import MapView
from driftmap.pipeline.build_config import BuildConfig, BuildResult, ProgressCallback
from driftmap.pipeline.resume import recorded_odometry
from driftmap.posegraph import PoseGraph, PoseGraphResult, RobustKernel
from driftmap.preprocess.scene import sample_positions
from driftmap.registration.loops import (
    CandidateKind,
    Keyframe,
    LoopCandidate,
    LoopClosureConfig,
    find_loops,
    gap_threshold,
    loop_gap,
    make_keyframe,
    select_keyframes,
)
from driftmap.registration.odometry import OdometryConfig, OdometryMethod
from driftmap.registration.pairwise import register_prepared, relative_pose
from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)


def used_odometry(store: FrameStore, result: BuildResult) -> OdometryConfig:
    """The odometry settings the store's frames were registered with (this run's, or the earlier build's), else the
    defaults for its scene: loop closure scales its LiDAR lengths with the odometry voxel."""
    if result.odometry_config is not None:
        return OdometryConfig.model_validate(result.odometry_config)
    recorded = recorded_odometry(store) if len(store) else None
    if recorded is not None:
        return recorded
    if len(store) == 0:
        return OdometryConfig()
    return OdometryConfig.for_frames([store.frame(int(store.frame_ids[k])) for k in sample_positions(len(store))],
                                     log=False)


def fallback_information(T_a_b: np.ndarray, config: BuildConfig) -> np.ndarray:
    """Odometry-edge information when registration could not provide one: sigma grows with the motion."""
    motion = float(np.linalg.norm(T_a_b[:3, 3]))
    sigma_t = config.fallback_sigma_translation * motion + 0.01
    sigma_r = np.radians(config.fallback_sigma_rotation_deg)
    return np.diag([1 / sigma_t**2] * 3 + [1 / sigma_r**2] * 3)


class EdgeGroup(enum.Enum):
    ODOMETRY = "odometry"
    FALLBACK = "fallback"
    LOOP = "loop"


def edge_residual_chi2(T_from_to: np.ndarray, information: np.ndarray, T_world_from: np.ndarray, T_world_to: np.ndarray) -> float:
    """Mahalanobis residual of a between-edge (driftmap [t, r] order, the same as GTSAM's after reordering)."""
    e = geometry.se3_log(geometry.invert(T_from_to) @ geometry.invert(T_world_from) @ T_world_to)
    return float(e @ information @ e)


def odometry_edges_from_trajectory(config: BuildConfig, store: FrameStore, own_odometry: bool) -> bool:
    """Whether odometry edges take the revision-0 relative pose or the keyframe registration.

    ``auto``: the relative pose when the frames were tracked against a map of *every* frame so far
    (``gicp_map`` without a horizon): such an odometry re-registers a revisited place to its first pass by
    itself, and its relative poses are more accurate than a keyframe-to-keyframe registration. Otherwise
    (KISS-ICP, a windowed ``gicp_map``, given poses) the keyframe registration: a local-map odometry's
    relative poses carry the drift the loops must take out, and as trajectory edges they could not be
    calibrated (they start at zero residual), so their raw GICP information would hold the drift in place
    (measured in docs/build.md)."""
    if config.odometry_edges == "trajectory":
        return True
    if config.odometry_edges == "registration" or not own_odometry or len(store) == 0:
        return False
    cfg = config.odometry or OdometryConfig.for_sensor(store.frame(int(store.frame_ids[0])).sensor_kind)
    return cfg.method is OdometryMethod.GICP_MAP and cfg.gicp_map_horizon_frames is None


def check_place_descriptor(lc: LoopClosureConfig, frame: Frame) -> None:
    """A Scan Context needs a z-up LiDAR frame: refuse it for a depth camera's frames."""
    if lc.place_descriptor == "scan_context" and frame.sensor_kind is not SensorKind.LIDAR:
        raise ConfigError(f"loop_closure.place_descriptor = 'scan_context' needs LiDAR scans (a z-up sensor frame); "
                          f"frame {frame.frame_id} is from {frame.sensor_name!r}, a {frame.sensor_kind.value}: use 'shape'")


Edge = tuple[EdgeGroup, int, int, np.ndarray, np.ndarray]
"""(group, key_from, key_to, T_from_to, information): the graph is rebuilt from these for the information calibration"""


def close_loops(store: FrameStore, config: BuildConfig, result: BuildResult, tick: ProgressCallback,
                stages: dict[str, float], inject_wrong_loop: tuple[int, int, np.ndarray] | None, *, own_odometry: bool) -> None:
    """The loop-closure stage: keyframes of revision 0, verified loop candidates, odometry edges between keyframes, a
    pose graph with calibrated information and, when a loop was accepted, the optimised poses stored as a new
    revision and applied to the map. Numbers go into ``result`` and ``stages`` (seconds per step)."""
    t0 = time.perf_counter()
    odometry_cfg = config.odometry or used_odometry(store, result)
    lc = loop_config_for(store, config, odometry_cfg)
    result.loop_closure_config = lc.model_dump(mode="json")
    key_rows = select_keyframes(store.poses(0), lc)
    result.n_keyframes = len(key_rows)
    if inject_wrong_loop is None and _too_short_for_loops(store, lc, key_rows):
        return
    max_range_m = lc.max_range_m
    if max_range_m is None and own_odometry:  # the range the odometry trusted; given poses: every point
        max_range_m = odometry_cfg.max_range_m
    keyframes = keyframe_clouds(store, lc, key_rows, max_range_m, tick)
    result.n_keyframes = len(keyframes)
    stages["keyframes"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    candidates, edges = verified_loops(store, keyframes, lc, inject_wrong_loop, tick)
    stages["loop candidates"] = time.perf_counter() - t1
    result.loops_tried = len(candidates)
    result.loops_accepted = len(edges)
    result.loops = [{"a": c.a, "b": c.b, "kind": c.kind.value, "accepted": c.accepted, "reason": c.reason,
                     "fitness": None if c.result is None else c.result.fitness,
                     "rmse_m": None if c.result is None else c.result.rmse_m} for c in candidates]
    if not edges:
        logger.info("no loop closure accepted; the odometry stays revision 0")
        return
    t_edges = time.perf_counter()
    from_trajectory = odometry_edges_from_trajectory(config, store, own_odometry)
    edges += odometry_edges(keyframes, lc, config, from_trajectory, tick)
    result.odometry_edges = sum(group is not EdgeGroup.LOOP for group, *_ in edges)
    stages["odometry edges"] = time.perf_counter() - t_edges
    t2 = time.perf_counter()
    opt = optimize_calibrated(keyframes, edges, config, result, calibrate_odometry=not from_trajectory)
    stages["pose graph"] = time.perf_counter() - t2
    result.graph_error_before, result.graph_error_after = opt.initial_error, opt.final_error
    _record_graph_verdicts(result, opt)
    if opt.loop_residuals and result.loops_rejected_by_graph >= len(opt.loop_residuals):
        # nothing closed: a revision would only carry the keyframe edges' re-registration, labelled a loop closure
        logger.warning("loop closure: the pose graph rejected all %d verified loops; no loop closure revision, the "
                       "odometry stays revision 0", len(opt.loop_residuals))
        return
    t3 = time.perf_counter()
    _store_correction(store, result, opt)
    stages["correction"] = time.perf_counter() - t3


def loop_config_for(store: FrameStore, config: BuildConfig, odometry_cfg: OdometryConfig) -> LoopClosureConfig:
    """``config.loop_closure`` over the defaults of the store's sensor: LiDAR lengths scaled with the odometry voxel
    and keyframe clouds of 0.3 s (:meth:`LoopClosureConfig.for_lidar`); ``build.num_threads`` over its threads."""
    lc = config.loop_closure
    first = store.frame(int(store.frame_ids[0])) if len(store) else None
    if first is not None and first.sensor_kind is SensorKind.LIDAR:
        odometry_voxel_m = odometry_cfg.voxel_size_m if odometry_cfg.method is OdometryMethod.KISS else odometry_cfg.gicp_map_voxel_m
        stamps = store.ledger.stamps_ns
        period_s = float(np.median(np.diff(stamps))) * 1e-9 if len(stamps) > 1 else None
        lc = lc.over(LoopClosureConfig.for_lidar(odometry_voxel_m, period_s))
    elif first is not None:
        check_place_descriptor(lc, first)
    if config.num_threads is not None:
        lc = lc.model_copy(update={"num_threads": config.num_threads})
    return lc


def _too_short_for_loops(store: FrameStore, lc: LoopClosureConfig, key_rows: list[int]) -> bool:
    """The keyframes span less than the loop gap (no candidate can be that far apart): warn and say so."""
    ids = [int(i) for i in store.frame_ids]
    stamps_ns = store.ledger.stamps_ns
    span_s = 1e-9 * float(stamps_ns[key_rows[-1]] - stamps_ns[key_rows[0]])
    if loop_gap(lc)[0] == "frames":  # in the source's frame numbers
        span, what = ids[key_rows[-1]] - ids[key_rows[0]], f"loop_closure.min_gap_frames = {lc.min_gap_frames} source frames"
    else:
        span, what = span_s, f"loop_closure.min_gap_s = {lc.min_gap_s:g} s"
    if len(key_rows) >= 2 and span >= gap_threshold(lc):
        return False
    logger.warning("loop closure skipped: the %d keyframes (of %d stored frames, source frames %d..%d) span "
                   "source frames %d..%d (%.2f s), less than %s (loop candidates are at least that far apart); "
                   "store a longer stretch of the source, or lower it", len(key_rows), len(ids), ids[0], ids[-1],
                   ids[key_rows[0]], ids[key_rows[-1]], span_s, what)
    return True


def keyframe_clouds(store: FrameStore, lc: LoopClosureConfig, key_rows: list[int], max_range_m: float | None,
                    tick: ProgressCallback) -> list[Keyframe]:
    """A :class:`Keyframe` per row of ``key_rows``: its cloud holds the frames within ``submap_radius_frames``,
    placed by revision 0, points within ``max_range_m`` of their sensor (None: every point). Frames are read once."""
    ids = [int(i) for i in store.frame_ids]
    poses, stamps_ns = store.poses(0), store.ledger.stamps_ns
    cache: dict[int, np.ndarray] = {}

    def points(row: int) -> np.ndarray:
        if row not in cache:
            pts = store.frame(ids[row]).points_sensor
            if max_range_m is not None:
                pts = pts[np.einsum("ij,ij->i", pts, pts) <= max_range_m**2]
            cache[row] = pts
        return cache[row]

    keyframes: list[Keyframe] = []
    for n, row in enumerate(key_rows):
        rows = range(max(0, row - lc.submap_radius_frames), min(len(ids), row + lc.submap_radius_frames + 1))
        inv = geometry.invert(poses[row])
        cloud = np.concatenate([geometry.transform_points(inv @ poses[r], points(r)) for r in rows])
        keyframes.append(make_keyframe(ids[row], row, poses[row], cloud, lc, stamp_ns=int(stamps_ns[row])))
        for r in [r for r in cache if r < row - lc.submap_radius_frames]:
            del cache[r]
        tick("keyframes", n + 1, len(key_rows))
    return keyframes


def verified_loops(store: FrameStore, keyframes: list[Keyframe], lc: LoopClosureConfig,
                   inject_wrong_loop: tuple[int, int, np.ndarray] | None,
                   tick: ProgressCallback) -> tuple[list[LoopCandidate], list[Edge]]:
    """Every loop candidate tried (verified by :func:`find_loops`, never across flagged odometry) and the graph edges
    of the accepted ones; ``inject_wrong_loop=(frame_a, frame_b, T_a_b)`` adds a deliberately wrong one (tests)."""
    candidates: list[LoopCandidate] = find_loops(keyframes, lc, progress=lambda d, t: tick("loop candidates", d, t),
                                                 flagged=flagged_rows(store))
    injected_info = None
    if inject_wrong_loop is not None:
        fa, fb, T_wrong = inject_wrong_loop
        by_id = {k.frame_id: k for k in keyframes}
        if fa not in by_id or fb not in by_id:
            raise ConfigError(f"injected loop {fa}<->{fb}: both frames must be keyframes ({[k.frame_id for k in keyframes][:10]}...)")
        accepted_info = [c.result.information_6x6 for c in candidates if c.accepted and c.result is not None]
        injected_info = accepted_info[0] if accepted_info else np.diag([1e4] * 3 + [1e4] * 3)
        candidates.append(LoopCandidate(fa, fb, CandidateKind.INJECTED, True, "deliberately wrong (injected)", None, T_wrong))
    edges: list[Edge] = [(EdgeGroup.LOOP, c.a, c.b, c.T_a_b, c.result.information_6x6 if c.result is not None else injected_info)
                         for c in candidates if c.accepted]
    return candidates, edges


def odometry_edges(keyframes: list[Keyframe], lc: LoopClosureConfig, config: BuildConfig, from_trajectory: bool,
                   tick: ProgressCallback) -> list[Edge]:
    """Edges between keyframes up to ``odometry_edge_window`` apart: the registration of their clouds where it fits
    and agrees with the odometry (its information; the odometry's relative pose when ``from_trajectory``), else,
    between neighbours, the odometry with :func:`fallback_information`."""
    v = lc.registration_voxel_m
    pairs = [(i, i + d) for i in range(len(keyframes)) for d in range(1, config.odometry_edge_window + 1) if i + d < len(keyframes)]
    edges: list[Edge] = []
    for n, (i, j) in enumerate(pairs):
        a, b = keyframes[i], keyframes[j]
        odom = relative_pose(a.T_world_sensor, b.T_world_sensor)
        reg = register_prepared(a.cloud, b.cloud, odom, voxel_size_m=v, max_correspondence_m=2.5 * v)
        good = reg.converged and reg.fitness >= lc.min_fitness and \
            geometry.translation_distance_m(odom, reg.T_target_source) <= config.odometry_edge_max_disagreement_m
        if good:
            edges.append((EdgeGroup.ODOMETRY, a.frame_id, b.frame_id, odom if from_trajectory else reg.T_target_source,
                          reg.information_6x6))
        elif j == i + 1:
            logger.info("odometry edge %d->%d: registration not usable (%s); odometry with fallback information",
                        a.frame_id, b.frame_id, reg.describe())
            edges.append((EdgeGroup.FALLBACK, a.frame_id, b.frame_id, odom, fallback_information(odom, config)))
        tick("odometry edges", n + 1, len(pairs))
    return edges


def _record_graph_verdicts(result: BuildResult, opt: PoseGraphResult) -> None:
    """The graph's chi2 and weight of each accepted loop into ``result.loops``; count (and log) the loops it rejected."""
    accepted: dict[tuple[int, int], dict] = {}  # the first accepted entry per (a, b): one pass, not one per residual
    for x in result.loops:
        if x["accepted"]:
            accepted.setdefault((x["a"], x["b"]), x)
    for res in opt.loop_residuals:
        entry = accepted.get((res.key_from, res.key_to))
        if entry is not None:
            entry.update(graph_chi2=res.chi2, graph_weight=res.weight, kept_by_graph=res.accepted)
        if not res.accepted:
            result.loops_rejected_by_graph += 1
            logger.info("loop %d<->%d rejected by the pose graph (chi2 %.1f, weight %.3f)", res.key_from, res.key_to,
                        res.chi2, res.weight if res.weight is not None else float("nan"))
    if result.loops_rejected_by_graph:
        logger.warning("%d of %d loops rejected by the pose graph (chi2 > %.1f)", result.loops_rejected_by_graph,
                       len(opt.loop_residuals), opt.chi2_threshold)


def _loops_note(result: BuildResult, opt: PoseGraphResult) -> str:
    """"N loops", or "K of N loops kept by the graph" when it rejected some (trial 24 W2)."""
    if not result.loops_rejected_by_graph:
        return f"{result.loops_accepted} loops"
    kept = len(opt.loop_residuals) - result.loops_rejected_by_graph
    return f"{kept} of {len(opt.loop_residuals)} loops kept by the graph"


def _store_correction(store: FrameStore, result: BuildResult, opt: PoseGraphResult) -> None:
    """The optimised keyframe poses as a new ``loop_closure`` revision (propagated to the other frames) applied to
    the map; the largest correction into ``result``."""
    head = store.ledger.revision(store.head)
    if store.head != 0 and head.source is not PoseSource.LOOP_CLOSURE:  # a --resume after `correct` (trial 16 B6)
        logger.warning("loop closure: the store's head was revision %d (%s), a correction; the new loop-closure revision "
                       "is optimised from the odometry's poses (revision 0), so that correction is not in it (it stays "
                       "in the history: `driftmap correct` again, or compare with `driftmap revisions`)", store.head,
                       head.source.value)
    # the keyframes were optimised from revision 0's poses: the other frames follow them from revision 0 as well
    revision = store.add_revision(opt.poses, source=PoseSource.LOOP_CLOSURE, parent=0, propagate=True,
                                  covariances=opt.covariances,
                                  note=f"{_loops_note(result, opt)}, graph error {opt.initial_error:.3g} -> {opt.final_error:.3g}")
    changes = MapView.from_store(store, 0).apply(revision.revision_id)
    result.loop_revision = revision.revision_id
    result.max_correction_m = changes.max_translation_m
    result.max_correction_deg = max((c.rotation_deg for c in changes.changes), default=0.0)
    logger.info("loop closure: revision %d moved %d frames (max %.3f m)", revision.revision_id, len(changes.changes),
                result.max_correction_m)


def optimize_calibrated(keyframes: list[Keyframe], edges: list[Edge],
                         config: BuildConfig, result: BuildResult, *, calibrate_odometry: bool) -> PoseGraphResult:
    """Optimise, then rescale the information of each edge group so that its median chi2 at the optimum is the
    chi2(6) median, and optimise again (a robust variance-component estimate, ``information_calibration_iterations``
    times). Registration Hessians know the shape of the uncertainty but not its size: neighbouring points'
    residuals are correlated and the sensor's systematic errors are not in them."""
    scale = dict.fromkeys(EdgeGroup, 1.0)
    # odometry edges taken from frame-to-map odometry are not independent registrations: only the loops are calibrated
    calibrate = [EdgeGroup.ODOMETRY, EdgeGroup.LOOP] if calibrate_odometry else [EdgeGroup.LOOP]

    def make_graph(kernel: RobustKernel = config.loop_kernel) -> PoseGraph:
        graph = PoseGraph()
        for k in keyframes:
            graph.add_node(k.frame_id, k.T_world_sensor)
        graph.add_prior(keyframes[0].frame_id, keyframes[0].T_world_sensor, np.diag([1e8] * 6))
        for group, a, b, T, info in edges:
            if group is EdgeGroup.LOOP:
                graph.add_loop(a, b, T, info * scale[group], robust=kernel)
            else:
                graph.add_odometry(a, b, T, info * scale[group])
        return graph

    # the first round is plain least squares: with uncalibrated (over-confident) information a robust kernel
    # would switch every loop off, and the median chi2 is robust to a few wrong loops by itself
    graph = make_graph(RobustKernel.NONE if config.information_calibration_iterations else config.loop_kernel)
    # the rounds before the last are quiet: their rejected loops and convergence say nothing about the result
    opt = graph.optimize(config.optimizer, warn=not config.information_calibration_iterations)
    for _ in range(config.information_calibration_iterations):
        changed = False
        for group in calibrate:
            chi2 = [edge_residual_chi2(T, info * scale[group], opt.poses[a], opt.poses[b]) for g, a, b, T, info in edges if g is group]
            if len(chi2) < 6:
                continue
            factor = _CHI2_6DOF_MEDIAN / max(float(np.median(chi2)), 1e-9)
            scale[group] *= factor
            changed |= abs(factor - 1.0) > 0.05
        graph = make_graph()
        opt = graph.optimize(config.optimizer, warn=False)
        if not changed:
            break
    if not opt.converged:
        logger.warning("pose graph %s did not converge after the information calibration (%s)", opt.method.name,
                       "; ".join(opt.warnings) or "see the pose graph's log")
    result.information_scale = {g.value: s for g, s in scale.items() if g is not EdgeGroup.FALLBACK}
    logger.info("information calibration: odometry x%.3g, loops x%.3g", scale[EdgeGroup.ODOMETRY], scale[EdgeGroup.LOOP])
    try:  # the keyframes' uncertainty, kept with the revision (decisions propagate it to the points)
        opt = dataclasses.replace(opt, covariances=MappingProxyType(graph.marginal_covariances(opt.poses)))
    except PoseGraphError as exc:
        logger.warning("loop closure: no pose uncertainty for the revision (%s)", exc)
    return opt


def flagged_rows(store: FrameStore) -> dict[int, int]:
    """``{position in the store's frame order: frame id}`` of the frames whose odometry is flagged (lost or
    reinitialised): loop closure does not trust the trajectory across them."""
    out = {}
    for row, fid in enumerate(store.frame_ids):
        record = store.frame_info(int(fid)).get("tracking")
        if record is not None and record["status"] in ("lost", "reinitialised"):
            out[row] = int(fid)
    return out


#: median of a chi-square variable with 6 degrees of freedom
_CHI2_6DOF_MEDIAN = 5.348
