"""The synthetic LiDARs: a spinning multi-beam scanner and a non-repetitive rosette scanner, with per-point times.

Each scan is a set of rays in the LiDAR frame (x forward, z up) with a capture time each (:func:`lidar_rays`):

- ``spinning``: ``lidar_beams`` rings from ``lidar_elevation_deg[0]`` to ``[1]`` times ``lidar_azimuth_steps``
  azimuths, beam by beam; a point's time grows with its azimuth (one turn per scan, counter-clockwise from +x).
- ``rosette`` (a Livox Avia / Mid-70 like scanner): ``lidar_points_per_scan`` points along the rose curve
  ``rho = (lidar_fov_deg / 2) cos(k theta)``, ``k = lidar_rosette_k``, where ``rho`` is the angle from the x axis
  and ``theta`` the direction round it. ``theta`` grows uniformly in time, one turn per scan, and continues from
  scan to scan (scan ``j`` covers ``theta`` in ``[2 pi j, 2 pi (j + 1))``); as ``k`` is not a whole number the
  petals of each scan fall between those of the scans before, so the field of view fills up with integration
  time. A point's time grows with its position along the curve.

A point's capture time is ``stamp_ns + time_offset_ns``, the stamp being the scan's start; offsets lie in
``[0, frame_period_ns)``.
"""

from __future__ import annotations

import enum
import math
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

SyntheticLogConfig = Any
"""A :class:`driftmap.sources.synthetic.SyntheticLogConfig` (not imported here: that module imports this one)."""


class LidarPattern(str, enum.Enum):
    """How the synthetic LiDAR scans."""

    SPINNING = "spinning"
    ROSETTE = "rosette"


def lidar_rays(config: SyntheticLogConfig, scan_index: int = 0) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The rays of scan ``scan_index`` in the LiDAR frame, unit vectors (N, 3), and each ray's capture time after
    the scan's stamp (N,) int64 ns, in ``[0, frame_period_ns)``."""
    period = np.int64(config.frame_period_ns)
    if config.lidar_pattern == LidarPattern.ROSETTE:
        n = int(config.lidar_points_per_scan)
        i = np.arange(n, dtype=np.int64)
        theta = 2.0 * math.pi * (scan_index + i / n)
        rho = math.radians(config.lidar_fov_deg / 2.0) * np.cos(config.lidar_rosette_k * theta)
        dirs = np.stack([np.cos(rho), np.sin(rho) * np.cos(theta), np.sin(rho) * np.sin(theta)], axis=-1)
        return dirs, i * period // n
    elev = np.radians(np.linspace(*config.lidar_elevation_deg, config.lidar_beams))
    azim = np.linspace(0.0, 2 * math.pi, config.lidar_azimuth_steps, endpoint=False)
    ee, aa = np.meshgrid(elev, azim, indexing="ij")
    dirs = np.stack([np.cos(ee) * np.cos(aa), np.cos(ee) * np.sin(aa), np.sin(ee)], axis=-1).reshape(-1, 3)
    steps = np.int64(config.lidar_azimuth_steps)
    azimuth_index = np.tile(np.arange(config.lidar_azimuth_steps, dtype=np.int64), config.lidar_beams)
    return dirs, azimuth_index * period // steps


def cast_lidar(
    scene: o3d.t.geometry.RaycastingScene,
    T_world_lidar: NDArray[np.float64],
    dirs_l: NDArray[np.float64],
    config: SyntheticLogConfig,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Cast ``dirs_l`` (LiDAR frame) into the scene: the returns as (M, 4) float32 x, y, z, intensity in the LiDAR
    frame (range noise ``lidar_range_sigma_m``, nothing beyond ``lidar_max_range_m``), and which rays returned.

    ``T_world_lidar`` is one pose (4, 4) for the whole scan, or one per ray (N, 4, 4): the pose each ray was cast
    from (a moving sensor); every point is then in the LiDAR frame of its own instant."""
    if T_world_lidar.ndim == 2:
        dirs_w = dirs_l @ T_world_lidar[:3, :3].T
        origins = np.broadcast_to(T_world_lidar[:3, 3], dirs_w.shape)
    else:
        dirs_w = np.einsum("nij,nj->ni", T_world_lidar[:, :3, :3], dirs_l)
        origins = T_world_lidar[:, :3, 3]
    ans = scene.cast_rays(o3d.core.Tensor(np.hstack([origins, dirs_w]).astype(np.float32)))
    r = ans["t_hit"].numpy().astype(np.float64)
    ok = np.isfinite(r) & (r < config.lidar_max_range_m)
    normals = ans["primitive_normals"].numpy()
    r_noisy = r + rng.normal(0.0, config.lidar_range_sigma_m, r.shape)
    pts = dirs_l[ok] * r_noisy[ok, None]
    intensity = np.abs(np.einsum("ij,ij->i", normals[ok], dirs_w[ok]))
    return np.hstack([pts, intensity[:, None]]).astype(np.float32), ok
