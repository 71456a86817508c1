"""Typed, layered configuration (pydantic): defaults < config file (JSON or TOML) < environment < flags.

Environment variables use the prefix ``DRIFTMAP_`` and ``__`` between levels, e.g.
``DRIFTMAP_DEPTH__MAX_DEPTH_M=3.0``. The configuration that produced a result is written next to it.

One file can hold both: the ``depth`` / ``map`` tables are :class:`DriftmapConfig`, a ``build`` table is
``driftmap build``'s :class:`~driftmap.pipeline.build.BuildConfig` (``driftmap config --file F`` shows both,
``driftmap build --config F`` reads all three, ``driftmap export --config F`` the ``map`` table). A file with
none of these tables is a bare build config.

Every setting here takes effect (the tests check it):

* ``depth.*`` -- ``driftmap build`` passes them to a depth-image source (7-Scenes, TUM, Redwood / ICL-NUIM,
  synthetic logs, ROS depth topics, as far as the format takes the option); ``None`` keeps the source's own
  default. A setting the format cannot take (e.g. ``max_depth_m`` on KITTI scans) is refused.
* ``map.export_voxel_size_m`` -- ``driftmap export --map`` / ``--mcap`` without ``--voxel-size-m``.

Per-frame point processing (``preprocess``: voxel downsampling, outlier removal, normals) is not part of
``build`` -- the store keeps the frames at full resolution -- so it is not a table here; the library's
:func:`driftmap.preprocess.cloud.process_frame` takes :class:`PreprocessConfig` (``**cfg.model_dump()``).
"""

from __future__ import annotations

import enum
import json
import math
import numbers
import os
import tomllib
import types
import typing
from pathlib import Path
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from driftmap.errors import ConfigError
from driftmap.files import json_loads_unique
from driftmap.frame import SensorKind

ENV_PREFIX = "DRIFTMAP_"
ENV_DELIMITER = "__"

THREADS_PER_CPU = 4
"""Registration threads are refused beyond this many per CPU of the machine (small_gicp / TBB / OpenMP crash or
stall with absurd counts: 100000 threads segfaulted; more threads than cores only slow a registration down)."""


def max_threads() -> int:
    """The most registration threads driftmap accepts on this machine: :data:`THREADS_PER_CPU` per CPU."""
    return THREADS_PER_CPU * max(1, os.cpu_count() or 1)


def check_threads(n: int, what: str = "num_threads") -> int:
    """``n`` if it is a usable thread count (1 .. :func:`max_threads`), else a :class:`ConfigError` naming ``what``:
    the one check of every thread count driftmap takes (config files, ``--threads``)."""
    if isinstance(n, numbers.Integral) and not isinstance(n, bool):  # numpy's ints too (hostile trial 25 W5)
        n = int(n)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ConfigError(f"{what}: a thread count must be a whole number >= 1, got {n!r}")
    if n > max_threads():
        raise ConfigError(f"{what}: {n} threads is more than this machine takes (at most {max_threads()}: "
                          f"{THREADS_PER_CPU} per CPU, {os.cpu_count() or 1} CPUs)")
    return n


def _threads_field(n: int) -> int:
    try:
        return check_threads(n, "thread count")
    except ConfigError as exc:
        raise ValueError(str(exc).removeprefix("thread count: ")) from None


Threads = Annotated[int, Field(ge=1), AfterValidator(_threads_field)]
"""A thread-count field of a settings model, checked by :func:`check_threads`."""


def _accepts_bool(annotation: Any) -> bool:
    """A field type that a ``true`` / ``false`` may fill (``bool`` itself, or a union or annotation holding it)."""
    if annotation is bool:
        return True
    return any(_accepts_bool(a) for a in typing.get_args(annotation))


class SettingsModel(BaseModel):
    """The base of every settings table: unknown keys and non-finite numbers are refused, and so is ``true`` /
    ``false`` where a number or a name is expected (pydantic would read ``min_depth_m = true`` as 1.0 m)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _no_bools_for_numbers(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for name, value in data.items():
                field = cls.model_fields.get(name)
                if isinstance(value, bool) and field is not None and not _accepts_bool(field.annotation):
                    raise ValueError(f"{name}: expected {_type_name(field.annotation)}, got {str(value).lower()}")
        return data


def _type_name(annotation: Any) -> str:
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    base = args[0] if typing.get_origin(annotation) is not None and args else annotation
    return getattr(base, "__name__", str(base))


class DepthConfig(SettingsModel):
    """Depth-image sources: the options ``driftmap build`` passes to them (None: the source's own default)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    min_depth_m: float | None = Field(None, ge=0.0, description="closest valid depth (m); None: the source's default (0.2 m for 7-Scenes, TUM, Redwood)")
    max_depth_m: float | None = Field(None, gt=0.0, description="depth at and beyond which pixels are rejected (m), like Open3D depth_trunc; None: the source's default (7-Scenes 4.0 m, TUM and Redwood 5.0 m)")
    depth_scale: float | None = Field(None, gt=0.0, description="depth-image units per metre (1000: millimetres, TUM 5000); None: the format's own; 'build --depth-scale' sets it")
    check_scale: bool = Field(True, description="false: skip the sources' sensor-range check of the depth scale (the DepthScaleError that suggests another depth_scale)")
    intrinsics: str | None = Field(None, description="depth camera intrinsics 'fx,fy,cx,cy[,width,height]' (pixels), a TUM setup fr1 | fr2 | fr3, or an Open3D intrinsics JSON path, for sources that take them (7-Scenes, TUM, Redwood / ICL-NUIM); None: the source's own (its calibration file, the TUM folder name); 'build --intrinsics' sets it")

    @field_validator("intrinsics")
    @classmethod
    def _intrinsics(cls, value: str | None) -> str | None:
        if value is not None:
            try:
                _intrinsics_option(value)
            except ConfigError as exc:
                raise ValueError(str(exc).removeprefix("depth.intrinsics: ")) from None
        return value

    @model_validator(mode="after")
    def _range(self) -> DepthConfig:
        if self.min_depth_m is not None and self.max_depth_m is not None and self.max_depth_m <= self.min_depth_m:
            raise ValueError(f"max_depth_m ({self.max_depth_m}) must exceed min_depth_m ({self.min_depth_m})")
        return self

    def source_options(self) -> dict[str, Any]:
        """The options this sets, as keyword arguments of a source opener (nothing for the defaults)."""
        options: dict[str, Any] = {name: getattr(self, name) for name in ("min_depth_m", "max_depth_m", "depth_scale")
                                   if getattr(self, name) is not None}
        if not self.check_scale:
            options["sensor_range_m"] = None
        if self.intrinsics is not None:
            options["intrinsics"] = _intrinsics_option(self.intrinsics)
        return options


def _intrinsics_option(text: str) -> Any:
    """``depth.intrinsics`` as a source takes it: numbers as a list, anything else (fr1, a JSON path) as given."""
    parts = [p.strip() for p in text.split(",")]
    try:
        numbers = [float(p) for p in parts]
    except ValueError:
        if len(parts) > 1:
            raise ConfigError(f"depth.intrinsics: {text!r} is neither 'fx,fy,cx,cy[,width,height]' numbers nor a name or path") from None
        return text
    if len(numbers) not in (4, 6):
        raise ConfigError(f"depth.intrinsics: {text!r} has {len(numbers)} numbers; give fx,fy,cx,cy[,width,height]")
    if any(not math.isfinite(v) or v != int(v) or v <= 0 for v in numbers[4:]):
        raise ConfigError(f"depth.intrinsics: {text!r}: width and height are whole numbers of pixels, got "
                          f"{', '.join(parts[4:])}")
    return numbers[:4] + [int(v) for v in numbers[4:]]


class PreprocessConfig(SettingsModel):
    """Per-frame processing of sensor-frame points, for :func:`driftmap.preprocess.cloud.process_frame` (library
    only: ``driftmap build`` stores full-resolution frames, so this is not a table of :class:`DriftmapConfig`)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    voxel_size_m: float | None = Field(None, gt=0.0, description="voxel size for per-frame downsampling (m); None keeps full resolution")
    statistical_outlier_neighbors: int | None = Field(None, ge=2, description="neighbours for statistical outlier removal; None disables it")
    statistical_outlier_std_ratio: float = Field(2.0, gt=0.0, description="std-dev multiple beyond which a point is an outlier")
    radius_outlier_min_points: int | None = Field(None, ge=1, description="minimum neighbours within radius_outlier_radius_m; None disables it")
    radius_outlier_radius_m: float = Field(0.05, gt=0.0, description="radius for radius outlier removal (m)")
    normals_k: int = Field(20, ge=3, le=200, description="nearest neighbours used for normals")


class MapConfig(SettingsModel):
    """Fused map export."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    export_voxel_size_m: float | None = Field(None, gt=0.0, description="voxel size of 'export --map' / '--mcap' without --voxel-size-m (m); None: every point (--map), 0.02 m (--mcap)")
    mesh_weight_threshold: float = Field(3.0, gt=0.0, le=1e6, description="the TSDF mesh ('export --mesh' without --mesh-weight-threshold, the MCAP's mesh, batch's mesh export) meshes only voxels observed by at least this many frames (Open3D's default 3; lower it for a log of a few frames)")


# ---------------------------------------------------------------------------------------- volumetric layers
# The occupancy sensor model is OctoMap's (Hornung et al. 2013): each frame adds at most one hit or one miss to a voxel
# (a voxel a ray ends in is a hit, a voxel it passes through a miss, a hit wins over a miss of the same frame), as
# log-odds of prob_hit / prob_miss, clamped to clamp_min .. clamp_max; a voxel is occupied at or above
# occupancy_threshold, free below it, unknown when no ray ended in or passed through it. driftmap keeps the integer
# counts and clamps only when it reads a voxel, so a frame's contribution can be taken out and put back at a corrected
# pose with exactly the layers a rebuild gives (OctoMap clamps after every update: order-dependent). docs/volume.md.

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
MAX_TRUNCATION_VOXELS = 100.0
"""volume.truncation_m may be at most this many voxels (a TSDF band is usually 3-10; trial 26 W3: 100 m gave a
200 m grid whose error blamed the voxel size)"""


def _physical_memory_mb() -> float | None:
    """This machine's physical memory in MiB (None where the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20
    except (ValueError, OSError, AttributeError):
        return None


class VolumeConfig(SettingsModel):
    """Voxel size, TSDF truncation, OctoMap's sensor model, ranges, the unknown-space policy and a memory budget."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    voxel_size_m: float | None = Field(None, ge=1e-4, le=10.0, description="voxel edge (m), at least 0.1 mm (finer than any depth camera resolves) and at most 10 m (a building in one voxel tells a planner nothing), never larger than the map; None: 0.02 m for depth cameras, LiDAR 0.4 m x the scene scale (as the odometry's lengths)")
    truncation_m: float | None = Field(None, gt=0.0, description="TSDF truncation distance (m); None: 4 voxels")
    prob_hit: float = Field(0.7, gt=0.5, lt=1.0, description="occupancy probability of a voxel a ray ends in (OctoMap's default)")
    prob_miss: float = Field(0.4, gt=0.0, lt=0.5, description="occupancy probability of a voxel a ray passes through (OctoMap's default)")
    clamp_min: float = Field(0.1192, gt=0.0, lt=0.5, description="occupancy probability clamp, lower (OctoMap's default)")
    clamp_max: float = Field(0.971, gt=0.5, lt=1.0, description="occupancy probability clamp, upper (OctoMap's default)")
    occupancy_threshold: float = Field(0.5, gt=0.0, lt=1.0, description="a voxel is occupied at or above this probability, free below it (OctoMap's default)")
    min_range_m: float = Field(0.05, ge=0.0, description="points closer than this to their sensor carve and mark nothing (a point at the sensor origin is no observation)")
    max_range_m: float | None = Field(None, gt=0.0, description="points farther than this carve free space only up to this range and mark no hit; None: a depth camera's range where its noise reaches half a voxel (2.29 m at 2 cm), a LiDAR odometry's max range")
    surface_min_hits: int = Field(2, ge=1, description="clearance counts an occupied voxel as a surface when at least this many points ended in it (one stray point of depth noise is no wall: on the synthetic log's noisy camera single-point voxels put 97 % of the clearance errors over a voxel)")
    unknown_is: UnknownIs = Field(UnknownIs.OCCUPIED, description="occupied | free: how the distance field and swept checks treat never-observed voxels")
    memory_budget_mb: float = Field(4096.0, gt=0.0, description="layers whose grid would allocate more than this (MiB) are refused before anything is allocated; the frames' kept missed voxels (keep_frame_voxels) stop being kept beyond it")
    padding_m: float = Field(0.5, ge=0.0, description="the grid spans the observations plus this margin, so small corrections do not grow it")
    keep_frame_voxels: bool = Field(True, description="keep each frame's missed voxels (4 bytes each, ~1 MB a 2 cm depth frame) so that a correction takes a frame out by decrementing them instead of tracing its rays again; kept while the grid and the kept voxels fit memory_budget_mb")

    @field_validator("memory_budget_mb")
    @classmethod
    def _within_memory(cls, value: float) -> float:
        physical_mb = _physical_memory_mb()
        if physical_mb is not None and value > physical_mb:
            raise ValueError(f"must be at most this machine's memory, {physical_mb:,.0f} MiB (more would have the "
                             f"process killed instead of refused)")
        return value

    @model_validator(mode="after")
    def _clamps(self) -> VolumeConfig:
        if self.max_range_m is not None and not self.min_range_m < self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be less than max_range_m ({self.max_range_m}): "
                             f"no ray would carve or mark anything")
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
        max_range = self.max_range_m if self.max_range_m is not None else sensor_max_range_m
        if self.truncation_m is not None and self.truncation_m < voxel:
            raise ConfigError(f"volume.truncation_m ({self.truncation_m} m) must be at least one voxel "
                              f"(volume.voxel_size_m {voxel} m; default {TRUNCATION_VOXELS} voxels): a thinner band "
                              f"leaves the TSDF no zero crossing to mesh")
        if self.truncation_m is not None and self.truncation_m > MAX_TRUNCATION_VOXELS * voxel:
            raise ConfigError(f"volume.truncation_m ({self.truncation_m:g} m) must be at most {MAX_TRUNCATION_VOXELS:g} "
                              f"voxels (volume.voxel_size_m {voxel:g} m; default {TRUNCATION_VOXELS:g}): the TSDF band "
                              f"pads the grid by it on every side (a 3 m room grows to a "
                              f"{3 + 2 * self.truncation_m:g} m grid)")
        if max_range is not None and not self.min_range_m < max_range:
            raise ConfigError(f"volume.min_range_m ({self.min_range_m} m) must be less than the max range "
                              f"({max_range} m, the sensor's): no ray would carve or mark anything")
        return self.model_copy(update={
            "voxel_size_m": voxel,
            "truncation_m": self.truncation_m if self.truncation_m is not None else TRUNCATION_VOXELS * voxel,
            "max_range_m": max_range,
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


class DecideConfig(SettingsModel):
    """Thresholds of the five query kinds and of the uncertainty (``driftmap decide``; the ``[decide]`` table)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    sweep_step_m: float | None = Field(None, gt=0.0, description="collision: the footprint is placed every this many metres along the path; None: half a voxel; never more than the footprint's smallest extent plus half a voxel (so no obstacle lies between two placements)")
    grasp_min_points: int = Field(30, ge=3, le=100_000_000, description="grasp: fewer map points than this inside the ROI is too_few_points")
    grasp_max_normal_spread_deg: float = Field(20.0, ge=0.0, le=90.0, description="grasp: the normal is unstable when the 90th percentile of the angles between the points' normals and the dominant normal exceeds this (deg)")
    normal_radius_m: float = Field(0.03, gt=0.0, description="grasp and foothold: a point's normal is fitted to its neighbours within this radius (m)")
    normal_max_neighbors: int = Field(64, ge=5, le=1000, description="grasp and foothold: at most this many neighbours per normal")
    normal_margin_m: float = Field(0.03, ge=0.0, description="grasp and foothold: no longer used (kept so that files giving it still load): since stop 54 the normals take their neighbours among all the map's voxels, so a region's border does not tilt them")
    normal_voxel_m: float | None = Field(0.01, gt=0.0, description="grasp and foothold: the normals are fitted on the region's points averaged per voxel of this size (m; each point takes its voxel's normal), so that the normal_max_neighbors nearest span about normal_radius_m however many frames overlap; None: on every full-resolution point (slow where frames overlap). The point counts always use every point")
    foothold_min_points: int = Field(30, ge=3, le=100_000_000, description="foothold: fewer map points than this in the patch is too_few_points")
    foothold_max_flatness_m: float = Field(0.02, gt=0.0, description="foothold: RMS distance of the patch's points from their plane above which the patch is uneven (m)")
    spread_radius_m: float = Field(0.05, gt=0.0, description="uncertainty: the map points within this radius of a decision's evidence point are grouped by frame (m)")
    spread_min_points: int = Field(5, ge=1, le=100_000_000, description="uncertainty: a frame takes part in the spread with at least this many points near the evidence")
    double_wall_reach_m: float = Field(0.3, ge=0.0, description="a double wall (diagnose) whose centre lies within this distance of a query's region is in reach (m)")
    range_limited_points: bool = Field(True, description="grasp, foothold, uncertainty: use only points within the volume's max range of their sensor (where the depth noise stays below 0.4 voxel)")


class DriftmapConfig(BaseSettings):
    """Everything configurable outside ``build.*``, with units in every name."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, env_nested_delimiter=ENV_DELIMITER, extra="forbid", allow_inf_nan=False)
    depth: DepthConfig = Field(default_factory=DepthConfig)
    map: MapConfig = Field(default_factory=MapConfig)
    volume: VolumeConfig = Field(default_factory=VolumeConfig)
    decide: DecideConfig = Field(default_factory=DecideConfig)

    @classmethod
    def load(cls, path: str | Path | None = None, **overrides: Any) -> DriftmapConfig:
        """Defaults, then the file (``.json`` or ``.toml``), then ``DRIFTMAP_*`` environment, then ``overrides``
        (the command line's flags, nested: ``depth={"depth_scale": 5000.0}``).

        Raises :class:`ConfigError` with one line per problem, each naming where the value came from (the file,
        the environment variable or the command line) and the key."""
        data = split_config_file(path)[0] if path is not None else {}
        if path is not None:
            for name, table in data.items():
                field = cls.model_fields.get(name)
                if field is not None and isinstance(field.annotation, type):
                    check_written_types(table, field.annotation, path, f"{name}.")
        _check_env_tables()
        try:
            # file values act as init values, which pydantic-settings ranks above the environment;
            # build from the environment first, then layer file and overrides so the order is documented
            env_only = cls()
        except ValidationError as exc:
            raise ConfigError(validation_problems(exc, lambda loc: "environment", env_names=True)) from exc
        env = _explicit(env_only)
        try:
            return cls(**_deep_merge(_deep_merge(data, env), overrides))
        except ValidationError as exc:
            def origin(loc: tuple[Any, ...]) -> str:
                if _has(overrides, loc):
                    return "command line"
                if _has(env, loc):
                    return "environment"
                return str(path) if path is not None else "defaults"
            raise ConfigError(validation_problems(exc, origin, env_names=True)) from exc

    def write(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.model_dump_json(indent=2) + "\n")
        return path


BUILD_TABLE = "build"
DIAGNOSE_TABLE = "diagnose"
"""``driftmap diagnose --config``'s table (:meth:`driftmap.diagnostics.report.DiagnoseConfig.load`); build ignores it."""
"""The table of a config file that holds ``driftmap build``'s settings."""

FLEET_TABLE = "fleet"
"""``driftmap batch --config``'s own table (:mod:`driftmap.fleet.config`): the other commands take a batch config as
it is and leave this table to batch (hostile trial 29 W2: they refused it as an unknown table)."""

GENERAL_TABLES = tuple(DriftmapConfig.model_fields)
"""The tables of a config file that are :class:`DriftmapConfig` (``depth``, ``map``, ``volume``, ``decide``)."""

_REMOVED_TABLES = {
    "preprocess": "per-frame processing is not part of 'driftmap build' (the store keeps full-resolution frames), so "
                  "there are no preprocess.* settings (the library's process_frame takes driftmap.config.PreprocessConfig)",
}


def check_written_types(table: Any, model: type[BaseModel], where: str | Path, prefix: str = "") -> None:
    """A config file's ``table`` (for ``model``) as the file wrote it: a number is written as a number (``0.1``, not
    the text ``"0.1"``, which pydantic would read as 0.1) and a flag as ``true`` / ``false``, in nested tables too.
    A :class:`ConfigError` naming the file (``where``) and the key (``prefix`` + key); other problems are left to
    the model, which names them. Not for the environment, whose values are always text."""
    if not isinstance(table, dict):
        return
    for key, value in table.items():
        field = model.model_fields.get(key) if isinstance(key, str) else None
        if field is None:
            continue
        kinds = _annotation_types(field.annotation)
        nested = [k for k in kinds if issubclass(k, BaseModel)]
        if nested:
            if not isinstance(value, dict) and not (value is None and type(None) in kinds):
                # a table's settings given one value (``loop_closure = false``): pydantic's message named no key, and
                # its origin was guessed as the environment (hostile trial 29 follow-up)
                raise ConfigError(f"{where}: {prefix}{key}: expected a table of settings ([{prefix}{key}] ...), got "
                                  f"{_shown_value(value)}")
            check_written_types(value, nested[0], where, f"{prefix}{key}.")
            continue
        if not kinds or not kinds <= {int, float, bool, type(None)} or (value is None and type(None) in kinds):
            continue  # text, names, enumerations, paths: text is theirs to judge
        flag = kinds & {int, float} == set()
        ok = isinstance(value, bool) if flag else isinstance(value, (int, float)) and not isinstance(value, bool)
        if ok:
            continue
        expected = "true or false" if flag else "a number"
        hint = ""
        if isinstance(value, str):
            hint = " (text, in quotes: write the number without quotes)" if not flag and _is_number_text(value) else \
                " (text, in quotes: write true or false without quotes)" if flag and value.strip().lower() in (
                    "true", "false") else " (text, in quotes)"
        raise ConfigError(f"{where}: {prefix}{key}: expected {expected}, got {_shown_value(value)}{hint}")


def _annotation_types(annotation: Any) -> set[type]:
    """The types of an annotation (``float | None`` -> {float, NoneType}); none for ``Literal`` and the like."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return {t for a in typing.get_args(annotation) for t in _annotation_types(a)}
    if typing.get_origin(annotation) is Annotated:
        return _annotation_types(typing.get_args(annotation)[0])
    return {annotation} if isinstance(annotation, type) else set()


def _is_number_text(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _shown_value(value: Any) -> str:
    """A value for an error line: the TOML / JSON spelling of true and false, long values shortened."""
    if isinstance(value, bool):
        return str(value).lower()
    text = repr(value)
    return text if len(text) <= 60 else f"{text[:40]}... ({len(text):,} characters)"


def read_config_file(path: str | Path) -> dict[str, Any]:
    """The top-level table of a ``.toml`` file, or the object of any other (JSON) file."""
    path = Path(path)
    is_toml = path.suffix.lower() == ".toml"
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (some editors write one) is not a setting
        data = tomllib.loads(text) if is_toml else json_loads_unique(text)
    except (OSError, ValueError, RecursionError) as exc:
        kind = "" if is_toml or path.suffix.lower() == ".json" else " (config files are read as TOML when named .toml, else as JSON)"
        raise ConfigError(f"{path}: cannot read config ({exc}){kind}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file holds an object of settings, not {type(data).__name__}")
    return data


COMMAND_TABLES: dict[str, tuple[str, ...]] = {
    "build": (BUILD_TABLE, "depth"),
    "merge": (BUILD_TABLE,),
    "diagnose": (DIAGNOSE_TABLE, "volume"),
    "export": ("map", "volume"),
    "decide": ("volume", "decide"),
}
"""The tables of a config file each command reads (``batch`` reads every one, and its own ``[fleet]``)."""


def refuse_unread_tables(path: str | Path, command: str) -> None:
    """A config file whose tables ``command`` never reads (:data:`COMMAND_TABLES`) is refused, naming the file, its
    tables and the ones the command reads: nothing in it would change the result (hostile trial 30 W3: a
    ``[map]``-only file was taken silently by build, diagnose, decide and merge, a ``[build]``-only one by export,
    while a ``[fleet]``-only one was refused). A file without any known table is a bare config, judged by the
    command's own loader."""
    data = read_config_file(path)
    known = (BUILD_TABLE, DIAGNOSE_TABLE, FLEET_TABLE, *GENERAL_TABLES)
    present = [t for t in known if t in data]
    reads = COMMAND_TABLES[command]
    if set(present) == {FLEET_TABLE}:
        raise ConfigError(f"{path}: holds only a [{FLEET_TABLE}] table, driftmap batch's settings, none of which "
                          f"applies here (driftmap batch --config takes it)")
    if not present or set(present) & set(reads) or set(data) - set(known):
        return  # a bare config, one the command reads, or an unknown table its loader names
    held = "] / [".join(present)
    raise ConfigError(f"{path}: holds only the [{held}] table{'s' if len(present) > 1 else ''}, none of which driftmap "
                      f"{command} reads (it reads [{'] / ['.join(reads)}]): nothing in the file would change its "
                      f"result (driftmap config --show lists each table's settings)")


def split_config_file(path: str | Path) -> tuple[dict[str, Any], dict[str, Any], tuple[str, ...]]:
    """``(general tables, build settings, the build settings' key prefix)`` of a config file.

    A file with a ``build``, ``depth`` or ``map`` table holds only such tables (anything else at its top level
    is refused, naming the file); a file with none of them is a bare build config (the whole file, prefix ``()``;
    else ``("build",)``)."""
    data = read_config_file(path)
    tables = {BUILD_TABLE, DIAGNOSE_TABLE, FLEET_TABLE, *GENERAL_TABLES, *_REMOVED_TABLES}
    if not tables & set(data):
        return {}, data, ()
    if FLEET_TABLE in data and not isinstance(data[FLEET_TABLE], dict):
        raise ConfigError(f"{path}: '{FLEET_TABLE}' must be a table of settings, not {type(data[FLEET_TABLE]).__name__}")
    if set(data) == {FLEET_TABLE}:
        refuse_unread_tables(path, "build")
    for name, why in _REMOVED_TABLES.items():
        if name in data:
            raise ConfigError(f"{path}: {name}: {why}")
    unknown = sorted(set(data) - tables)
    if unknown:
        raise ConfigError(f"{path}: unknown top-level settings {unknown} next to the [{BUILD_TABLE}] / "
                          f"[{DIAGNOSE_TABLE}] / [{'] / ['.join(GENERAL_TABLES)}] / [{FLEET_TABLE}] tables (build "
                          f"settings go into the [{BUILD_TABLE}] table)")
    for name in (BUILD_TABLE, *GENERAL_TABLES):
        if name in data and not isinstance(data[name], dict):
            raise ConfigError(f"{path}: '{name}' must be a table of settings, not {type(data[name]).__name__}")
    return {k: v for k, v in data.items() if k in GENERAL_TABLES}, data.get(BUILD_TABLE, {}), (BUILD_TABLE,)


def validation_problems(exc: ValidationError, origin: Any, *, prefix: tuple[str, ...] = (), env_names: bool = False) -> str:
    """One line per problem of a pydantic error: ``WHERE: KEY: what is wrong (got VALUE)``, no documentation
    links. ``origin(loc)`` names where the value came from (a file, "environment", "command line");
    ``env_names`` names the environment variable of a value from the environment."""
    lines = []
    errors = exc.errors(include_url=False)
    item_locs = {tuple(str(p) for p in e["loc"][:-1]) for e in errors if e["loc"]}
    for err in errors:
        loc = tuple(str(p) for p in err["loc"])
        if err["type"] == "too_short" and loc in item_locs:
            continue  # its items' errors said why: pydantic counts a list of refused items as too short as well
        key = ".".join(prefix + loc) or "(top level)"
        where = origin(loc) if callable(origin) else str(origin)
        if env_names and where == "environment":
            where = f"environment {ENV_PREFIX}{ENV_DELIMITER.join(prefix + loc).upper()}"
        kind = err["type"]
        if kind == "extra_forbidden":
            message = "unknown setting"
        else:
            message = str(err["msg"]).removeprefix("Value error, ").removeprefix("Assertion failed, ")
        value = err.get("input")
        got = "" if kind in ("extra_forbidden", "missing") or isinstance(value, (dict, list)) else f" (got {value!r})"
        lines.append(f"{where}: {key}: {message}{got}")
    return "\n".join(lines)


_ENV_FILE_ONLY = {
    DIAGNOSE_TABLE: "the diagnose settings are read from a config file's [diagnose] table (diagnose --config), not "
                    "from the environment",
}


def _check_env_tables() -> None:
    """``DRIFTMAP_X__...`` variables whose table X does not exist are refused (pydantic-settings ignores them);
    ``DRIFTMAP_BUILD__...`` are the build settings' (:func:`env_table`)."""
    known = {name.upper() for name in DriftmapConfig.model_fields} | {BUILD_TABLE.upper()}
    tables = known | {DIAGNOSE_TABLE.upper()}
    for name in sorted(os.environ):
        if not name.upper().startswith(ENV_PREFIX):
            continue
        if ENV_DELIMITER not in name:  # DRIFTMAP_MAP_EXPORT_VOXEL_SIZE_M: one underscore, ignored by the settings
            rest = name[len(ENV_PREFIX):]
            table = next((t for t in sorted(tables) if rest.upper().startswith(t + "_")), None)
            if table is not None:
                meant = f"{ENV_PREFIX}{table}{ENV_DELIMITER}{rest[len(table) + 1:]}"
                raise ConfigError(f"environment {name}: names no setting (a table and its key are joined by two "
                                  f"underscores: {meant}?)")
            continue
        table = name[len(ENV_PREFIX):].split(ENV_DELIMITER)[0].upper()
        if table not in known:
            why = _REMOVED_TABLES.get(table.lower()) or _ENV_FILE_ONLY.get(table.lower()) or (
                f"no such table (known: {', '.join(sorted(k.lower() for k in known))})")
            raise ConfigError(f"environment {name}: {table.lower()}: {why}")


def env_table(table: str) -> dict[str, Any]:
    """The ``DRIFTMAP_<TABLE>__KEY[__SUBKEY]`` environment variables as a nested dict (keys lower-case; a value
    starting with ``[`` or ``{`` is read as JSON, any other stays a string for the settings model to validate)."""
    _check_env_tables()
    head = f"{ENV_PREFIX}{table.upper()}{ENV_DELIMITER}"
    out: dict[str, Any] = {}
    for name in sorted(os.environ):
        if not name.upper().startswith(head):
            continue
        keys = name[len(head):].lower().split(ENV_DELIMITER)
        node = out
        for key in keys[:-1]:
            node = node.setdefault(key, {})
            if not isinstance(node, dict):
                raise ConfigError(f"environment {name}: {table}.{'.'.join(keys)}: conflicts with another variable")
        raw = os.environ[name]
        if raw.strip()[:1] in ("[", "{"):
            try:
                node[keys[-1]] = json.loads(raw)
            except (ValueError, RecursionError) as exc:
                raise ConfigError(f"environment {name}: {table}.{'.'.join(keys)}: not valid JSON ({exc})") from None
        else:
            node[keys[-1]] = raw
    return out


def merge_settings(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    """``top`` over ``base``, nested tables merged key by key."""
    return _deep_merge(base, top)


def has_setting(data: dict[str, Any], loc: tuple[str, ...]) -> bool:
    """Whether the nested ``data`` sets the key at ``loc``."""
    return _has(data, loc)


def _has(data: dict[str, Any], loc: tuple[str, ...]) -> bool:
    for part in loc:
        if not isinstance(data, dict) or part not in data:
            return False
        data = data[part]
    return True


def _explicit(model: BaseModel) -> dict[str, Any]:
    """Only the values that were set explicitly (here: by the environment), nested."""
    out: dict[str, Any] = {}
    for name in model.model_fields_set:
        value = getattr(model, name)
        out[name] = _explicit(value) if isinstance(value, BaseModel) else value
    return out


def _deep_merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        out[key] = _deep_merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out
