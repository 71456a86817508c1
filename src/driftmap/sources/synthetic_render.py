"""How the synthetic log's sensors see its scene: where the depth camera and the LiDAR sit on the robot, a noisy
Kinect-like depth image, a LiDAR scan (:mod:`driftmap.sources.synthetic`)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.sources.synthetic_config import SyntheticLogConfig
from driftmap.sources.synthetic_lidar import cast_lidar, lidar_rays
from driftmap.sources.synthetic_motion import MotionSchedule, base_poses_at


def T_base_camera(config: SyntheticLogConfig) -> NDArray[np.float64]:
    """Depth camera (optical frame: x right, y down, z forward) on the robot base (x forward, z up)."""
    R_base_optical = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R_pitch = Rotation.from_euler("y", config.camera_pitch_down_deg, degrees=True).as_matrix()
    return geometry.make_transform(R_pitch @ R_base_optical, (0.1, 0.0, config.camera_height_m))


def T_base_lidar(config: SyntheticLogConfig) -> NDArray[np.float64]:
    """LiDAR frame (x forward, z up) on the robot base: 1.3 m up in the room, 1.73 m (KITTI's) on the street."""
    return geometry.make_transform(None, (0.0, 0.0, 1.73 if config.scene == "street" else 1.3))


def _camera_rays(config: SyntheticLogConfig) -> NDArray[np.float64]:
    u, v = np.meshgrid(np.arange(config.width, dtype=np.float64), np.arange(config.height, dtype=np.float64))
    return np.stack([(u - config.cx) / config.fx, (v - config.cy) / config.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)


def render_depth(
    scene: o3d.t.geometry.RaycastingScene,
    glass_ids: set[int],
    T_world_camera: NDArray[np.float64],
    config: SyntheticLogConfig,
    rng: np.random.Generator,
) -> NDArray[np.uint16]:
    """One noisy uint16 depth image (``config.depth_scale`` units per metre, 0 = no reading)."""
    rays_cam = _camera_rays(config)
    dirs = rays_cam @ T_world_camera[:3, :3].T  # z-component 1 in the camera => t_hit is the depth z
    origins = np.broadcast_to(T_world_camera[:3, 3], dirs.shape)
    ans = scene.cast_rays(o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32)))
    z = ans["t_hit"].numpy().astype(np.float64)
    gid = ans["geometry_ids"].numpy()
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    noisy = z + rng.normal(0.0, 1.0, z.shape) * np.where(np.isfinite(sigma), sigma, 0.0)
    invalid = ~np.isfinite(z) | (z > config.max_range_m) | (rng.random(z.shape) < config.dropout_fraction)
    for g in glass_ids:
        invalid |= gid == g
    codes = np.where(invalid, 0.0, np.rint(noisy * config.depth_scale))
    return np.clip(codes, 0, 65534).astype(np.uint16).reshape(config.height, config.width)


def render_lidar(
    scene: o3d.t.geometry.RaycastingScene,
    T_world_lidar: NDArray[np.float64],
    config: SyntheticLogConfig,
    rng: np.random.Generator,
    *,
    scan_index: int = 0,
) -> NDArray[np.float32]:
    """One LiDAR scan in the LiDAR frame: (N, 4) float32 x, y, z, intensity, of ``config.lidar_pattern`` (the
    rosette's part of the pattern depends on ``scan_index``), seen from one pose ``T_world_lidar`` (4, 4) or from
    one pose per ray of :func:`~driftmap.sources.synthetic_lidar.lidar_rays` (N, 4, 4)."""
    dirs_l, _ = lidar_rays(config, scan_index)
    return cast_lidar(scene, T_world_lidar, dirs_l, config, rng)[0]


def render_scan(scene: o3d.t.geometry.RaycastingScene, config: SyntheticLogConfig, schedule: MotionSchedule,
                 T_world_lidar: NDArray[np.float64], k: int, stamp_ns: int,
                 rng: np.random.Generator) -> tuple[NDArray[np.float32], NDArray[np.int64] | None]:
    """Scan ``k``: its points and, with ``lidar_point_times``, their times after ``stamp_ns`` (each ray cast from
    the ground-truth pose at its capture time)."""
    dirs_l, offsets_ns = lidar_rays(config, k)
    if not config.lidar_point_times:
        return cast_lidar(scene, T_world_lidar, dirs_l, config, rng)[0], None
    poses = base_poses_at(config, np.int64(stamp_ns) + offsets_ns, schedule) @ T_base_lidar(config)
    scan, ok = cast_lidar(scene, poses, dirs_l, config, rng)
    return scan, offsets_ns[ok]
