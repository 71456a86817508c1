"""Odometry: frame-to-map GICP (small_gicp) for depth cameras, KISS-ICP for LiDAR.

* :class:`GicpMapOdometry` (default for depth cameras) registers each frame to a persistent Gaussian voxel
  map of everything registered so far (small_gicp VGICP), starting from a constant-velocity prediction,
  with a coarse-map fallback when the fine registration finds too few inliers. Registering to the fused
  map instead of the previous frame keeps the drift low (the map averages many views) and makes a
  revisited place snap back to the geometry already mapped.
* :class:`KissOdometry` (default for LiDAR) wraps KISS-ICP.

Both time each step. Their state is built only by registering frames: ``build --resume`` registers the stored
frames again (``pipeline/build.py``) to continue exactly where a build stopped. :func:`make_odometry` picks the
implementation named by the configuration.
"""

from __future__ import annotations

import enum
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import small_gicp
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP
from numpy.typing import NDArray
from pydantic import ConfigDict, Field

from driftmap import geometry
from driftmap.config import SettingsModel, Threads
from driftmap.frame import Frame, SensorKind, TrackingHealth, TrackingStatus
from driftmap.preprocess.scene import (
    LIDAR_MIN_SCENE_SCALE,
    LIDAR_OUTDOOR_P99_RANGE_M,
    lidar_frames,
    lidar_odometry_scale,
    scan_reach_m,
    scene_reach,
)
from driftmap.registration import tracking
from driftmap.registration.pairwise import register

logger = logging.getLogger(__name__)


class OdometryMethod(enum.Enum):
    GICP_MAP = "gicp_map"
    """frame-to-map GICP against a persistent Gaussian voxel map (small_gicp VGICP)"""
    KISS = "kiss"
    """KISS-ICP (point-to-point ICP against a local voxel map, adaptive threshold)"""


class OdometryConfig(SettingsModel):
    """Odometry settings, in metres. ``method`` picks the implementation; the ``gicp_*`` fields apply to
    ``gicp_map``, ``voxel_size_m`` .. ``max_points_per_voxel`` to ``kiss``, the ranges and ``max_points`` to both."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    method: OdometryMethod = Field(OdometryMethod.GICP_MAP, description="gicp_map (frame-to-map GICP) or kiss (KISS-ICP)")
    max_points: int | None = Field(20_000, ge=100, description="register at most about this many points per frame (every k-th point); None: all")
    min_range_m: float = Field(0.2, ge=0.0, description="points closer than this are ignored (m)")
    max_range_m: float = Field(2.75, gt=0.0, description="points farther than this are ignored (m)")
    gicp_downsample_m: float = Field(0.03, gt=0.0, description="gicp_map: frame voxel downsampling (m)")
    gicp_map_voxel_m: float = Field(0.05, gt=0.0, description="gicp_map: Gaussian voxel map resolution (m)")
    gicp_max_correspondence_m: float = Field(0.1, gt=0.0, description="gicp_map: correspondence distance (m)")
    gicp_coarse_downsample_m: float = Field(0.1, gt=0.0, description="gicp_map: coarse fallback downsampling (m)")
    gicp_coarse_map_voxel_m: float = Field(0.25, gt=0.0, description="gicp_map: coarse fallback map resolution (m)")
    gicp_coarse_max_correspondence_m: float = Field(0.5, gt=0.0, description="gicp_map: coarse fallback correspondence distance (m)")
    gicp_min_inlier_fraction: float = Field(0.5, ge=0.0, le=1.0, description="gicp_map: below this inlier fraction the coarse fallback is tried")
    gicp_map_horizon_frames: int | None = Field(None, ge=1, description="gicp_map: map voxels unseen for this many frames are dropped (None: keep the whole map)")
    gicp_max_iterations: int = Field(30, ge=1, description="gicp_map: Gauss-Newton iterations per registration")
    gicp_degenerate_shift_m: float | None = Field(0.1, gt=0.0, description="gicp_map: a registration that moved more than this (m) from the prediction along directions the frame barely constrains (degeneracy of the registration's translational Hessian below tracking_degenerate_below) keeps the prediction's translation along them and the frame is reported degenerate; None: off. Measured: the synthetic room log's first step slid 21 cm along a bare wall, reported ok (hostile trial 30 B2)")
    voxel_size_m: float = Field(0.08, gt=0.0, description="kiss: KISS-ICP map voxel size (m)")
    deskew: bool = Field(False, description="kiss: motion-compensate scans with per-point time (LiDAR)")
    initial_threshold_m: float = Field(0.3, gt=0.0, description="kiss: initial correspondence threshold (m)")
    min_motion_m: float = Field(0.01, ge=0.0, description="kiss: motion below which the adaptive threshold is not updated (m)")
    max_points_per_voxel: int = Field(20, ge=1, description="kiss: points kept per map voxel")
    kiss_refine_gicp: bool = Field(False, description="kiss: refine each KISS-ICP registration by GICP (small_gicp) of the scan against the local map; measured: synthetic street ATE 9.1 -> 0.2 cm, the real Livox log 2.2 -> 1.6 cm, KITTI 00 0-15 0.36 -> 0.38 m, at 1.5-2x the odometry time (off by default: KITTI)")
    kiss_refine_plane: bool = Field(True, description="kiss: refine each KISS-ICP registration by point-to-plane ICP (small_gicp, the local map's normals) from KISS-ICP's result and from the prediction, keeping of those within 0.05 inlier share of the best the one nearest the prediction; measured (odometry ATE): synthetic rosette street 548 -> 8.5 cm, spinning street 9.1 -> 1.1 cm, the real Livox log 2.25 -> 1.55 cm, KITTI 00 0-15 36.4 -> 37.0 cm, at 1.5-3x the odometry time")
    kiss_prime_motion: bool = Field(True, description="kiss: whenever the motion model says the sensor stands (the first scans, after a stop), estimate the motion to the next scan by GICP of the two scans and start KISS-ICP's constant-velocity model with it when it is at least half a voxel or 5 deg (from zero velocity a LiDAR that drives off lands short)")
    num_threads: Threads = Field(2, description="threads of the registration (small_gicp / KISS-ICP); 1: the same frames give the same poses to the bit")
    tracking_retry: bool = Field(True, description="kiss: when a registration fits the map clearly worse than the frames before it, retry from other initial guesses (zero motion, half velocity, turned +-yaw) and keep the best fit (registration/tracking.py)")
    tracking_fitness_radius_voxels: float = Field(0.5, gt=0.0, description="kiss: a registered point fits the map when a map point is within this many voxels")
    tracking_min_fitness: float = Field(0.25, ge=0.0, le=1.0, description="kiss: a frame whose best registration fits less than this share of its points is lost (flagged, its pose bridged); 0.25: a forward-looking non-repetitive scanner moving into new space fits 0.3-0.5 of its points within half a voxel (0.5 lost 9 of the synthetic rosette street's scans)")
    tracking_retry_fitness_ratio: float = Field(0.9, ge=0.0, le=1.0, description="kiss: retry when the fitness is below this share of the median of the last 10 frames")
    tracking_check_deviation_deg: float = Field(15.0, gt=0.0, description="kiss: a registration that ended this far from the prediction (deg) is cross-checked from zero motion and half velocity; the better fit (fitness, then RMSE) is kept")
    tracking_check_deviation_voxels: float = Field(2.0, gt=0.0, description="kiss: ... or this many voxels from it")
    tracking_min_gain: float = Field(0.02, ge=0.0, le=1.0, description="kiss: another initial guess replaces the prediction's registration only when its fitness is higher by this")
    tracking_yaw_hypotheses_deg: tuple[float, ...] = Field((15.0, 30.0, 45.0), description="kiss: the retry also starts from the prediction turned by +- each of these about the sensor's z axis (deg)")
    tracking_max_lost_frames: int = Field(2, ge=0, description="kiss: after this many lost frames in a row the local map restarts at the bridged pose (flagged as reinitialised)")
    tracking_degenerate_below: float = Field(0.11, ge=0.0, le=1.0, description="kiss (with kiss_refine_plane): along a direction whose point-to-plane information is below this degeneracy (sqrt(lambda / lambda_max) of the refinement's translational Hessian) the registration's translation is replaced by the prediction's and the frame is reported degenerate; 0: off. Measured (odometry ATE): synthetic rosette room 38 -> 2.2 cm (5 of 59 scans, facing one wall with a 70 deg field of view); spinning room and street, rosette street and the real Livox log unchanged (no scan below 0.14)")

    @classmethod
    def for_sensor(cls, kind: SensorKind) -> OdometryConfig:
        """Defaults for indoor RGB-D (frame-to-map GICP on points within 0.2..2.75 m) or outdoor LiDAR
        (KISS-ICP with its own settings, every point)."""
        if kind is SensorKind.LIDAR:
            return cls(method=OdometryMethod.KISS, voxel_size_m=1.0, min_range_m=0.5, max_range_m=100.0, deskew=False,
                       initial_threshold_m=2.0, min_motion_m=0.1, max_points=None)
        return cls()

    @classmethod
    def for_frame(cls, frame: Frame, *, log: bool = True) -> OdometryConfig:
        """:meth:`for_frames` of one frame (prefer many: one scan may face a wall)."""
        return cls.for_frames([frame], log=log)

    @classmethod
    def for_frames(cls, frames: Sequence[Frame], *, log: bool = True) -> OdometryConfig:
        """Defaults for the sensor of ``frames`` (a build's first frame and others spread over the log), LiDAR ones
        scaled to the scene.

        KISS-ICP ties every length to the sensor's range (voxel = max range / 100); :meth:`for_sensor`'s LiDAR
        settings are those of a 100 m outdoor sensor (KITTI scans reach 56-59 m at their 99th range percentile).
        The scene's reach is the median over ``frames`` of each scan's 99th range percentile
        (:func:`driftmap.preprocess.scene.scene_reach`); every KISS-ICP length is scaled by
        ``min(1, max(0.05, reach / 25 m))`` (:func:`~driftmap.preprocess.scene.lidar_odometry_scale`): a scene
        reaching 25 m or more keeps :meth:`for_sensor`'s settings. On the synthetic log's indoor LiDAR (p99 4.6 m:
        0.185 m voxels, 18.5 m range) the odometry ATE over 15 logs (seeds 1-7; 20, 30 and 60 frames per loop) is
        0.32-0.64 cm, against 3.4-6.6 cm with the outdoor settings; half that scale (KISS-ICP's rule taking the
        sensor's reach as twice the p99) was finer but lost the first, prediction-free registration on 2 of the 9
        logs tried (ATE 11 and 83 cm; docs/build.md)."""
        if not frames:
            raise ValueError("OdometryConfig.for_frames needs at least one frame")
        base = cls.for_sensor(frames[0].sensor_kind)
        if frames[0].sensor_kind is not SensorKind.LIDAR:
            return base
        if any(f.attributes.time_offset_ns is not None for f in frames):  # KISS-ICP deskews scans with point times
            base = base.model_copy(update={"deskew": True})
        reach = scene_reach(lidar_frames(frames))
        if reach is None:
            return base
        scale = lidar_odometry_scale(reach.reach_m)
        if scale >= 1.0:
            return base
        scaled = base.model_copy(update={name: getattr(base, name) * scale for name in KISS_LENGTHS})
        if log and (scale <= LIDAR_MIN_SCENE_SCALE or reach.n_frames < 3):
            logger.warning("LiDAR odometry lengths are scaled by %.3f from %d frame(s) reaching %s: if these scans are "
                           "not typical of the log, set the [build.odometry] lengths (voxel_size_m, max_range_m, ...)",
                           scale, reach.n_frames, reach.describe())
        if log:
            logger.info("LiDAR odometry scaled to the scene: it reaches %s (outdoor defaults from %.0f m), so every "
                        "KISS-ICP length is scaled by %.3f: voxels %.3f m, ranges %.3f .. %.1f m, initial threshold "
                        "%.3f m, minimum motion %.4f m (set [build.odometry] to override)", reach.describe(),
                        LIDAR_OUTDOOR_P99_RANGE_M, scale, scaled.voxel_size_m, scaled.min_range_m,
                        scaled.max_range_m, scaled.initial_threshold_m, scaled.min_motion_m)
        return scaled

    def to_kiss(self) -> KISSConfig:
        cfg = KISSConfig()
        cfg.data.max_range = self.max_range_m
        cfg.data.min_range = self.min_range_m
        cfg.data.deskew = self.deskew
        cfg.mapping.voxel_size = self.voxel_size_m
        cfg.mapping.max_points_per_voxel = self.max_points_per_voxel
        cfg.adaptive_threshold.initial_threshold = self.initial_threshold_m
        cfg.adaptive_threshold.min_motion_th = self.min_motion_m
        cfg.registration.max_num_threads = self.num_threads
        return cfg


def lidar_scene_scale(frame: Frame) -> tuple[float, float | None]:
    """``(scale, reach)`` of one LiDAR scan (:func:`driftmap.preprocess.scene.lidar_odometry_scale` of its
    :func:`~driftmap.preprocess.scene.scan_reach_m`); ``(1.0, None)`` for other sensors and empty scans."""
    if frame.sensor_kind is not SensorKind.LIDAR:
        return 1.0, None
    reach = scan_reach_m(frame)
    if reach is None:
        return 1.0, None
    return lidar_odometry_scale(reach), reach


def is_indoor_lidar(frame: Frame) -> bool:
    """A LiDAR scan that reaches less than :data:`LIDAR_OUTDOOR_P99_RANGE_M` (a room, a corridor)."""
    return lidar_scene_scale(frame)[0] < 1.0


KISS_LENGTHS = ("voxel_size_m", "min_range_m", "max_range_m", "initial_threshold_m", "min_motion_m")
"""The LiDAR defaults :meth:`OdometryConfig.for_frame` scales to the scene."""


PLANE_REFINE_SHARE_TOLERANCE = 0.05
"""``kiss_refine_plane``: refinements whose inlier share is within this of the best are equally good."""

REFINE_CORRESPONDENCE_VOXELS = 1.0
"""``kiss_refine_gicp``: GICP correspondences within this many odometry voxels."""

MIN_REGISTRATION_POINTS = 10
"""A scan (or depth frame) with fewer points than this after the odometry's voxel grid is not registered: its pose is
predicted (constant velocity) and it stays out of the map. One distinct point fits any surface perfectly (hostile
trial 25 B2: 87,000 copies of one point were tracked "ok" 1.4 m off)."""


@dataclass(frozen=True, slots=True)
class OdometryStep:
    frame_id: int
    T_world_sensor: NDArray[np.float64]
    n_points: int
    seconds: float
    health: TrackingHealth | None = None
    """How the registration went (:mod:`driftmap.registration.tracking`); None where it is not measured."""


def make_odometry(config: OdometryConfig, T_world_first: NDArray[np.float64] | None = None) -> KissOdometry | GicpMapOdometry:
    """The odometry ``config.method`` names."""
    if config.method is OdometryMethod.KISS:
        return KissOdometry(config, T_world_first)
    return GicpMapOdometry(config, T_world_first)


def _strided_points(frame: Frame, max_points: int | None) -> tuple[NDArray[np.float64], int]:
    step = 1
    if max_points is not None and frame.n_points > max_points:
        step = -(-frame.n_points // max_points)
    return frame.points_sensor[::step].astype(np.float64), step


def _nearest_rigid(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """Project the rotation block onto SO(3): chaining ``T_prev @ delta`` predictions otherwise lets round-off
    in the rotation grow from frame to frame."""
    out = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = U @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


class GicpMapOdometry:
    """Frame-to-map GICP odometry; poses start at ``T_world_first`` (identity by default).

    Each frame (points within ``min_range_m .. max_range_m``, voxel-downsampled) is registered with small_gicp
    VGICP to a Gaussian voxel map of all frames so far, starting from the constant-velocity prediction. If
    fewer than ``gicp_min_inlier_fraction`` of its points find a map correspondence (or during the first
    frames, before a velocity is known), a coarse registration against a coarse voxel map is tried first and
    kept when it ends with more inliers. The frame is then inserted into both maps at its new pose.
    """

    def __init__(self, config: OdometryConfig, T_world_first: NDArray[np.float64] | None = None):
        self.config = config
        self._T_world_first = np.eye(4) if T_world_first is None else np.array(geometry.as_rigid(T_world_first))
        self._fine = small_gicp.GaussianVoxelMap(config.gicp_map_voxel_m)
        self._coarse = small_gicp.GaussianVoxelMap(config.gicp_coarse_map_voxel_m)
        horizon = config.gicp_map_horizon_frames if config.gicp_map_horizon_frames is not None else 2**31 - 1
        for m in (self._fine, self._coarse):
            m.set_lru(horizon=horizon, clear_cycle=10)
        self._last: NDArray[np.float64] | None = None
        self._delta = np.eye(4)
        self.n_frames = 0
        self.seconds = 0.0
        self.n_coarse = 0
        self._last_hessian = np.zeros((6, 6))
        self._n_tracked = 0  # frames registered so far (while under 3, the coarse map is tried too)

    def _clouds(self, frame: Frame) -> tuple[small_gicp.PointCloud, small_gicp.PointCloud, int]:
        c = self.config
        pts, _ = _strided_points(frame, c.max_points)
        r = np.linalg.norm(pts, axis=1)
        pts = pts[(r >= c.min_range_m) & (r <= c.max_range_m)]
        if len(pts) == 0:  # small_gicp prints "warning: Empty point cloud" to the console for each
            empty = small_gicp.PointCloud(np.zeros((0, 3)))
            return empty, empty, 0
        fine, _ = small_gicp.preprocess_points(pts, downsampling_resolution=c.gicp_downsample_m, num_neighbors=10,
                                               num_threads=c.num_threads)
        coarse, _ = small_gicp.preprocess_points(pts, downsampling_resolution=c.gicp_coarse_downsample_m, num_neighbors=10,
                                                 num_threads=c.num_threads)
        return fine, coarse, len(pts)

    def _align(self, target: small_gicp.GaussianVoxelMap, source: small_gicp.PointCloud, init: NDArray[np.float64],
               max_correspondence_m: float) -> tuple[NDArray[np.float64], float, bool]:
        res = small_gicp.align(target, source, init, max_correspondence_distance=max_correspondence_m, num_threads=self.config.num_threads,
                               max_iterations=self.config.gicp_max_iterations)
        T = np.array(res.T_target_source)
        if not np.all(np.isfinite(T)):
            return init, 0.0, False
        self._last_hessian = np.asarray(res.H, dtype=np.float64)
        return _nearest_rigid(T), res.num_inliers / max(source.size(), 1), bool(res.converged)

    def register(self, frame: Frame) -> OdometryStep:
        t0 = time.perf_counter()
        fine, coarse, n_points = self._clouds(frame)
        c = self.config
        radius = c.gicp_max_correspondence_m
        if self._last is None and fine.size() >= MIN_REGISTRATION_POINTS:
            T = self._T_world_first.copy()
            health = TrackingHealth(TrackingStatus.FIRST, n_points=fine.size(), fitness_radius_m=radius, hypothesis="start")
        elif fine.size() < MIN_REGISTRATION_POINTS:  # the map does not start (or grow) with it
            started = self._last is not None
            reason = (f"{fine.size()} points within {c.min_range_m:.2f}..{c.max_range_m:.2f} m after the "
                      f"{c.gicp_downsample_m:g} m voxel grid ({n_points} measured): pose "
                      f"{'predicted' if started else 'of the start; the map begins at the next frame'}")
            logger.warning("frame %d: %s", frame.frame_id, reason)
            T = _nearest_rigid(self._last @ self._delta) if started else self._T_world_first.copy()
            health = TrackingHealth(TrackingStatus.LOST, n_points=fine.size(), fitness_radius_m=radius,
                                    hypothesis="constant_velocity" if started else "start", reason=reason)
            if started:  # as before trial 25: the frame counts among the tracked ones, its (few) points stay out
                self._last = T
                self._n_tracked += 1
            self.n_frames += 1
            self.seconds += time.perf_counter() - t0
            return OdometryStep(frame.frame_id, T, n_points, time.perf_counter() - t0, health)
        else:
            pred = _nearest_rigid(self._last @ self._delta)
            T, inliers, _ = self._align(self._fine, fine, pred, c.gicp_max_correspondence_m)
            hessian, hypothesis = self._last_hessian, "constant_velocity"
            if inliers < c.gicp_min_inlier_fraction or self._n_tracked < 3:
                T_coarse, _, _ = self._align(self._coarse, coarse, pred, c.gicp_coarse_max_correspondence_m)
                T2, inliers2, _ = self._align(self._fine, fine, T_coarse, c.gicp_max_correspondence_m)
                if inliers2 > inliers:
                    T, inliers = T2, inliers2
                    hessian, hypothesis = self._last_hessian, "coarse_map"
                    self.n_coarse += 1
            status, reason = TrackingStatus.OK, ""
            if inliers < c.gicp_min_inlier_fraction:
                status, reason = TrackingStatus.LOST, f"only {100 * inliers:.0f} % of the points match the map"
                logger.warning("frame %d: %s", frame.frame_id, reason)
            elif hypothesis != "constant_velocity" and self._n_tracked >= 3:
                status, reason = TrackingStatus.RECOVERED, "the coarse map's registration matches more points"
            if status is not TrackingStatus.LOST:
                T, status, reason = self._bridge_weak_directions(T, pred, hessian, status, reason, frame.frame_id)
            dev_m, dev_deg = tracking.deviation(pred, T)
            health = TrackingHealth(status, fitness=inliers, degeneracy=tracking.hessian_degeneracy(hessian),
                                    deviation_m=dev_m, deviation_deg=dev_deg, hypothesis=hypothesis,
                                    n_points=fine.size(), fitness_radius_m=radius, reason=reason)
            self._delta = geometry.invert(self._last) @ T
        self._insert(fine, coarse, T)
        self._n_tracked += 1
        dt = time.perf_counter() - t0
        self.n_frames += 1
        self.seconds += dt
        return OdometryStep(frame.frame_id, T, n_points, dt, health)

    def _bridge_weak_directions(self, T: NDArray[np.float64], predicted: NDArray[np.float64],
                                hessian: NDArray[np.float64], status: TrackingStatus, reason: str, frame_id: int
                                ) -> tuple[NDArray[np.float64], TrackingStatus, str]:
        """Along the directions the registration's translational Hessian leaves unconstrained
        (``tracking_degenerate_below``), a registration that moved more than ``gicp_degenerate_shift_m`` from the
        prediction keeps the prediction's translation (:func:`tracking.keep_prediction_along_weak_directions`) and the
        frame is reported ``degenerate`` (a recovered one keeps its status, with the reason added). Smaller moves stay:
        along a weak direction they are within what the correspondences can hold.

        Hostile trial 30 B2: on the default synthetic room log the first step (no velocity known yet) slid 21 cm along
        a bare wall (degeneracy 0.079; the true pose fit 0.839 of the points, the slid one 0.837) and every later frame
        followed it, all reported ok."""
        shift_m = self.config.gicp_degenerate_shift_m
        if shift_m is None:
            return T, status, reason
        bridged, weak = tracking.keep_prediction_along_weak_directions(T, predicted, hessian,
                                                                      self.config.tracking_degenerate_below)
        if weak is None or weak.replaced_m <= shift_m:
            return T, status, reason
        why = (f"the frame barely constrains motion along {weak.directions_text()} (world; degeneracy {weak.degeneracy:.3f} < "
               f"{self.config.tracking_degenerate_below:g}) and the registration moved {100 * weak.replaced_m:.1f} cm "
               f"along it from the prediction (more than {100 * shift_m:g} cm): the prediction's translation kept there")
        logger.warning("frame %d: %s", frame_id, why)
        return _nearest_rigid(bridged), *tracking.degenerate_status(status, reason, why)

    def _insert(self, fine: small_gicp.PointCloud, coarse: small_gicp.PointCloud, T: NDArray[np.float64]) -> None:
        self._fine.insert(fine, T)
        self._coarse.insert(coarse, T)
        self._last = T

    @property
    def fps(self) -> float:
        return self.n_frames / self.seconds if self.seconds > 0 else float("nan")


_kiss_threads_of_process: int | None = None
"""The thread limit of the first KISS-ICP odometry made in this process (see :class:`KissOdometry`)."""


class KissOdometry:
    """Register frames one after the other with KISS-ICP; poses start at ``T_world_first`` (identity by default).

    KISS-ICP (1.3.0) sets TBB's thread limit for the whole process when its first registration object is made,
    and keeps it: ``num_threads`` takes effect for the first KISS-ICP odometry of a process only (a later one that
    asks for another number says so in a warning). A one-thread, repeatable KISS-ICP run needs a process whose
    first KISS-ICP odometry has ``num_threads=1`` (``driftmap build --threads 1`` is one)."""

    def __init__(self, config: OdometryConfig, T_world_first: NDArray[np.float64] | None = None):
        global _kiss_threads_of_process
        if _kiss_threads_of_process is None:
            _kiss_threads_of_process = config.num_threads
        elif config.num_threads != _kiss_threads_of_process:
            logger.warning("KISS-ICP odometry with num_threads=%d: KISS-ICP's thread limit is process-wide and was set "
                           "to %d by the first KISS-ICP odometry of this process, so it stays %d (start a new process "
                           "for another limit)", config.num_threads, _kiss_threads_of_process, _kiss_threads_of_process)
        self.config = config
        self._kiss = KissICP(config.to_kiss())
        self._T_world_odom = np.eye(4) if T_world_first is None else np.array(geometry.as_rigid(T_world_first))
        self.n_frames = 0
        self.seconds = 0.0
        self._prev_scan: NDArray[np.float64] | None = None
        """The last scan's points, for the scan-to-scan GICP that restarts the motion model (``kiss_prime_motion``)."""
        self.primed_motion: NDArray[np.float64] | None = None
        """The first motion that started KISS-ICP's constant-velocity model (None: KISS-ICP's own zero start)."""
        self._recent_fitness: list[float] = []
        self._lost_in_a_row = 0
        self._last_stamp_ns: int | None = None

    def _points(self, frame: Frame) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        pts, step = _strided_points(frame, self.config.max_points)
        t = frame.attributes.time_offset_ns
        if t is not None:
            t = t[::step]
        if t is None or len(t) == 0 or np.ptp(t) == 0:
            stamps = np.zeros(len(pts))
        else:  # KISS-ICP wants per-point times normalised to [0, 1]
            stamps = (t - t.min()) / max(float(np.ptp(t)), 1.0)
        return pts, stamps

    def _checked_motion(self, frame_id: int) -> None:
        """KISS-ICP deskews with its last motion through Sophus, which aborts the process on a NaN or non-rigid one:
        such a motion model is reset to zero motion (logged) before it gets there."""
        d = self._kiss.last_delta
        ok = np.all(np.isfinite(d)) and abs(np.linalg.det(d[:3, :3]) - 1.0) < 1e-6 and np.allclose(d[3], (0, 0, 0, 1))
        if not ok:
            logger.warning("frame %d: the motion model is not a rigid motion (%s); it restarts from zero motion",
                           frame_id, "non-finite" if not np.all(np.isfinite(d)) else "not rigid")
            self._kiss.last_delta = np.eye(4)
        else:
            self._kiss.last_delta = _nearest_rigid(d)

    def _standing(self) -> bool:
        """The motion model says the sensor stands (or has not moved yet): under half a voxel and 2 deg per scan."""
        d = self._kiss.last_delta
        return (float(np.linalg.norm(d[:3, 3])) < 0.5 * self.config.voxel_size_m
                and geometry.rotation_angle_deg(np.eye(4), d) < 2.0)

    def _prime(self, first: NDArray[np.float64], second: NDArray[np.float64], frame_id: int) -> None:
        """Start KISS-ICP's constant-velocity model with the motion between the last two scans, when it says the
        sensor stands: at the start of a log, and after every stop.

        KISS-ICP predicts each scan's pose from the last motion, which is zero for the second scan and after a
        stop. A LiDAR that is already moving (a car at 10 m/s, 1 m per scan) then starts from 1 m off, and with a
        local map whose rings repeat in the next scan wherever the sensor is, its ICP stops short: 0.44 m of 1.0 m on
        the synthetic street log, an error every later pose keeps (and 23 standing scans before the car drives
        off, 17 cm ATE against 9). A two-stage GICP of the two scans (the odometry voxel, then half of it) measures
        the motion instead; it is used when it converged, overlaps (fitness >= 0.3) and is at least half a voxel or
        5 deg (a slower start is within what KISS-ICP's own ICP recovers, and is left to it)."""
        v = self.config.voxel_size_m
        threads = self.config.num_threads
        first, second = (p[(np.einsum("ij,ij->i", p, p) >= self.config.min_range_m**2)
                           & (np.einsum("ij,ij->i", p, p) <= self.config.max_range_m**2)] for p in (first, second))
        coarse = register(first, second, np.eye(4), voxel_size_m=v, max_correspondence_m=5 * v, num_threads=threads)
        fine = register(first, second, coarse.T_target_source, voxel_size_m=0.5 * v, max_correspondence_m=1.25 * v,
                        num_threads=threads)
        moved_m = float(np.linalg.norm(fine.T_target_source[:3, 3]))
        turned_deg = geometry.rotation_angle_deg(np.eye(4), fine.T_target_source)
        if fine.converged and fine.fitness >= 0.3 and (moved_m >= 0.5 * v or turned_deg >= 5.0):
            self._kiss.last_delta = fine.T_target_source
            if self.primed_motion is None:
                self.primed_motion = fine.T_target_source
            logger.info("KISS-ICP motion model started from GICP of the last two scans: %.2f m / %.1f deg to frame "
                        "%d (fitness %.2f)", moved_m, turned_deg, frame_id, fine.fitness)
        else:
            logger.debug("KISS-ICP motion model stays at zero (motion to frame %d %.3f m, fitness %.2f, converged %s)",
                         frame_id, moved_m, fine.fitness, fine.converged)

    def _policy(self) -> tracking.RetryPolicy:
        c = self.config
        return tracking.RetryPolicy(
            min_fitness=c.tracking_min_fitness, retry_fitness_ratio=c.tracking_retry_fitness_ratio,
            min_gain=c.tracking_min_gain,
            yaw_deg=tuple(c.tracking_yaw_hypotheses_deg), up_axis=tracking.UP_AXIS_LIDAR, retry=c.tracking_retry,
            deviation_m=c.tracking_check_deviation_voxels * c.voxel_size_m, deviation_deg=c.tracking_check_deviation_deg)

    def register(self, frame: Frame) -> OdometryStep:
        """Register one scan to KISS-ICP's local map (KISS-ICP's own steps: deskew with the last motion, voxelise,
        ICP from the constant-velocity prediction with the adaptive threshold, map update) with the health check
        and retry of :mod:`driftmap.registration.tracking` around the ICP."""
        t0 = time.perf_counter()
        pts, stamps = self._points(frame)
        if self.config.kiss_prime_motion:
            if self._prev_scan is not None and self._standing():
                self._prime(self._prev_scan, pts, frame.frame_id)
            self._prev_scan = pts
        kiss, c = self._kiss, self.config
        self._checked_motion(frame.frame_id)
        scan = kiss.preprocessor.preprocess(pts, stamps, kiss.last_delta)
        source, scan_down = kiss.voxelize(scan)
        radius = c.tracking_fitness_radius_voxels * c.voxel_size_m
        if len(source) < MIN_REGISTRATION_POINTS:
            health, T = self._predicted(frame.frame_id, len(source), len(pts), radius)
        elif kiss.local_map.empty():
            T = kiss.last_pose
            health = TrackingHealth(TrackingStatus.FIRST, n_points=len(source), fitness_radius_m=radius,
                                    hypothesis="start")
            self._insert(scan_down, T, T)
        else:
            health, T = self._track(frame, source, scan_down, radius)
        dt = time.perf_counter() - t0
        self.n_frames += 1
        self.seconds += dt
        T_stamp = self._at_stamp(frame, T)
        self._last_stamp_ns = frame.stamp_ns
        return OdometryStep(frame.frame_id, self._T_world_odom @ T_stamp, len(pts), dt, health)

    def _predicted(self, frame_id: int, n_source: int, n_points: int, radius: float
                   ) -> tuple[TrackingHealth, NDArray[np.float64]]:
        """A scan with too few distinct points to register (:data:`MIN_REGISTRATION_POINTS`): the constant-velocity
        pose (the start pose before the map has begun), the scan kept out of the map, the motion model unchanged."""
        kiss, c = self._kiss, self.config
        started = not kiss.local_map.empty()
        T = _nearest_rigid(kiss.last_pose @ kiss.last_delta) if started else kiss.last_pose
        reason = (f"{n_source} points within {c.min_range_m:.2f}..{c.max_range_m:.2f} m after the {c.voxel_size_m:g} m "
                  f"voxel grid ({n_points} measured): pose {'predicted' if started else 'of the start; the map begins at the next scan'}")
        logger.warning("frame %d: %s", frame_id, reason)
        kiss.last_pose = T
        return TrackingHealth(TrackingStatus.LOST, n_points=n_source, fitness_radius_m=radius,
                              hypothesis="constant_velocity" if started else "start", reason=reason), T

    def _at_stamp(self, frame: Frame, T_mid: NDArray[np.float64]) -> NDArray[np.float64]:
        """KISS-ICP's pose of a scan with per-point times is the pose at the middle of its times (it deskews about
        it, and an undeskewed scan fits there best); the stored pose is the one at the frame's stamp, the map view's
        convention (:mod:`driftmap.preprocess.deskew`): moved back along the motion model by the middle's offset."""
        t = frame.attributes.time_offset_ns
        if t is None or len(t) == 0 or self._last_stamp_ns is None:
            return T_mid
        dt_ns = frame.stamp_ns - self._last_stamp_ns
        mid_ns = 0.5 * (float(t.min()) + float(t.max()))
        if dt_ns <= 0 or mid_ns == 0:
            return T_mid
        return T_mid @ geometry.se3_exp(-(mid_ns / dt_ns) * geometry.se3_log(self._kiss.last_delta))

    def _track(self, frame: Frame, source: NDArray[np.float64], scan_down: NDArray[np.float64],
               radius: float) -> tuple[TrackingHealth, NDArray[np.float64]]:
        kiss, c = self._kiss, self.config
        sigma = kiss.adaptive_threshold.get_threshold()
        map_points = kiss.local_map.point_cloud()
        tree = small_gicp.KdTree(map_points, num_threads=c.num_threads)

        def align(guess: NDArray[np.float64]) -> NDArray[np.float64]:
            return kiss.registration.align_points_to_map(points=source, voxel_map=kiss.local_map, initial_guess=guess,
                                                         max_correspondance_distance=3 * sigma, kernel=sigma)


        def evaluate(T: NDArray[np.float64], with_degeneracy: bool = False) -> tracking.MapFit:
            return tracking.fit_to_map(geometry.transform_points(T, source).astype(np.float64), map_points, tree,
                                       radius, with_degeneracy=with_degeneracy, num_threads=c.num_threads)

        attempt, status, reason, dev_m, dev_deg = tracking.register_robustly(
            align, evaluate, kiss.last_pose, kiss.last_delta, self._recent_fitness, self._policy(), frame_id=frame.frame_id)
        if c.kiss_refine_gicp and status is not TrackingStatus.LOST:
            attempt = self._refine(attempt, scan_down, map_points, evaluate)
        plane_degeneracy = None
        if c.kiss_refine_plane and status is not TrackingStatus.LOST:
            predicted = kiss.last_pose @ kiss.last_delta
            attempt, hessian = self._refine_plane(attempt, scan_down, map_points, predicted, evaluate)
            if hessian is not None:
                plane_degeneracy = tracking.hessian_degeneracy(hessian)
                attempt, status, reason = self._bridge_weak_directions(attempt, hessian, predicted, status, reason,
                                                                       frame.frame_id, evaluate)
        T = attempt.T_world_sensor
        degeneracy = plane_degeneracy if plane_degeneracy is not None else evaluate(T, with_degeneracy=True).degeneracy
        if status is TrackingStatus.LOST:
            self._lost_in_a_row += 1
            if self._lost_in_a_row > c.tracking_max_lost_frames:
                status = TrackingStatus.REINITIALISED
                reason = (f"{self._lost_in_a_row} frames in a row lost: the local map restarts here at the bridged "
                          f"pose ({reason})")
                logger.warning("frame %d: %s", frame.frame_id, reason)
                kiss.local_map.clear()
                self._recent_fitness.clear()
                self._lost_in_a_row = 0
                self._insert(scan_down, None, T)
            else:  # bridged: the pose of the best guess, the scan kept out of the map
                kiss.last_delta = geometry.invert(kiss.last_pose) @ T
                kiss.last_pose = T
        else:
            self._lost_in_a_row = 0
            self._recent_fitness = [*self._recent_fitness[-9:], attempt.fit.fitness]
            # a recovered frame's deviation from the prediction is not the motion model's ordinary error: learnt by
            # the adaptive threshold, one 40 deg turn that stopped would blur every later registration
            self._insert(scan_down, attempt.T_init if status in (TrackingStatus.OK, TrackingStatus.DEGENERATE) else None, T)
        return tracking.health(attempt, status, reason, dev_m, dev_deg, len(source), radius, degeneracy), T

    def _half_voxel_clouds(self, scan_down: NDArray[np.float64], map_points: NDArray[np.float64]
                           ) -> tuple[small_gicp.PointCloud, small_gicp.KdTree, small_gicp.PointCloud] | None:
        """``(local map, its KD-tree, scan)`` at half the odometry voxel with normals and covariances of 10
        neighbours, for the refinements; None when either has fewer than 10 points."""
        v, threads = self.config.voxel_size_m, self.config.num_threads
        target, tree = small_gicp.preprocess_points(map_points, downsampling_resolution=0.5 * v, num_neighbors=10,
                                                    num_threads=threads)
        source, _ = small_gicp.preprocess_points(scan_down, downsampling_resolution=0.5 * v, num_neighbors=10,
                                                 num_threads=threads)
        if target.size() < 10 or source.size() < 10:
            return None
        return target, tree, source

    def _refine_plane(self, attempt: tracking.Attempt, scan_down: NDArray[np.float64], map_points: NDArray[np.float64],
                      predicted: NDArray[np.float64],
                      evaluate: Callable[[NDArray[np.float64]], tracking.MapFit]
                      ) -> tuple[tracking.Attempt, NDArray[np.float64] | None]:
        """Point-to-plane ICP (small_gicp ``PLANE_ICP``; the local map at half the voxel, its normals from 10
        neighbours) of the scan from the kept registration and from the constant-velocity ``predicted`` pose; of the
        converged ones whose inlier share is within :data:`PLANE_REFINE_SHARE_TOLERANCE` of the best, the one nearest
        the prediction replaces the registration (unless it would fit less than ``tracking_min_fitness`` where the
        registration did not). Returns the attempt and the kept refinement's Hessian (None when it was not kept).

        KISS-ICP's point-to-point ICP is biased on the few hundred points a downsampled scan of a forward-looking
        (non-repetitive, Livox-like) scanner keeps: most lie on one surface and the in-plane pulls of mismatched
        samples point the same way (around a spinning sensor they cancel); the map's normals remove the in-plane
        pull. Two starts, because from KISS-ICP's result the refinement stays in its minimum where a surface leaves
        one direction weak. Measured (odometry ATE, cm, without / with; docs/build.md): synthetic street rosette 548 /
        8.5, room rosette 74 / 55, spinning street 9.1 / 1.1, spinning room 0.33 / 0.32, the real Livox log 2.25 /
        1.55, KITTI 00 0-15 36.4 / 37.0, at 1.5-3x the odometry time."""
        v, threads = self.config.voxel_size_m, self.config.num_threads
        clouds = self._half_voxel_clouds(scan_down, map_points)
        if clouds is None:
            return attempt, None
        target, tree, source = clouds
        found = []
        for start in (attempt.T_world_sensor, predicted):
            res = small_gicp.align(target, source, tree, start, registration_type="PLANE_ICP",
                                   max_correspondence_distance=REFINE_CORRESPONDENCE_VOXELS * v, num_threads=threads)
            T = np.array(res.T_target_source)
            if res.converged and np.all(np.isfinite(T)):
                found.append((res.num_inliers / source.size(), _nearest_rigid(T), np.asarray(res.H, dtype=np.float64)))
        if not found:
            return attempt, None
        best_share = max(share for share, _, _ in found)
        T, H = min(((T, H) for share, T, H in found if share >= best_share - PLANE_REFINE_SHARE_TOLERANCE),
                   key=lambda TH: tracking.deviation(predicted, TH[0])[0])
        refined = tracking.Attempt(attempt.hypothesis, attempt.T_init, T, evaluate(T))
        min_fitness = self.config.tracking_min_fitness
        if refined.fit.fitness < min_fitness <= attempt.fit.fitness:
            return attempt, None
        return refined, H

    def _bridge_weak_directions(self, attempt: tracking.Attempt, hessian: NDArray[np.float64],
                                predicted: NDArray[np.float64], status: TrackingStatus, reason: str, frame_id: int,
                                evaluate: Callable[[NDArray[np.float64]], tracking.MapFit]
                                ) -> tuple[tracking.Attempt, TrackingStatus, str]:
        """Along the directions the point-to-plane refinement leaves unconstrained (``tracking_degenerate_below``),
        the prediction's translation replaces the registration's (:func:`tracking.keep_prediction_along_weak_directions`);
        the frame is then reported ``degenerate`` (a recovered one keeps its status, with the reason added).

        Facing one wall with a 70 deg field of view, a synthetic rosette scan's point-to-plane minimum lay 25 cm
        sideways from the truth (registered from the truth itself: the map cannot tell), and each such scan pushed the
        next along: four scans took the room's odometry from 1 to 38 cm ATE (2.2 cm with this bridge)."""
        T, weak = tracking.keep_prediction_along_weak_directions(attempt.T_world_sensor, predicted, hessian,
                                                                 self.config.tracking_degenerate_below)
        if weak is None:
            return attempt, status, reason
        why = (f"the scan barely constrains motion along {weak.directions_text()} (world; degeneracy {weak.degeneracy:.3f} < "
               f"{self.config.tracking_degenerate_below:g}): {100 * weak.replaced_m:.1f} cm of the registration along "
               f"it replaced by the prediction")
        logger.info("frame %d: %s", frame_id, why)
        bridged = tracking.Attempt(attempt.hypothesis, attempt.T_init, T, evaluate(T))
        return bridged, *tracking.degenerate_status(status, reason, why)

    def _refine(self, attempt: tracking.Attempt, scan_down: NDArray[np.float64], map_points: NDArray[np.float64],
                evaluate: Callable[[NDArray[np.float64]], tracking.MapFit]) -> tracking.Attempt:
        """GICP (small_gicp: point-to-distribution, covariances of 10 neighbours) of the scan at half the voxel against
        KISS-ICP's local map, from KISS-ICP's pose; kept when it converged and fits as well (within ``tracking_min_gain``).
        Point-to-point ICP stops where few scan points fall near map points: from the true pose on a true map, a
        synthetic rosette street scan moved 4.8 cm (median), GICP 0.4 cm. Measured with / without it (docs/build.md):
        the synthetic street's odometry ATE 0.22 / 9.1 cm, the real Livox log's 1.6 / 2.2 cm, KITTI 00 0-15 0.38 /
        0.36 m, the room LiDAR 0.32 / 0.34 cm, at 1.5-2x the odometry time."""
        v, threads = self.config.voxel_size_m, self.config.num_threads
        clouds = self._half_voxel_clouds(scan_down, map_points)
        if clouds is None:
            return attempt
        target, tree, source = clouds
        res = small_gicp.align(target, source, tree, attempt.T_world_sensor,
                               max_correspondence_distance=REFINE_CORRESPONDENCE_VOXELS * v, num_threads=threads)
        T = np.array(res.T_target_source)
        if not res.converged or not np.all(np.isfinite(T)):
            return attempt
        refined = tracking.Attempt(attempt.hypothesis, attempt.T_init, _nearest_rigid(T), evaluate(_nearest_rigid(T)))
        return refined if refined.fit.fitness >= attempt.fit.fitness - self.config.tracking_min_gain else attempt

    def _insert(self, scan_down: NDArray[np.float64], T_init: NDArray[np.float64] | None, T: NDArray[np.float64]) -> None:
        """KISS-ICP's update step: the adaptive threshold learns the registration's deviation from the guess it
        started from (not with ``T_init`` None), the scan joins the local map, the motion model takes the last
        motion."""
        kiss = self._kiss
        if T_init is not None:
            kiss.adaptive_threshold.update_model_deviation(geometry.invert(T_init) @ T)
        kiss.local_map.update(scan_down, T)
        kiss.last_delta = geometry.invert(kiss.last_pose) @ T
        kiss.last_pose = T

    @property
    def fps(self) -> float:
        return self.n_frames / self.seconds if self.seconds > 0 else float("nan")
