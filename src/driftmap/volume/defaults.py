"""The volumetric settings a store gets when they are not set: its sensor's voxel, truncation and max range."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from driftmap.errors import ConfigError, StoreError
from driftmap.frame import SensorKind
from driftmap.preprocess.noise import NoiseModel
from driftmap.preprocess.scene import lidar_frames, lidar_odometry_scale, sample_positions, scene_reach
from driftmap.volume.config import VolumeConfig

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)

NOISE_PER_VOXEL = 0.4
"""A depth camera's points count as hits up to the depth at which its noise sigma reaches this share of a voxel
(Kinect v1, :class:`~driftmap.preprocess.noise.NoiseModel`: 2.29 m at 2 cm voxels, 2.5 sigma within a voxel); farther ones carve free space
up to that range only. With every point to 4 m, 11 % of the synthetic log's occupied voxels were more than a voxel
off its true surfaces (1.3 % at 2.55 m, sigma half a voxel)."""
DEPTH_MAX_RANGE_LIMITS_M = (1.0, 4.0)
BUILD_SUMMARY = "build_summary.json"
MERGE_SUMMARY = "merge_summary.json"


def resolve_config(store: FrameStore, config: VolumeConfig) -> VolumeConfig:
    """``config`` with its sensor defaults filled in for ``store``: a depth camera's 2 cm voxels and the range where
    its depth noise stays within half a voxel (:data:`NOISE_PER_VOXEL`, 1..4 m); a
    LiDAR's voxel scaled with the scene as the odometry's lengths are, and the odometry's max range
    (:func:`lidar_max_range`: recorded in ``build_summary.json``, or for a merged store in ``merge_summary.json``;
    else, for a store built with given poses, :func:`lidar_max_range_from_frames`, with a warning). A LiDAR store
    whose range cannot be told at all (no frame with a point) is a :class:`ConfigError` (its rays would set the
    grid's extent: set ``volume.max_range_m``)."""
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
    max_range = config.max_range_m
    if max_range is None:
        max_range, _ = lidar_max_range(store)
    if max_range is None:  # built with given poses: the range our odometry's defaults take for these frames
        max_range = lidar_max_range_from_frames(store)
        if max_range is not None:
            logger.warning("%s: no max range recorded for the LiDAR rays (built with given poses?): the volumetric "
                           "layers take %.2f m, the odometry defaults' rule on the frames' reach; set "
                           "volume.max_range_m (--config [volume] or DRIFTMAP_VOLUME__MAX_RANGE_M) to choose it",
                           store.path, max_range)
    if max_range is None:
        raise ConfigError(f"{store.path}: a LiDAR store without a max range for its rays (no odometry settings in "
                          f"{BUILD_SUMMARY}, no merged range in {MERGE_SUMMARY}): set volume.max_range_m (metres) in "
                          f"a [volume] table of --config or as DRIFTMAP_VOLUME__MAX_RANGE_M (export --mcap "
                          f"--no-volume writes the MCAP without the layers)")
    return config.resolved(SensorKind.LIDAR, scale, max_range)


def lidar_max_range(store: FrameStore) -> tuple[float | None, str]:
    """The max range a LiDAR store's rays get when ``volume.max_range_m`` is not set, and where it came from:
    ``"build_summary"``, the odometry's max range recorded by ``build`` (every store built with our odometry: its
    resolved config is what it always was); ``"merge_summary"``, the one ``merge`` recorded for a merged store
    (session 0's: :func:`driftmap.pipeline.merge.volume_defaults`); ``"none"`` (None) without either (a store built
    with given poses: set ``volume.max_range_m``)."""
    recorded = _odometry_max_range(store)
    if recorded is not None:
        return recorded, "build_summary"
    merged = _merge_max_range(store)
    if merged is not None:
        return merged, "merge_summary"
    return None, "none"


def lidar_max_range_from_frames(store: FrameStore) -> float | None:
    """The max range our odometry's defaults would take for ``store``'s frames
    (:meth:`~driftmap.registration.odometry.OdometryConfig.for_frames`: the outdoor 100 m times the scene scale, from
    the median over frames spread across the store of each scan's 99th range percentile -- never one frame); None
    when no sampled frame has a point. ``merge`` records it for a session whose store records no range."""
    from driftmap.registration.odometry import OdometryConfig  # KISS-ICP's settings: imported only when needed

    lidar = lidar_frames(store.frame(int(store.frame_ids[k])) for k in sample_positions(len(store)))
    if scene_reach(lidar) is None:
        return None
    value = float(OdometryConfig.for_frames(lidar, log=False).max_range_m)
    logger.info("%s: no recorded max range for the LiDAR rays; %.2f m from the reach of %d frames spread over the "
                "store (the odometry defaults' rule)", store.path, value, len(lidar))
    return value


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        return None
    return data if isinstance(data, dict) else None


def _positive(value: object) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0 else None


def _odometry_max_range(store: FrameStore) -> float | None:
    return _recorded_max_range(store, BUILD_SUMMARY, "odometry_config")


def _merge_max_range(store: FrameStore) -> float | None:
    return _recorded_max_range(store, MERGE_SUMMARY, "volume_defaults")


def _recorded_max_range(store: FrameStore, file: str, table: str) -> float | None:
    """``max_range_m`` of the ``table`` object in the store's ``file`` (a positive number, else None)."""
    summary = _read_json(store.path / file)
    values = (summary or {}).get(table) or {}
    return _positive(values.get("max_range_m")) if isinstance(values, dict) else None
