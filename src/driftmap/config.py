"""Typed, layered configuration (pydantic): defaults < config file (JSON or TOML) < environment < flags.

Environment variables use the prefix ``DRIFTMAP_`` and ``__`` between levels, e.g.
``DRIFTMAP_DEPTH__MAX_DEPTH_M=4.0``. The configuration that produced a result is written next to it.

One file can hold both: the ``depth`` / ``preprocess`` / ``map`` tables are :class:`DriftmapConfig`, a ``build``
table is ``driftmap build``'s :class:`~driftmap.pipeline.build.BuildConfig` (``driftmap config --file F`` shows
both, ``driftmap build --config F`` reads the ``build`` table; a file without one is a bare build config).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from driftmap.errors import ConfigError


class DepthConfig(BaseModel):
    """Depth-image validation."""

    model_config = ConfigDict(extra="forbid")
    min_depth_m: float = Field(0.1, ge=0.0, description="closest valid depth (m)")
    max_depth_m: float = Field(10.0, gt=0.0, description="depth at and beyond which pixels are rejected (m), like Open3D depth_trunc")
    check_scale: bool = Field(True, description="raise DepthScaleError when the depth scale puts the scene at an implausible distance")

    @model_validator(mode="after")
    def _range(self) -> DepthConfig:
        if self.max_depth_m <= self.min_depth_m:
            raise ValueError(f"max_depth_m ({self.max_depth_m}) must exceed min_depth_m ({self.min_depth_m})")
        return self


class PreprocessConfig(BaseModel):
    """Per-frame processing of sensor-frame points."""

    model_config = ConfigDict(extra="forbid")
    voxel_size_m: float | None = Field(None, gt=0.0, description="voxel size for per-frame downsampling (m); None keeps full resolution")
    statistical_outlier_neighbors: int | None = Field(None, ge=2, description="neighbours for statistical outlier removal; None disables it")
    statistical_outlier_std_ratio: float = Field(2.0, gt=0.0, description="std-dev multiple beyond which a point is an outlier")
    radius_outlier_min_points: int | None = Field(None, ge=1, description="minimum neighbours within radius_outlier_radius_m; None disables it")
    radius_outlier_radius_m: float = Field(0.05, gt=0.0, description="radius for radius outlier removal (m)")
    normals_k: int = Field(20, ge=3, le=200, description="nearest neighbours used for normals")


class MapConfig(BaseModel):
    """Fused map export."""

    model_config = ConfigDict(extra="forbid")
    export_voxel_size_m: float = Field(0.01, gt=0.0, description="voxel size of the fused, deduplicated map export (m)")


class DriftmapConfig(BaseSettings):
    """Everything configurable in driftmap, with units in every name."""

    model_config = SettingsConfigDict(env_prefix="DRIFTMAP_", env_nested_delimiter="__", extra="forbid")
    depth: DepthConfig = Field(default_factory=DepthConfig)
    preprocess: PreprocessConfig = Field(default_factory=PreprocessConfig)
    map: MapConfig = Field(default_factory=MapConfig)

    @classmethod
    def load(cls, path: str | Path | None = None, **overrides: Any) -> DriftmapConfig:
        """Defaults, then the file (``.json`` or ``.toml``), then ``DRIFTMAP_*`` environment, then ``overrides``."""
        data: dict[str, Any] = {}
        if path is not None:
            data = read_config_file(path)
            data.pop(BUILD_TABLE, None)  # driftmap build's settings (BuildConfig.load reads them)
        try:
            # file values act as init values, which pydantic-settings ranks above the environment;
            # build from the environment first, then layer file and overrides so the order is documented
            env_only = cls()
            merged = _deep_merge(_deep_merge(data, _explicit(env_only)), overrides)
            return cls(**merged)
        except ValidationError as exc:
            raise ConfigError(f"invalid configuration{f' in {path}' if path else ''}: {exc}") from exc

    def write(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.model_dump_json(indent=2) + "\n")
        return path


BUILD_TABLE = "build"
"""The table of a config file that holds ``driftmap build``'s settings."""


def read_config_file(path: str | Path) -> dict[str, Any]:
    """The top-level table of a ``.toml`` file, or the object of any other (JSON) file."""
    path = Path(path)
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot read config ({exc})") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file holds an object of settings, not {type(data).__name__}")
    return data


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
