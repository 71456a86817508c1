"""One frame as the volumetric layers see it: the rays from its sensor origin to its points in the world frame of a
revision, which of them end in a hit, and for a depth camera the depth image the points came from.

Only what a sensor measured becomes a ray: a stored frame holds its valid points only, so invalid depth pixels and
LiDAR beams without a return carve nothing (the store keeps no ray for them); a point closer than ``min_range_m``
to its sensor (e.g. at the camera origin) is no observation; a point beyond ``max_range_m`` carves free space up to
that range and marks no hit (OctoMap's ``maxrange``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import ConfigError
from driftmap.frame import Frame, SensorKind
from driftmap.volume.config import VolumeConfig


@dataclass(frozen=True)
class Observation:
    """The rays of one frame in the world frame of one revision (metres)."""

    frame_id: int
    origin_m: NDArray[np.float64]
    """the sensor origin (3,)"""
    ends_m: NDArray[np.float64]
    """(N, 3) ray ends: the points, or the point where a ray beyond the max range was cut"""
    is_hit: NDArray[np.bool_]
    """(N,) the ray ends in a measured point (False: cut at the max range, it carves only)"""
    T_world_sensor: NDArray[np.float64]
    depth_m: NDArray[np.float32] | None = None
    """a depth camera's depth image (H, W) at the frame's intrinsics, metres, 0 where there is no point"""
    intrinsics: tuple[float, float, float, float] | None = None
    """``(fx, fy, cx, cy)`` of ``depth_m``"""

    @property
    def bounds_m(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The box of the origin and every ray end (column by column: no copy of the ends)."""
        if len(self.ends_m) == 0:
            return self.origin_m.copy(), self.origin_m.copy()
        lo = np.array([min(self.ends_m[:, k].min(), self.origin_m[k]) for k in range(3)])
        hi = np.array([max(self.ends_m[:, k].max(), self.origin_m[k]) for k in range(3)])
        return lo, hi


def observe(frame: Frame, T_world_sensor: NDArray[np.float64], points_world_m: NDArray[np.floating] | None,
            config: VolumeConfig) -> Observation:
    """The :class:`Observation` of ``frame`` placed at ``T_world_sensor`` (``points_world_m``: its points as the map
    view places them, deskewed where the frame has point times; None: ``T_world_sensor`` applied to them).
    ``config`` must be :meth:`~VolumeConfig.resolved` (a max range may still be None: no ray is cut)."""
    pts_s = np.asarray(frame.points_sensor, dtype=np.float64)
    world = (geometry.transform_points(T_world_sensor, pts_s) if points_world_m is None
             else np.asarray(points_world_m, dtype=np.float64))
    r = np.linalg.norm(pts_s, axis=1)
    keep = np.isfinite(r) & np.all(np.isfinite(world), axis=1) & (r >= config.min_range_m)
    origin = np.asarray(T_world_sensor, dtype=np.float64)[:3, 3].copy()
    ends, r = world[keep], r[keep]
    is_hit = np.ones(len(ends), dtype=bool)
    if config.max_range_m is not None:
        far = r > config.max_range_m
        if far.any():
            ends = ends.copy()
            ends[far] = origin + (ends[far] - origin) * (config.max_range_m / r[far])[:, None]
            is_hit[far] = False
    depth, intr = None, None
    if frame.sensor_kind is SensorKind.DEPTH_CAMERA:
        if frame.intrinsics is None:
            raise ConfigError(f"frame {frame.frame_id}: a depth camera's frame without intrinsics: its TSDF projects "
                              f"into the depth image the points came from (a source that stores intrinsics, or --intrinsics)")
        depth, intr = depth_image(frame, pts_s[keep])
    return Observation(int(frame.frame_id), origin, ends, is_hit, np.asarray(T_world_sensor, dtype=np.float64),
                       depth, intr)


def depth_image(frame: Frame, points_sensor: NDArray[np.float64]) -> tuple[NDArray[np.float32], tuple[float, float, float, float]]:
    """The depth image ``points_sensor`` (back-projected from the frame's pixels) came from: each point projected
    with the frame's intrinsics lands on its pixel; ``(depth (H, W) float32 metres, (fx, fy, cx, cy))``."""
    K = frame.intrinsics
    assert K is not None
    depth = np.zeros((K.height, K.width), dtype=np.float32)
    z = points_sensor[:, 2]
    front = z > 0
    u = np.rint(K.fx * points_sensor[front, 0] / z[front] + K.cx).astype(np.int64)
    v = np.rint(K.fy * points_sensor[front, 1] / z[front] + K.cy).astype(np.int64)
    inside = (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    depth[v[inside], u[inside]] = z[front][inside]
    return depth, (float(K.fx), float(K.fy), float(K.cx), float(K.cy))
