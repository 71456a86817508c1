"""The settings of a batch: ``driftmap batch --config FILE``.

The file is a driftmap config file (JSON or TOML: the ``[build]``, ``[diagnose]``, ``[depth]``, ``[map]`` and
``[volume]`` tables that ``build``, ``diagnose`` and ``export`` read) with one more table, ``[fleet]``
(:class:`FleetSettings`): which exports each log gets, ground truth, the comparison before loop closure, threads.

The file without its ``[fleet]`` table is written to ``DIR/fleet_config.json`` (with a bare build config wrapped into
a ``[build]`` table), which is what every log's ``build`` and ``diagnose`` read, so a log's results are exactly those
of ``driftmap build --config DIR/fleet_config.json`` + ``diagnose --config DIR/fleet_config.json``.

:func:`config_hash` fingerprints everything that decides a log's results (the loaded settings, environment
overrides included, the log's own options, driftmap's version); ``--resume`` keeps a log only when its recorded hash
equals the current one.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError

from driftmap._version import __version__
from driftmap.config import (
    BUILD_TABLE,
    DIAGNOSE_TABLE,
    FLEET_TABLE,
    GENERAL_TABLES,
    DriftmapConfig,
    SettingsModel,
    Threads,
    read_config_file,
    validation_problems,
)
from driftmap.diagnostics.report import DiagnoseConfig
from driftmap.errors import ConfigError
from driftmap.fleet.inputs import LogSpec
from driftmap.pipeline.build import BuildConfig

__all__ = ["EXPORTS", "FLEET_TABLE", "BatchConfig", "FleetSettings", "config_hash", "load_batch_config"]

CONFIG_FILE = "fleet_config.json"
"""The batch's config without its ``[fleet]`` table, in ``DIR``: what each log's build and diagnose read."""

EXPORTS = ("trajectory", "map", "mesh", "octomap", "grid2d", "mcap", "report")
"""What a log's folder may get besides ``store/`` and ``diagnosis.json``: ``trajectory.tum`` (or ``.kitti``),
``map.ply``, ``mesh.ply``, ``octomap.bt``, ``grid2d.yaml`` + ``.pgm``, ``foxglove.mcap``, ``report/`` (the diagnose
figures)."""

Export = Literal["trajectory", "map", "mesh", "octomap", "grid2d", "mcap", "report"]


class FleetSettings(SettingsModel):
    """The ``[fleet]`` table of a batch config file."""

    exports: list[Export] = Field(default_factory=lambda: ["trajectory"], description="what each log's folder gets besides store/ and diagnosis.json: trajectory | map | mesh | octomap | grid2d | mcap | report")
    trajectory_format: Literal["tum", "kitti"] = Field("tum", description="format of the exported trajectory")
    ground_truth: Literal["auto", "none"] = Field("auto", description="auto: a log folder's groundtruth.txt (TUM: synthetic logs, TUM RGB-D) gives ATE when no --gt is listed for it; none: only listed --gt files")
    compare_before_loop_closure: bool = Field(True, description="diagnose also revision 0 (before loop closure) when the build made a loop-closure revision: smearing score before / after")
    loop_closure: bool = Field(True, description="false: build without loop closure (as build --no-loop-closure)")
    threads_per_log: Threads | None = Field(None, description="registration threads of each log's build (None: the machine's CPUs shared by the workers; with 1 every log gives the same poses, to the bit, as a sequential 'build --threads 1')")


@dataclass(frozen=True)
class BatchConfig:
    """A loaded batch config: the ``[fleet]`` settings, the other tables (as ``fleet_config.json`` holds them) and
    what they load to."""

    fleet: FleetSettings = field(default_factory=FleetSettings)
    tables: dict[str, Any] = field(default_factory=dict)
    """the file without ``[fleet]`` (a bare build config wrapped into ``build``); empty without a file"""
    build: BuildConfig = field(default_factory=BuildConfig)
    settings: DriftmapConfig = field(default_factory=DriftmapConfig)
    source: str | None = None
    """the file as given"""

    def write_tables(self, out_dir: Path) -> Path | None:
        """``DIR/fleet_config.json`` (None, and no file, without tables)."""
        path = out_dir / CONFIG_FILE
        if not self.tables:
            path.unlink(missing_ok=True)
            return None
        path.write_text(json.dumps(self.tables, indent=1, sort_keys=True) + "\n")
        return path

    def digest(self) -> str:
        """Fingerprint of the settings (before the per-log options: :func:`config_hash`)."""
        record = {"fleet": self.fleet.model_dump(mode="json"), "build": self.build.model_dump(mode="json"),
                  "settings": self.settings.model_dump(mode="json"), "diagnose": self.tables.get(DIAGNOSE_TABLE),
                  "driftmap": __version__}
        return hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()


def config_hash(config: BatchConfig, spec: LogSpec) -> str:
    """What decides a log's results, fingerprinted: the batch's settings and the log's input and options."""
    record = {"config": config.digest(), "log": spec.options_record()}
    return hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()[:32]


def _split(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(fleet table, the other tables)`` of a config file; a bare build config goes into a ``build`` table."""
    data = read_config_file(path)
    fleet = data.pop(FLEET_TABLE, {})
    if not isinstance(fleet, dict):
        raise ConfigError(f"{path}: '{FLEET_TABLE}' must be a table of settings, not {type(fleet).__name__}")
    known = {BUILD_TABLE, DIAGNOSE_TABLE, *GENERAL_TABLES}
    if data and not known & set(data):
        data = {BUILD_TABLE: data}
    return fleet, data


def _load_tables(tables: dict[str, Any], named: Path) -> tuple[BuildConfig, DriftmapConfig]:
    """The other tables loaded (and diagnose's checked) by the loaders ``build`` and ``diagnose`` use; their
    messages name ``named`` (the user's file), not the temporary copy they read."""
    if not tables:
        return BuildConfig(), DriftmapConfig.load()
    fd, tmp_name = tempfile.mkstemp(suffix=".json", prefix="driftmap-fleet-config-")
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(tables, f)
        problems = []
        loaded: list[Any] = []
        for load in (BuildConfig.load, DriftmapConfig.load, lambda p: DiagnoseConfig.load(p, DiagnoseConfig())):
            try:
                loaded.append(load(tmp))
            except ConfigError as exc:
                problems.append(str(exc).replace(str(tmp), str(named)))
        if problems:
            raise ConfigError("\n".join(dict.fromkeys(problems)))
        return loaded[0], loaded[1]
    finally:
        tmp.unlink(missing_ok=True)


def load_batch_config(path: str | Path | None) -> BatchConfig:
    """The batch config of ``path`` (None: the defaults and the ``DRIFTMAP_*`` environment). Every problem is a
    :class:`ConfigError` naming the file and the key, before any log is run."""
    if path is None:
        return BatchConfig(settings=DriftmapConfig.load())
    path = Path(path)
    fleet_data, tables = _split(path)
    problems = []
    fleet = FleetSettings()
    try:
        fleet = FleetSettings(**fleet_data)
    except ValidationError as exc:
        problems.append(validation_problems(exc, str(path), prefix=(FLEET_TABLE,)))
    try:
        build, settings = _load_tables(tables, path)
    except ConfigError as exc:
        problems.append(str(exc))
    if problems:
        raise ConfigError("\n".join(problems))
    return BatchConfig(fleet=fleet, tables=tables, build=build, settings=settings, source=str(path))
