"""The settings of the decisions (thresholds with units) and the hash that names them with the volumetric settings.

A query may override its own thresholds (``min_points``, ``max_normal_spread_deg``, ``max_flatness_m``,
``unknown_is``); everything else is :class:`DecideConfig`, the ``[decide]`` table of a config file
(:class:`driftmap.config.DriftmapConfig`; defined there, below the decisions, and re-exported here).
"""

from __future__ import annotations

import hashlib
import json

import logging

from driftmap.config import DEPTH_VOXEL_SIZE_M, DecideConfig, VolumeConfig
from driftmap.frame import SensorKind

__all__ = ["SENSOR_SCALED_LENGTHS", "DecideConfig", "for_sensor", "settings_hash"]

logger = logging.getLogger(__name__)

SENSOR_SCALED_LENGTHS = ("normal_radius_m", "normal_voxel_m", "spread_radius_m")
"""The estimation lengths a LiDAR map scales (thresholds such as ``foothold_max_flatness_m`` are the robot's and are
not scaled)."""


def for_sensor(config: DecideConfig, sensor_kind: SensorKind, voxel_size_m: float) -> DecideConfig:
    """``config`` for a map of ``sensor_kind`` whose layers have ``voxel_size_m`` voxels: on a LiDAR map each of
    :data:`SENSOR_SCALED_LENGTHS` the configuration does not set is scaled by ``voxel_size_m`` /
    :data:`~driftmap.config.DEPTH_VOXEL_SIZE_M` (KITTI's 0.4 m voxels: normals on 0.2 m voxels from neighbours
    within 0.6 m), as the layers' own voxel is. The depth-camera defaults (3 cm neighbourhoods of 1 cm voxel means)
    hold a few points of one scan ring on a LiDAR map: its normals point anywhere across the ring, and a flat road
    read 31-66 deg steep (hostile trial 27 B3). Depth-camera maps keep ``config``."""
    if sensor_kind is not SensorKind.LIDAR:
        return config
    factor = float(voxel_size_m) / DEPTH_VOXEL_SIZE_M
    update = {name: getattr(config, name) * factor for name in SENSOR_SCALED_LENGTHS
              if name not in config.model_fields_set and getattr(config, name) is not None}
    if not update:
        return config
    logger.debug("decide on a LiDAR map (%g m voxels): %s", voxel_size_m,
                 ", ".join(f"{k} {v:.3g} m" for k, v in update.items()))
    return config.model_copy(update=update)


def settings_hash(volume: VolumeConfig, decide: DecideConfig) -> str:
    """16 hex digits of the SHA-256 of the resolved volumetric settings and the decision settings (canonical JSON):
    two decision sets with the same hash were made with the same settings."""
    payload = {"volume": volume.model_dump(mode="json"), "decide": decide.model_dump(mode="json")}
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]
