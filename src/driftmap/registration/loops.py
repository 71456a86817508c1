"""Keyframes, loop-closure candidates and their geometric verification.

Candidates come from two independent cues:

* **pose proximity** -- keyframes far apart in time whose odometry poses are close and look the same way;
* **a place descriptor** that ignores the (drifted) poses, so that its nearest neighbours are candidates even
  when the odometry puts them metres apart: for depth cameras (``place_descriptor = "shape"``) a rotation- and
  translation-invariant shape distribution of the keyframe's points (histogram of distances between random point
  pairs, plus the range histogram), aligned globally first (Open3D FPFH + RANSAC); for LiDAR
  (``"scan_context"``, :mod:`driftmap.registration.place`) the Scan Context of the keyframe cloud, whose best
  column shift gives the yaw that starts the registration.

Every candidate is verified with GICP (small_gicp) and gated on convergence, overlap (fitness), residual
RMSE and on how far the result is from what the odometry says (proximity candidates: ``max_correction_m`` plus 5 %
of the path between the two keyframes; descriptor candidates: plus ``descriptor_max_drift_fraction`` of it, which
refuses look-alike places far apart, while overlap and RMSE alone do not tell them from a revisit). Accepted and
rejected candidates are logged with their numbers and returned.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from pydantic import ConfigDict, Field
from scipy.spatial import cKDTree

from driftmap import geometry
from driftmap.config import SettingsModel, Threads
from driftmap.errors import ConfigError
from driftmap.registration.pairwise import (
    PreparedCloud,
    RegistrationResult,
    downsample,
    register_prepared,
    relative_pose,
)
from driftmap.registration.place import ScanContext, scan_context, scan_context_distance, yaw_guess

logger = logging.getLogger(__name__)


LIDAR_SUBMAP_RADIUS_FRAMES = 3
LIDAR_SUBMAP_RADIUS_S = 0.3
"""A LiDAR keyframe cloud holds the scans within this of the keyframe (3 on each side at 10 Hz, none at 2 Hz), at
most :data:`LIDAR_SUBMAP_RADIUS_FRAMES` on each side."""
LIDAR_VOXEL_PER_ODOMETRY_VOXEL = 0.5
RMSE_GATE_PER_VOXEL = 0.875  # the depth camera's 3.5 cm per 4 cm
LIDAR_PROXIMITY_PER_ODOMETRY_VOXEL = 10.0
LIDAR_CORRECTION_PER_ODOMETRY_VOXEL = 2.5
LIDAR_SCAN_CONTEXT_RADIUS_PER_ODOMETRY_VOXEL = 80.0
PROXIMITY_DRIFT_FRACTION = 0.05
"""Proximity loops may disagree with odometry by ``max_correction_m`` plus this share of the path between them."""
LIDAR_LOOP_DEFAULTS = {"submap_radius_frames": f"the scans within {LIDAR_SUBMAP_RADIUS_S:g} s, at most {LIDAR_SUBMAP_RADIUS_FRAMES}",
                       "registration_voxel_m": f"{LIDAR_VOXEL_PER_ODOMETRY_VOXEL:g} x the odometry voxel",
                       "max_rmse_m": f"{RMSE_GATE_PER_VOXEL:g} x registration_voxel_m",
                       "proximity_radius_m": f"{LIDAR_PROXIMITY_PER_ODOMETRY_VOXEL:g} x the odometry voxel",
                       "max_correction_m": f"{LIDAR_CORRECTION_PER_ODOMETRY_VOXEL:g} x the odometry voxel",
                       "place_descriptor": "scan_context",
                       "scan_context_max_radius_m": f"{LIDAR_SCAN_CONTEXT_RADIUS_PER_ODOMETRY_VOXEL:g} x the odometry voxel"}
"""The fields :meth:`LoopClosureConfig.for_lidar` sets, as ``driftmap config`` describes them."""


class LoopClosureConfig(SettingsModel):
    """Keyframe selection, candidate search and verification gates (metres, degrees)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    keyframe_distance_m: float = Field(0.10, gt=0.0, description="new keyframe after this much translation (m), and never closer than 2 submap_radius_frames + 1 stored frames to the last (keyframe clouds share no frame)")
    keyframe_angle_deg: float = Field(10.0, gt=0.0, description="... or this much rotation (deg)")
    keyframe_max_gap_frames: int = Field(30, ge=1, description="... or this many stored frames (counted in the --frames selection)")
    min_gap_s: float = Field(2.0, gt=0.0, description="candidates must be at least this long apart (frame stamps; 7-Scenes' nominal 30 Hz: 60 frames), whatever the --frames step and the sensor rate")
    min_gap_frames: int | None = Field(None, ge=1, description="if set: candidates must instead be at least this many frames apart in the source's frame numbering (frame_id)")
    proximity_radius_m: float = Field(1.0, gt=0.0, description="odometry positions closer than this are candidates (m)")
    proximity_max_angle_deg: float = Field(45.0, gt=0.0, description="... if their viewing directions differ by less (deg)")
    max_candidates_per_keyframe: int = Field(15, ge=1, description="nearest proximity candidates kept per keyframe")
    descriptor_candidates: int = Field(1, ge=0, description="descriptor nearest neighbours tried per keyframe")
    descriptor_max_distance: float = Field(0.15, gt=0.0, description="shape descriptor distance (L1 of histograms) gate")
    session_descriptor_candidates: int = Field(3, ge=0, description="merge: shape descriptor nearest neighbours tried per keyframe between sessions (the descriptor is the only way to find them; verification and the sessions' consensus refuse the wrong ones)")
    session_descriptor_max_distance: float = Field(0.35, gt=0.0, description="merge: shape descriptor gate between sessions (7-Scenes redkitchen in two sessions: true matches 0.17-0.69, none within build's 0.15; at 0.35 the merge connected with 41 consistent loops)")
    place_descriptor: Literal["shape", "scan_context"] = Field("shape", description="shape: D2 shape histograms aligned by FPFH + RANSAC (depth cameras); scan_context: Scan Context of the keyframe cloud, its best column shift starting the registration (LiDAR, z up; the LiDAR default)")
    scan_context_max_distance: float = Field(0.3, gt=0.0, le=1.0, description="scan_context: distance gate (1 - mean cosine similarity of the sector columns)")
    scan_context_max_radius_m: float = Field(80.0, gt=0.0, description="scan_context: radius of the polar grid (m)")
    scan_context_ring_candidates: int = Field(10, ge=1, description="scan_context: older keyframes nearest in ring key compared in full")
    registration_voxel_m: float = Field(0.04, gt=0.0, description="GICP voxel size (m)")
    submap_radius_frames: int = Field(0, ge=0, description="a keyframe's cloud also holds this many frames on each side, placed by odometry")
    max_range_m: float | None = Field(None, gt=0.0, description="keyframe clouds keep points within this range (m); None: the odometry's max_range_m, or every point with given poses")
    min_fitness: float = Field(0.45, ge=0.0, le=1.0, description="minimum overlap after alignment")
    max_rmse_m: float = Field(0.035, gt=0.0, description="maximum inlier RMSE after alignment (m)")
    max_correction_m: float = Field(0.5, gt=0.0, description="proximity loops: max disagreement with odometry (m)")
    max_correction_deg: float = Field(15.0, gt=0.0, description="... and in rotation (deg)")
    descriptor_max_drift_fraction: float = Field(0.25, gt=0.0, description="descriptor loops: max disagreement with odometry, as a share of the path travelled between the two keyframes (plus max_correction_m): an odometry drifts, but not by a quarter of its path, and look-alike places far apart (parallel streets) are refused")
    num_threads: Threads = Field(2, description="threads of the keyframe registrations (small_gicp, Open3D RANSAC); 1: repeatable to the bit")

    @classmethod
    def for_lidar(cls, odometry_voxel_m: float, scan_period_s: float | None = None) -> LoopClosureConfig:
        """Defaults for LiDAR scans, whose odometry voxel (KISS-ICP's, scaled to the scene: 1 m outdoors) says how
        coarse and how large their scene is: keyframe clouds of 7 scans (``submap_radius_frames`` 3: one ring scan is
        too sparse for GICP at a depth camera's 4 cm, whose keyframe-to-keyframe edges then pull a good odometry off;
        keyframes are then at least 7 frames apart, :func:`keyframe_min_frames`), registered at half the odometry
        voxel, with the RMSE gate scaled alike (3.5 cm per 4 cm); proximity candidates within 10 odometry voxels and
        corrections up to 2.5 voxels (plus 5 % of the path) accepted: outdoors 10 m and 2.5 m, where keyframes
        7 scans apart are metres apart and a street's drift is metres; places recognised by their Scan Context
        (``place_descriptor``) on a polar grid of 80 odometry voxels (80 m outdoors), whatever the drift. The other
        fields keep their defaults. ``scan_period_s`` (the median time between scans): the keyframe cloud holds the
        scans within :data:`LIDAR_SUBMAP_RADIUS_S` (0.3 s) on each side, at most 3: at 2 Hz a scan moves five times as
        far, 7 scans span 35 m on a street and keyframes 7 scans apart miss a 22 m revisit (no loop closed; with
        single-scan keyframes the 2 Hz street closes to 0.7 cm)."""
        voxel = LIDAR_VOXEL_PER_ODOMETRY_VOXEL * odometry_voxel_m
        radius = LIDAR_SUBMAP_RADIUS_FRAMES
        if scan_period_s is not None and scan_period_s > 0:
            radius = min(LIDAR_SUBMAP_RADIUS_FRAMES, int(math.floor(LIDAR_SUBMAP_RADIUS_S / scan_period_s + 1e-9)))
        return cls(submap_radius_frames=radius, registration_voxel_m=voxel,
                   max_rmse_m=RMSE_GATE_PER_VOXEL * voxel,
                   proximity_radius_m=LIDAR_PROXIMITY_PER_ODOMETRY_VOXEL * odometry_voxel_m,
                   max_correction_m=LIDAR_CORRECTION_PER_ODOMETRY_VOXEL * odometry_voxel_m,
                   place_descriptor="scan_context",
                   scan_context_max_radius_m=LIDAR_SCAN_CONTEXT_RADIUS_PER_ODOMETRY_VOXEL * odometry_voxel_m)

    def over(self, defaults: LoopClosureConfig) -> LoopClosureConfig:
        """``defaults`` with the fields set explicitly in this config (``model_fields_set``) taken from it."""
        return defaults.model_copy(update={name: getattr(self, name) for name in self.model_fields_set})


@dataclass(frozen=True)
class Keyframe:
    frame_id: int
    """The source's frame number: ``min_gap_frames`` is counted in these."""
    index: int
    """Position in the frame sequence."""
    T_world_sensor: NDArray[np.float64]
    points_m: NDArray[np.float64]
    """Sensor-frame points downsampled to the registration voxel."""
    descriptor: NDArray[np.float64]
    cloud: PreparedCloud
    """The same points with their GICP preprocessing, cached per voxel size."""
    stamp_ns: int
    """The frame's stamp: ``min_gap_s`` is measured in these."""
    scan_context: ScanContext | None = None
    """The keyframe cloud's Scan Context (``place_descriptor = "scan_context"``)."""


class CandidateKind(enum.Enum):
    PROXIMITY = "proximity"
    DESCRIPTOR = "descriptor"
    SCAN_CONTEXT = "scan_context"
    INJECTED = "injected"


@dataclass(frozen=True)
class LoopCandidate:
    a: int
    """frame id of the older keyframe."""
    b: int
    kind: CandidateKind
    accepted: bool
    reason: str
    result: RegistrationResult | None
    T_a_b: NDArray[np.float64] | None
    """Measured relative pose (when verified)."""

    def describe(self) -> str:
        numbers = self.result.describe() if self.result is not None else "not registered"
        return f"{self.kind.value} {self.a}<->{self.b}: {'ACCEPTED' if self.accepted else 'rejected'} ({self.reason}; {numbers})"


def shape_descriptor(points_m: NDArray[np.floating], *, n_pairs: int = 4000, bins: int = 24, max_range_m: float = 5.0,
                     seed: int = 0) -> NDArray[np.float64]:
    """Rotation- and translation-invariant place descriptor: normalised histograms of distances between
    random point pairs (D2 shape distribution) and of distances to the centroid."""
    pts = np.asarray(points_m, dtype=np.float64)
    if len(pts) < 10:
        return np.zeros(2 * bins)
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, len(pts), n_pairs), rng.integers(0, len(pts), n_pairs)
    d2 = np.linalg.norm(pts[i] - pts[j], axis=1)
    dc = np.linalg.norm(pts - pts.mean(0), axis=1)
    h1, _ = np.histogram(d2, bins=bins, range=(0.0, max_range_m))
    h2, _ = np.histogram(dc, bins=bins, range=(0.0, max_range_m))
    return np.concatenate([h1 / max(h1.sum(), 1), h2 / max(h2.sum(), 1)])


def keyframe_min_frames(config: LoopClosureConfig) -> int:
    """The fewest stored frames between two keyframes: ``2 submap_radius_frames + 1``, so that no two keyframe
    clouds share a frame. Two clouds that share frames place them with the odometry's relative poses, and a
    registration of the two then copies part of the odometry instead of measuring it (synthetic street log, 7-scan
    clouds one scan apart: a quarter of the odometry's 1 % scale error came back in the odometry edges)."""
    return 2 * config.submap_radius_frames + 1


def select_keyframes(poses: NDArray[np.float64], config: LoopClosureConfig) -> list[int]:
    """Indices of keyframes along a trajectory (the first frame always is one), at least
    :func:`keyframe_min_frames` apart."""
    keys = [0]
    spacing = keyframe_min_frames(config)
    for i in range(1, len(poses)):
        last = poses[keys[-1]]
        if i - keys[-1] < spacing:
            continue
        if (geometry.translation_distance_m(last, poses[i]) >= config.keyframe_distance_m
                or geometry.rotation_angle_deg(last, poses[i]) >= config.keyframe_angle_deg
                or i - keys[-1] >= config.keyframe_max_gap_frames):
            keys.append(i)
    return keys


def loop_gap(config: LoopClosureConfig) -> tuple[str, float]:
    """``(unit, gap)``: how far apart loop candidates must be -- ``("frames", min_gap_frames)`` in the source's
    frame numbers when that is set, else ``("s", min_gap_s)`` in time."""
    if config.min_gap_frames is not None:
        return "frames", float(config.min_gap_frames)
    return "s", config.min_gap_s


GAP_TOLERANCE_S = 1e-3
"""Stamps a loop gap apart within this count as far enough apart (a nominal 30 Hz period of 33 333 333 ns puts
60 frames 20 ns short of 2 s)."""


def gap_threshold(config: LoopClosureConfig) -> float:
    """The least separation (in :func:`loop_gap`'s unit) that counts as a loop gap: the gap itself in frame
    numbers, ``GAP_TOLERANCE_S`` less in seconds."""
    unit, gap = loop_gap(config)
    return gap - GAP_TOLERANCE_S if unit == "s" else gap


def _gap_positions(keyframes: Sequence[Keyframe], config: LoopClosureConfig) -> NDArray[np.float64]:
    """Each keyframe's position on the axis :func:`loop_gap` measures along (frame number or seconds)."""
    unit, _ = loop_gap(config)
    if unit == "frames":
        return np.array([k.frame_id for k in keyframes], dtype=np.float64)
    return np.array([k.stamp_ns for k in keyframes], dtype=np.float64) * 1e-9


def _older(at: NDArray[np.float64], j: int, config: LoopClosureConfig) -> NDArray[np.intp]:
    """Positions of the keyframes at least the loop gap before keyframe ``j``."""
    return np.flatnonzero(at <= at[j] - gap_threshold(config))


def _viewing_angle_deg(T_a: NDArray[np.float64], T_b: NDArray[np.float64]) -> float:
    za, zb = T_a[:3, 2], T_b[:3, 2]
    return float(np.degrees(np.arccos(np.clip(za @ zb, -1.0, 1.0))))


def proximity_candidates(keyframes: Sequence[Keyframe], config: LoopClosureConfig) -> list[tuple[int, int]]:
    """Pairs (older, newer) of keyframe list positions that odometry places close together (nearer than
    ``proximity_radius_m``, viewing directions within ``proximity_max_angle_deg``), at least ``min_gap_s`` apart in
    time (or ``min_gap_frames`` in frame numbers, when set); per newer keyframe the
    ``max_candidates_per_keyframe`` nearest (ties: the older first). The neighbours come from one KD-tree over the
    positions, so the cost grows with the keyframes and their neighbours, not with their square."""
    if len(keyframes) < 2:
        return []
    T = np.array([k.T_world_sensor for k in keyframes])
    pos, view_z = T[:, :3, 3], T[:, :3, 2]
    at = _gap_positions(keyframes, config)
    threshold = gap_threshold(config)
    pairs = []
    for j, near in enumerate(cKDTree(pos).query_ball_point(pos, config.proximity_radius_m, return_sorted=True)):
        older = np.asarray(near, dtype=np.intp)
        older = older[at[older] <= at[j] - threshold]
        if older.size == 0:
            continue
        d = np.linalg.norm(pos[older] - pos[j], axis=1)
        angle = np.degrees(np.arccos(np.clip(view_z[older] @ view_z[j], -1.0, 1.0)))
        keep = (d < config.proximity_radius_m) & (angle < config.proximity_max_angle_deg)
        older, d = older[keep], d[keep]
        nearest = older[np.argsort(d, kind="stable")[: config.max_candidates_per_keyframe]]  # ties: older first
        pairs += [(int(i), j) for i in nearest]
    return pairs


def descriptor_candidates(keyframes: Sequence[Keyframe], config: LoopClosureConfig,
                          exclude: set[tuple[int, int]]) -> list[tuple[int, int]]:
    """Pairs whose shape descriptors are nearest neighbours, whatever the odometry says."""
    if config.descriptor_candidates == 0 or len(keyframes) < 2:
        return []
    desc = np.array([k.descriptor for k in keyframes])
    at = _gap_positions(keyframes, config)
    pairs = []
    for j in range(len(keyframes)):
        older = _older(at, j, config)
        if older.size == 0:
            continue
        dist = np.abs(desc[older] - desc[j]).sum(axis=1)
        order = np.argsort(dist)[: config.descriptor_candidates]
        for o in order:
            if dist[o] <= config.descriptor_max_distance and (older[o], j) not in exclude:
                pairs.append((int(older[o]), j))
    return pairs


def scan_context_candidates(keyframes: Sequence[Keyframe], config: LoopClosureConfig,
                            exclude: set[tuple[int, int]]) -> list[tuple[int, int, NDArray[np.float64]]]:
    """``(older, newer, T_a_b guess)`` for keyframe pairs whose Scan Contexts match, whatever the odometry says:
    per keyframe, the ``scan_context_ring_candidates`` older keyframes nearest in ring key are compared in full
    and the best ``descriptor_candidates`` within ``scan_context_max_distance`` kept (pairs in ``exclude``, the
    proximity candidates, are not proposed twice); the guess is the yaw of the best column shift."""
    if config.descriptor_candidates == 0 or len(keyframes) < 2:
        return []
    missing = [k.frame_id for k in keyframes if k.scan_context is None]
    if missing:
        raise ConfigError(f"scan_context_candidates: keyframes without a Scan Context (frames {missing[:5]}); "
                         "make them with place_descriptor = 'scan_context'")
    contexts = [k.scan_context for k in keyframes]
    ring_keys = np.array([c.ring_key for c in contexts])
    at = _gap_positions(keyframes, config)
    pairs = []
    for j in range(len(keyframes)):
        older = _older(at, j, config)
        if older.size == 0 or contexts[j].is_empty:
            continue
        near = older[np.argsort(np.linalg.norm(ring_keys[older] - ring_keys[j], axis=1), kind="stable")]
        scored = sorted((scan_context_distance(contexts[i], contexts[j]) + (int(i),)
                         for i in near[: config.scan_context_ring_candidates]), key=lambda x: (x[0], x[2]))
        for distance, yaw, i in scored[: config.descriptor_candidates]:
            if distance <= config.scan_context_max_distance and (i, j) not in exclude:
                logger.debug("scan context %d<->%d: distance %.3f, yaw %.1f deg", keyframes[i].frame_id,
                             keyframes[j].frame_id, distance, np.degrees(yaw))
                pairs.append((i, j, yaw_guess(yaw)))
    return pairs


def _fpfh(points_m: NDArray[np.float64], voxel_m: float) -> tuple[o3d.geometry.PointCloud, o3d.pipelines.registration.Feature]:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_m))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel_m, max_nn=30))
    feat = o3d.pipelines.registration.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel_m, max_nn=100))
    return pcd, feat


def global_initial_guess(target_m: NDArray[np.float64], source_m: NDArray[np.float64], voxel_m: float, *,
                         seed: int = 0, num_threads: int | None = None) -> NDArray[np.float64]:
    """Open3D FPFH + RANSAC alignment (no pose prior), used for descriptor candidates.

    RANSAC draws from Open3D's global random engine, which is seeded with ``seed`` first (this re-seeds it for
    everything else in the process too). Its worker threads share that engine, so only with ``num_threads=1``
    (Open3D's thread limit, restored afterwards) is the result the same in every run."""
    coarse = 2.5 * voxel_m
    t, ft = _fpfh(downsample(target_m, coarse), coarse)
    s, fs = _fpfh(downsample(source_m, coarse), coarse)
    reg = o3d.pipelines.registration
    previous = o3d.utility.get_max_threads()
    try:
        if num_threads is not None:
            o3d.utility.set_max_threads(num_threads)
        o3d.utility.random.seed(seed)
        # "Too few correspondences after mutual filter" is Open3D's warning for a pair that has nothing in common: the
        # gates after the registration say so (trials 14, 15: 45 coloured lines in a merge's output)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            result = reg.registration_ransac_based_on_feature_matching(
                s, t, fs, ft, True, 1.5 * coarse, reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                 reg.CorrespondenceCheckerBasedOnDistance(1.5 * coarse)],
                reg.RANSACConvergenceCriteria(100000, 0.999),
            )
    finally:
        if num_threads is not None:
            o3d.utility.set_max_threads(previous)
    return np.asarray(result.transformation)


def verify(a: Keyframe, b: Keyframe, kind: CandidateKind, config: LoopClosureConfig, *,
           path_length_m: float = 0.0, init_T_a_b: NDArray[np.float64] | None = None) -> LoopCandidate:
    """Register keyframe b to keyframe a and apply the gates."""
    odom = relative_pose(a.T_world_sensor, b.T_world_sensor)
    if init_T_a_b is None:
        init_T_a_b = odom if kind is CandidateKind.PROXIMITY else global_initial_guess(
            a.points_m, b.points_m, config.registration_voxel_m, seed=(a.frame_id * 1_000_003 + b.frame_id) & 0x7FFFFFFF,
            num_threads=config.num_threads)
    v = config.registration_voxel_m
    coarse = register_prepared(a.cloud, b.cloud, init_T_a_b, voxel_size_m=2 * v, max_correspondence_m=8 * v)
    result = register_prepared(a.cloud, b.cloud, coarse.T_target_source, voxel_size_m=v, max_correspondence_m=2.5 * v)
    reasons = []
    if not result.converged:
        reasons.append("did not converge")
    if result.fitness < config.min_fitness:
        reasons.append(f"fitness {result.fitness:.2f} < {config.min_fitness}")
    if result.rmse_m > config.max_rmse_m:
        reasons.append(f"rmse {result.rmse_m * 100:.1f} cm > {config.max_rmse_m * 100:.1f} cm")
    # the drift an odometry may have gathered between the two: 5 % of the path for the candidates it proposed
    # itself (and a rotation bound), a quarter of it for a descriptor's (the odometry did not see that loop)
    proximity = kind is CandidateKind.PROXIMITY
    fraction = PROXIMITY_DRIFT_FRACTION if proximity else config.descriptor_max_drift_fraction
    dt = geometry.translation_distance_m(odom, result.T_target_source)
    dr = geometry.rotation_angle_deg(odom, result.T_target_source)
    allowed = config.max_correction_m + fraction * path_length_m
    if dt > allowed or (proximity and dr > config.max_correction_deg):
        reasons.append(f"disagrees with odometry by {dt:.2f} m / {dr:.1f} deg (allowed {allowed:.2f} m: "
                       f"{config.max_correction_m:g} m + {100 * fraction:g} % of the {path_length_m:.2f} m travelled"
                       + (f", {config.max_correction_deg:g} deg)" if proximity else ")"))
    accepted = not reasons
    cand = LoopCandidate(a.frame_id, b.frame_id, kind, accepted, "; ".join(reasons) or "passed all gates", result,
                         result.T_target_source)
    logger.info("loop candidate %s", cand.describe())
    return cand


def make_keyframe(frame_id: int, index: int, T_world_sensor: NDArray[np.float64], points_m: NDArray[np.floating],
                  config: LoopClosureConfig, *, stamp_ns: int) -> Keyframe:
    pts = downsample(points_m, config.registration_voxel_m / 2)
    context = (scan_context(pts, max_radius_m=config.scan_context_max_radius_m)
               if config.place_descriptor == "scan_context" else None)
    return Keyframe(frame_id, index, T_world_sensor, pts, shape_descriptor(pts), PreparedCloud(pts, config.num_threads),
                    int(stamp_ns), context)


def untrusted_between(a: Keyframe, b: Keyframe, flagged: Mapping[int, int], config: LoopClosureConfig,
                      rows: NDArray[np.int64] | None = None) -> list[int]:
    """Frame ids of the ``flagged`` frames (``{position: frame id}``, tracking lost) in the odometry stretch that a
    candidate between keyframes ``a`` and ``b`` leans on: from ``a``'s cloud to ``b``'s (``submap_radius_frames``
    on each side). ``rows``: ``flagged``'s keys sorted, when the caller asks for many candidates."""
    lo, hi = a.index - config.submap_radius_frames, b.index + config.submap_radius_frames
    rows = np.array(sorted(flagged), dtype=np.int64) if rows is None else rows
    return [flagged[int(row)] for row in rows[np.searchsorted(rows, lo, "left"):np.searchsorted(rows, hi, "right")]]


def find_loops(keyframes: Sequence[Keyframe], config: LoopClosureConfig, *,
               progress: Callable[[int, int], None] | None = None,
               flagged: Mapping[int, int] | None = None) -> list[LoopCandidate]:
    """Propose candidates from both cues and verify each one. A candidate across a stretch whose odometry is
    ``flagged`` (``{position: frame id}`` of frames whose tracking was lost) is refused unverified: its
    keyframe clouds and its agreement gate would both stand on a trajectory that is not trusted."""
    positions = np.array([k.T_world_sensor[:3, 3] for k in keyframes])
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))]) if len(keyframes) else np.zeros(0)
    prox = proximity_candidates(keyframes, config)
    todo: list[tuple[int, int, CandidateKind, NDArray[np.float64] | None]] = [
        (i, j, CandidateKind.PROXIMITY, None) for i, j in prox]
    if config.place_descriptor == "scan_context":
        todo += [(i, j, CandidateKind.SCAN_CONTEXT, T) for i, j, T in scan_context_candidates(keyframes, config, set(prox))]
    else:
        todo += [(i, j, CandidateKind.DESCRIPTOR, None) for i, j in descriptor_candidates(keyframes, config, set(prox))]
    out = []
    flagged_rows = np.array(sorted(flagged or {}), dtype=np.int64)
    for n, (i, j, kind, guess) in enumerate(todo):
        lost = untrusted_between(keyframes[i], keyframes[j], flagged or {}, config, flagged_rows)
        if lost:
            cand = LoopCandidate(keyframes[i].frame_id, keyframes[j].frame_id, kind, False,
                                 f"the odometry between them is flagged (tracking lost at frame(s) "
                                 f"{', '.join(map(str, lost[:5]))}{' ...' if len(lost) > 5 else ''})", None, None)
            logger.info("loop candidate %s", cand.describe())
            out.append(cand)
        else:
            out.append(verify(keyframes[i], keyframes[j], kind, config, path_length_m=float(path[j] - path[i]),
                              init_T_a_b=guess))
        if progress:
            progress(n + 1, len(todo))
    return out
