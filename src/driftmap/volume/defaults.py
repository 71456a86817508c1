"""The volumetric settings a store gets when they are not set: its sensor's voxel, truncation and max range."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

import numpy as np

from driftmap.errors import ConfigError, StoreError
from driftmap.frame import SensorKind
from driftmap.preprocess.noise import NoiseModel
from driftmap.preprocess.scene import lidar_frames, lidar_odometry_scale, sample_positions, scene_reach
from driftmap.volume.config import VolumeConfig

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

NOISE_PER_VOXEL = 0.4
"""A depth camera's points count as hits up to the depth at which its noise sigma reaches this share of a voxel
(Kinect v1, :class:`~driftmap.preprocess.noise.NoiseModel`: 2.29 m at 2 cm voxels, 2.5 sigma within a voxel); farther ones carve free space
up to that range only. With every point to 4 m, 11 % of the synthetic log's occupied voxels were more than a voxel
off its true surfaces (1.3 % at 2.55 m, sigma half a voxel)."""
DEPTH_MAX_RANGE_LIMITS_M = (1.0, 4.0)
BUILD_SUMMARY = "build_summary.json"


def resolve_config(store: FrameStore, config: VolumeConfig) -> VolumeConfig:
    """``config`` with its sensor defaults filled in for ``store``: a depth camera's 2 cm voxels and the range where
    its depth noise stays within half a voxel (:data:`NOISE_PER_VOXEL`, 1..4 m); a
    LiDAR's voxel scaled with the scene as the odometry's lengths are, and the odometry's max range (recorded in
    ``build_summary.json``). A LiDAR store whose range cannot be told is a :class:`ConfigError` (its rays would set
    the grid's extent: set ``volume.max_range_m``)."""
    if len(store) == 0:
        raise StoreError(f"{store.path}: the store holds no frames: there is no map to build volumetric layers of")
    first = store.frame(int(store.frame_ids[0]))
    if first.sensor_kind is not SensorKind.LIDAR:
        voxel = config.resolved(first.sensor_kind).voxel_size_m
        noise = NoiseModel.for_sensor(first.sensor_kind).depth_for_sigma_m(NOISE_PER_VOXEL * float(voxel))
        return config.resolved(first.sensor_kind, 1.0, float(np.clip(noise, *DEPTH_MAX_RANGE_LIMITS_M)))
    sample = [store.frame(int(store.frame_ids[k])) for k in sample_positions(len(store))]
    reach = scene_reach(lidar_frames(sample))
    scale = lidar_odometry_scale(reach.reach_m) if reach is not None else 1.0
    max_range = config.max_range_m if config.max_range_m is not None else _odometry_max_range(store)
    if max_range is None:
        raise ConfigError(f"{store.path}: a LiDAR store without a max range for its rays (no odometry settings in "
                          f"{BUILD_SUMMARY}): set volume.max_range_m (metres) in a [volume] table of --config or "
                          f"as DRIFTMAP_VOLUME__MAX_RANGE_M (export --mcap --no-volume writes the MCAP without the "
                          f"layers)")
    return config.resolved(SensorKind.LIDAR, scale, max_range)


def _odometry_max_range(store: FrameStore) -> float | None:
    path = store.path / BUILD_SUMMARY
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        return None
    odometry = summary.get("odometry_config") or {}
    value = odometry.get("max_range_m")
    return float(value) if isinstance(value, (int, float)) and value > 0 else None
