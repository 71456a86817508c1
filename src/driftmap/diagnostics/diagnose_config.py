"""What ``driftmap diagnose`` is configured with: every part's settings in one :class:`DiagnoseConfig`, with
defaults for the sensor and the scene's reach (:mod:`driftmap.preprocess.scene`) and a config-file loader."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import ConfigDict, Field

from driftmap.config import SettingsModel
from driftmap.diagnostics.attribution import AttributionConfig
from driftmap.diagnostics.coverage import CoverageConfig
from driftmap.diagnostics.revisits import RevisitCheckConfig
from driftmap.diagnostics.samples import SamplingConfig
from driftmap.diagnostics.wall_results import DoubleWallConfig
from driftmap.errors import ConfigError, StoreError
from driftmap.frame import SensorKind
from driftmap.preprocess.scene import (
    OUTDOOR_DIAGNOSTICS_SCALE,
    diagnostics_scale,
    lidar_frames,
    sample_positions,
    scene_reach,
)

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)


class EntropyConfig(SettingsModel):
    """Neighbourhood rules of MME / MPV (values only compare within one rule set and one data set)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    radius_m: float = Field(0.1, gt=0.0, description="neighbours within this radius (m)")
    min_neighbors: int = Field(10, ge=4, description="points with fewer neighbours are skipped")
    max_neighbors: int = Field(64, ge=4, le=128, description="at most this many nearest neighbours (up to 128: the neighbourhoods of every sampled point are held at once)")
    max_query_points: int = Field(50_000, ge=100, description="random query points (neighbours come from every sample)")


class DiagnoseConfig(SettingsModel):
    """Everything ``diagnose`` uses; :meth:`for_sensor` gives indoor RGB-D or outdoor LiDAR defaults."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    sampling: SamplingConfig = Field(default_factory=SamplingConfig)
    double_wall: DoubleWallConfig = Field(default_factory=DoubleWallConfig)
    attribution: AttributionConfig = Field(default_factory=AttributionConfig)
    entropy: EntropyConfig = Field(default_factory=EntropyConfig)
    coverage: CoverageConfig = Field(default_factory=CoverageConfig)
    revisits: RevisitCheckConfig = Field(default_factory=RevisitCheckConfig)

    @classmethod
    def for_sensor(cls, kind: SensorKind) -> DiagnoseConfig:
        if kind is SensorKind.LIDAR:
            return cls(
                sampling=SamplingConfig(points_budget=1_000_000, min_points_per_frame=2000, normals_oversample=4.0, normals_k=20),
                double_wall=DoubleWallConfig(voxel_sizes_m=(0.5, 1.0, 2.0), min_separation_m=0.05, visit_gap_m=10.0),
                attribution=AttributionConfig(voxel_size_m=1.0, huber_m=0.1, max_residual_m=0.5, min_jump_m=0.05,
                                              revisit_min_path_m=10.0),
                entropy=EntropyConfig(radius_m=0.5),
                revisits=RevisitCheckConfig(revisit_min_path_m=10.0, registration_voxel_m=0.25, coarse_gate_m=4.0,
                                            max_detectable_m=1.0),
            )
        return cls()

    @classmethod
    def for_scene(cls, kind: SensorKind, reach_m: float | None) -> DiagnoseConfig:
        """Defaults for a sensor whose scene reaches ``reach_m`` (:mod:`driftmap.preprocess.scene`).

        Depth cameras: the indoor lengths. LiDAR: its sampling, with every diagnostic length (voxel sizes, the
        smallest separation, attribution cells and thresholds, entropy radius, the revisit check's voxel, gate and
        detectable separation) the indoor one times
        ``f = min(5, max(1, reach / 5 m))`` and the travel lengths (visit gap, revisit path) times ``f ** 1.43``
        (1 at f = 1, 10 at f = 5; the revisit check's travel too): a room reaching 5 m or less is diagnosed as a depth camera's, a scene reaching
        25 m or more with the outdoor lengths (2 m voxels, 10 m of travel between visits), and everything in
        between continuously."""
        if kind is not SensorKind.LIDAR:
            return cls()
        lidar = cls.for_sensor(kind)
        f = diagnostics_scale(reach_m) if reach_m is not None else OUTDOOR_DIAGNOSTICS_SCALE
        if f >= OUTDOOR_DIAGNOSTICS_SCALE:
            return lidar
        g = f ** (math.log(10.0) / math.log(OUTDOOR_DIAGNOSTICS_SCALE))
        dw, at, en, rv = DoubleWallConfig(), AttributionConfig(), EntropyConfig(), RevisitCheckConfig()
        return lidar.model_copy(update={
            "double_wall": dw.model_copy(update={"voxel_sizes_m": tuple(f * v for v in dw.voxel_sizes_m),
                                                 "min_separation_m": f * dw.min_separation_m,
                                                 "visit_gap_m": g * dw.visit_gap_m}),
            "attribution": at.model_copy(update={"voxel_size_m": f * at.voxel_size_m, "huber_m": f * at.huber_m,
                                                 "max_residual_m": f * at.max_residual_m,
                                                 "min_jump_m": f * at.min_jump_m,
                                                 "revisit_min_path_m": g * at.revisit_min_path_m}),
            "entropy": en.model_copy(update={"radius_m": f * en.radius_m}),
            "revisits": rv.model_copy(update={"revisit_min_path_m": g * rv.revisit_min_path_m,
                                              "registration_voxel_m": f * rv.registration_voxel_m,
                                              "coarse_gate_m": f * rv.coarse_gate_m,
                                              "max_detectable_m": f * rv.max_detectable_m}),
        })

    @classmethod
    def for_store(cls, store: FrameStore) -> DiagnoseConfig:
        """:meth:`for_scene` of the store's sensor and of the reach of 15 of its frames spread over the log (the
        median of their 99th range percentiles)."""
        if len(store) == 0:
            raise StoreError(f"{store.path}: the store has no frames")
        ids = store.frame_ids
        first = store.frame(int(ids[0]))
        if first.sensor_kind is not SensorKind.LIDAR:
            return cls.for_sensor(first.sensor_kind)
        reach = scene_reach(lidar_frames(store.frame(int(ids[k])) for k in sample_positions(len(ids))))
        cfg = cls.for_scene(first.sensor_kind, None if reach is None else reach.reach_m)
        if reach is not None:
            logger.info("%s: the LiDAR scene reaches %s: diagnosing with %.2g x the indoor lengths (voxels %s m, "
                        "visit gap %.3g m)", store.path, reach.describe(), diagnostics_scale(reach.reach_m),
                        ", ".join(f"{v:.3g}" for v in cfg.double_wall.voxel_sizes_m), cfg.double_wall.visit_gap_m)
        return cfg

    @classmethod
    def load(cls, path: str | Path, defaults: DiagnoseConfig) -> DiagnoseConfig:
        """A diagnose config file (JSON or TOML): its ``[diagnose]`` table (or the whole file without one), each
        field set there over ``defaults`` (the scene's, :meth:`for_store`); nested tables (``[diagnose.double_wall]``
        ...) are merged field by field. Problems are :class:`ConfigError`, one line each, naming the file and key."""
        from pydantic import ValidationError

        from driftmap.config import (
            BUILD_TABLE,
            DIAGNOSE_TABLE,
            FLEET_TABLE,
            GENERAL_TABLES,
            read_config_file,
            validation_problems,
        )

        data = read_config_file(path)
        prefix: tuple[str, ...] = ()
        if DIAGNOSE_TABLE in data:
            data, prefix = data[DIAGNOSE_TABLE], (DIAGNOSE_TABLE,)
        elif {BUILD_TABLE, FLEET_TABLE, *GENERAL_TABLES} & set(data):  # no [diagnose] table: the defaults
            return defaults
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: [diagnose] must be a table of settings")
        merged = defaults.model_dump(mode="json")
        for key, value in data.items():
            if isinstance(value, dict) and isinstance(merged.get(key), dict):
                merged[key] = {**merged[key], **value}
            else:
                merged[key] = value
        try:
            return cls.model_validate(merged)
        except ValidationError as exc:
            raise ConfigError(validation_problems(exc, str(path), prefix=prefix)) from exc
