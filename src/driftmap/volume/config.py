"""Settings of the volumetric layers: :class:`VolumeConfig` (the ``[volume]`` table of a config file) and its
defaults, defined with every other setting in :mod:`driftmap.config` and re-exported here."""

from driftmap.config import (
    DEPTH_VOXEL_SIZE_M,
    LIDAR_VOXEL_PER_SCALE_M,
    TRUNCATION_VOXELS,
    UnknownIs,
    VolumeConfig,
)

__all__ = ["DEPTH_VOXEL_SIZE_M", "LIDAR_VOXEL_PER_SCALE_M", "TRUNCATION_VOXELS", "UnknownIs", "VolumeConfig"]
