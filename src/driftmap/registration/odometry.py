"""Frame-to-map odometry with KISS-ICP (thin wrapper).

KISS-ICP estimates ``T_world_sensor`` of each frame by registering it to a local voxel map. The wrapper
picks settings per sensor kind (indoor RGB-D vs. LiDAR), feeds driftmap frames, times each step, and can
be re-seeded from stored frames and poses so that ``build --resume`` continues where a build stopped.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from driftmap import geometry
from driftmap.frame import Frame, SensorKind

logger = logging.getLogger(__name__)


class OdometryConfig(BaseModel):
    """KISS-ICP settings, in metres."""

    model_config = ConfigDict(extra="forbid")
    voxel_size_m: float = Field(0.08, gt=0.0, description="KISS-ICP map voxel size (m)")
    max_points: int | None = Field(20_000, ge=100, description="register at most about this many points per frame (every k-th point); None: all")
    min_range_m: float = Field(0.2, ge=0.0, description="points closer than this are ignored (m)")
    max_range_m: float = Field(4.0, gt=0.0, description="points farther than this are ignored (m)")
    deskew: bool = Field(False, description="motion-compensate scans with per-point time (LiDAR)")
    initial_threshold_m: float = Field(0.3, gt=0.0, description="initial correspondence threshold (m)")
    min_motion_m: float = Field(0.01, ge=0.0, description="motion below which the adaptive threshold is not updated (m)")
    max_points_per_voxel: int = Field(20, ge=1, description="points kept per map voxel")

    @classmethod
    def for_sensor(cls, kind: SensorKind) -> OdometryConfig:
        """Defaults that suit indoor RGB-D (8 cm voxels, 0.2..4 m, ~20k points per frame) or outdoor LiDAR
        (KISS-ICP's own, every point)."""
        if kind is SensorKind.LIDAR:
            return cls(voxel_size_m=1.0, min_range_m=0.5, max_range_m=100.0, deskew=False, initial_threshold_m=2.0,
                       min_motion_m=0.1, max_points=None)
        return cls()

    def to_kiss(self) -> KISSConfig:
        cfg = KISSConfig()
        cfg.data.max_range = self.max_range_m
        cfg.data.min_range = self.min_range_m
        cfg.data.deskew = self.deskew
        cfg.mapping.voxel_size = self.voxel_size_m
        cfg.mapping.max_points_per_voxel = self.max_points_per_voxel
        cfg.adaptive_threshold.initial_threshold = self.initial_threshold_m
        cfg.adaptive_threshold.min_motion_th = self.min_motion_m
        return cfg


@dataclass(frozen=True, slots=True)
class OdometryStep:
    frame_id: int
    T_world_sensor: NDArray[np.float64]
    n_points: int
    seconds: float


class KissOdometry:
    """Register frames one after the other; poses start at ``T_world_first`` (identity by default)."""

    def __init__(self, config: OdometryConfig, T_world_first: NDArray[np.float64] | None = None):
        self.config = config
        self._kiss = KissICP(config.to_kiss())
        self._T_world_odom = np.eye(4) if T_world_first is None else geometry.as_rigid(T_world_first).copy()
        self.n_frames = 0
        self.seconds = 0.0

    def _points(self, frame: Frame) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        step = 1
        if self.config.max_points is not None and frame.n_points > self.config.max_points:
            step = -(-frame.n_points // self.config.max_points)
        pts = frame.points_sensor[::step].astype(np.float64)
        t = frame.attributes.time_offset_ns
        if t is not None:
            t = t[::step]
        if t is None or len(t) == 0 or np.ptp(t) == 0:
            stamps = np.zeros(len(pts))
        else:  # KISS-ICP wants per-point times normalised to [0, 1]
            stamps = (t - t.min()) / max(float(np.ptp(t)), 1.0)
        return pts, stamps

    def register(self, frame: Frame) -> OdometryStep:
        t0 = time.perf_counter()
        pts, stamps = self._points(frame)
        self._kiss.register_frame(pts, stamps)
        dt = time.perf_counter() - t0
        self.n_frames += 1
        self.seconds += dt
        T = self._T_world_odom @ self._kiss.last_pose
        return OdometryStep(frame.frame_id, T, len(pts), dt)

    def seed(self, frames_with_poses: Iterable[tuple[Frame, NDArray[np.float64]]]) -> None:
        """Rebuild the local map and motion model from frames already registered (for ``--resume``).

        ``frames_with_poses`` are the last frames in order with their stored ``T_world_sensor``.
        """
        items = list(frames_with_poses)
        if not items:
            return
        T0 = items[0][1]
        self._T_world_odom = T0.copy()
        kiss = self._kiss
        prev = None
        for frame, T in items:
            pts, _ = self._points(frame)
            pose = geometry.invert(T0) @ T
            _, frame_down = kiss.voxelize(kiss.preprocessor.preprocess(pts, np.zeros(len(pts)), np.eye(4)))
            kiss.local_map.update(frame_down, pose)
            if prev is not None:
                kiss.last_delta = geometry.invert(prev) @ pose
            kiss.last_pose = pose
            prev = pose
        logger.info("odometry re-seeded from %d stored frames", len(items))

    @property
    def fps(self) -> float:
        return self.n_frames / self.seconds if self.seconds > 0 else float("nan")
