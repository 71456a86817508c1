"""Settings of the volumetric layers (the ``[volume]`` table of a config file), with units in every name.

The occupancy sensor model is OctoMap's (Hornung et al. 2013): each frame adds at most one hit or one miss to a
voxel (a voxel a ray ends in is a hit, a voxel it passes through a miss, a hit wins over a miss of the same frame),
as log-odds of ``prob_hit`` / ``prob_miss``, clamped to ``clamp_min`` .. ``clamp_max``; a voxel is occupied at or
above ``occupancy_threshold``, free below it, unknown when no ray ended in or passed through it. driftmap keeps the
integer counts of hits and misses and clamps only when it reads a voxel, so that removing a frame's contribution
and adding it again at a corrected pose gives exactly the layers a rebuild gives (OctoMap clamps after every
update, which makes the result depend on the order of the frames).
"""

from __future__ import annotations

import enum
import math

from pydantic import BaseModel, ConfigDict, Field, model_validator

from driftmap.frame import SensorKind


class UnknownIs(str, enum.Enum):
    """How the distance field and the swept checks treat never-observed space."""

    OCCUPIED = "occupied"
    """unknown space is an obstacle (what planners expect: no path through what nobody saw)"""
    FREE = "free"
    """unknown space is free (optimistic exploration)"""


DEPTH_VOXEL_SIZE_M = 0.02
"""Default voxel of a depth camera's layers."""
LIDAR_VOXEL_PER_SCALE_M = 0.4
"""Default voxel of a LiDAR's layers at scene scale 1 (outdoors: 0.4 m); scaled with the scene as the odometry is
(:func:`driftmap.preprocess.scene.lidar_odometry_scale`: the synthetic room 0.074 m)."""
TRUNCATION_VOXELS = 4.0
"""Default TSDF truncation, in voxels (Open3D's examples use 4-8)."""


class VolumeConfig(BaseModel):
    """Voxel size, TSDF truncation, OctoMap's sensor model, ranges, the unknown-space policy and a memory budget."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    voxel_size_m: float | None = Field(None, gt=0.0, description="voxel edge (m); None: 0.02 m for depth cameras, LiDAR 0.4 m x the scene scale (as the odometry's lengths)")
    truncation_m: float | None = Field(None, gt=0.0, description="TSDF truncation distance (m); None: 4 voxels")
    prob_hit: float = Field(0.7, gt=0.5, lt=1.0, description="occupancy probability of a voxel a ray ends in (OctoMap's default)")
    prob_miss: float = Field(0.4, gt=0.0, lt=0.5, description="occupancy probability of a voxel a ray passes through (OctoMap's default)")
    clamp_min: float = Field(0.1192, gt=0.0, lt=0.5, description="occupancy probability clamp, lower (OctoMap's default)")
    clamp_max: float = Field(0.971, gt=0.5, lt=1.0, description="occupancy probability clamp, upper (OctoMap's default)")
    occupancy_threshold: float = Field(0.5, gt=0.0, lt=1.0, description="a voxel is occupied at or above this probability, free below it (OctoMap's default)")
    min_range_m: float = Field(0.05, ge=0.0, description="points closer than this to their sensor carve and mark nothing (a point at the sensor origin is no observation)")
    max_range_m: float | None = Field(None, gt=0.0, description="points farther than this carve free space only up to this range and mark no hit; None: a depth camera's range where its noise reaches half a voxel (2.55 m at 2 cm), a LiDAR odometry's max range")
    surface_min_hits: int = Field(2, ge=1, description="clearance counts an occupied voxel as a surface when at least this many points ended in it (one stray point of depth noise is no wall: on the synthetic log's noisy camera single-point voxels put 97 % of the clearance errors over a voxel)")
    unknown_is: UnknownIs = Field(UnknownIs.OCCUPIED, description="occupied | free: how the distance field and swept checks treat never-observed voxels")
    memory_budget_mb: float = Field(4096.0, gt=0.0, description="layers that would allocate more than this (MiB) are refused before anything is allocated")
    padding_m: float = Field(0.5, ge=0.0, description="the grid spans the observations plus this margin, so small corrections do not grow it")

    @model_validator(mode="after")
    def _clamps(self) -> VolumeConfig:
        if not self.clamp_min < self.occupancy_threshold < self.clamp_max:
            raise ValueError(f"occupancy_threshold ({self.occupancy_threshold}) must lie between clamp_min "
                             f"({self.clamp_min}) and clamp_max ({self.clamp_max})")
        return self

    def resolved(self, sensor: SensorKind, scene_scale: float = 1.0, sensor_max_range_m: float | None = None) -> VolumeConfig:
        """The settings with their sensor defaults filled in: the voxel (:data:`DEPTH_VOXEL_SIZE_M`, or LiDAR
        :data:`LIDAR_VOXEL_PER_SCALE_M` x ``scene_scale``), the truncation (:data:`TRUNCATION_VOXELS` voxels) and the
        max range (``sensor_max_range_m``: a depth camera's depth limit, a LiDAR odometry's range)."""
        voxel = self.voxel_size_m
        if voxel is None:
            voxel = DEPTH_VOXEL_SIZE_M if sensor is not SensorKind.LIDAR else LIDAR_VOXEL_PER_SCALE_M * scene_scale
        return self.model_copy(update={
            "voxel_size_m": voxel,
            "truncation_m": self.truncation_m if self.truncation_m is not None else TRUNCATION_VOXELS * voxel,
            "max_range_m": self.max_range_m if self.max_range_m is not None else sensor_max_range_m,
        })

    # OctoMap's log-odds of the sensor model
    @property
    def log_odds_hit(self) -> float:
        return _logit(self.prob_hit)

    @property
    def log_odds_miss(self) -> float:
        return _logit(self.prob_miss)

    @property
    def log_odds_min(self) -> float:
        return _logit(self.clamp_min)

    @property
    def log_odds_max(self) -> float:
        return _logit(self.clamp_max)

    @property
    def log_odds_threshold(self) -> float:
        return _logit(self.occupancy_threshold)


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))
