"""``driftmap diagnose`` as one library call: sample the store, diagnose a revision (and optionally a second one to
compare), verify the regions, write the JSON and the report figures, and return what was found.

The command line only parses its flags, opens the store, calls :func:`run_diagnose` and renders the result
(:mod:`driftmap.cli.diagnose_cmds`); a navigation stack or a batch job calls the same function.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from driftmap.diagnostics.double_wall import DiagnosticCloud
from driftmap.diagnostics.report import (
    GT_FORMATS,
    DiagnoseConfig,
    Diagnosis,
    diagnose_store,
    write_report,
)
from driftmap.errors import ConfigError, DriftmapError
from driftmap.pipeline.pose_files import read_ground_truth
from driftmap.store.frame_store import FrameStore

ProgressCallback = Callable[[str, int, int | None], None]
"""``progress(stage, done, total)``: stages ``sampling frames``, ``diagnosing``, ``verifying``."""

__all__ = ["GT_FORMATS", "DiagnoseRun", "diagnose_config", "diagnosis_json", "run_diagnose"]


@dataclass
class DiagnoseRun:
    """What :func:`run_diagnose` found and wrote."""

    result: Diagnosis
    """the diagnosis of the requested revision"""
    other: Diagnosis | None
    """the diagnosis of ``compare_revision``, if one was asked for"""
    data: dict[str, Any]
    """the JSON document written to ``json_path``"""
    files: dict[str, Path] = field(default_factory=dict)
    """the report figures, by name (empty without ``report_dir``)"""


def diagnose_config(store: FrameStore, config_file: str | Path | None = None,
                    points_per_frame: int | None = None) -> DiagnoseConfig:
    """The scene's defaults for ``store`` (:meth:`DiagnoseConfig.for_store`), then a config file's ``[diagnose]``
    table, then ``points_per_frame``."""
    cfg = DiagnoseConfig.for_store(store)
    if config_file is not None:
        cfg = DiagnoseConfig.load(config_file, cfg)
    if points_per_frame is not None:
        cfg = cfg.model_copy(update={"sampling": cfg.sampling.model_copy(update={"points_per_frame": points_per_frame})})
    return cfg


def run_diagnose(store: FrameStore, json_path: str | Path, *, revision: int | None = None,
                 gt: str | Path | None = None, gt_format: str | None = None, report_dir: str | Path | None = None,
                 compare_revision: int | None = None, points_per_frame: int | None = None, kitti_frame: str = "auto",
                 calib: str | Path | None = None, verify: bool = False, config_file: str | Path | None = None,
                 progress: ProgressCallback | None = None) -> DiagnoseRun:
    """Diagnose ``revision`` (default: the head) of an open ``store`` and write the JSON to ``json_path`` (and the
    figures to ``report_dir``).

    ``gt`` (``gt_format`` tum | kitti | redwood | 4x4; ``kitti_frame`` / ``calib`` for a KITTI file): ground truth for
    ATE / RPE. ``compare_revision``: also diagnosed, its score added as ``comparison`` and to the report. ``verify``:
    every double-wall region re-measured from the full-resolution frames (``verification``). ``config_file``: its
    ``[diagnose]`` table over the scene's defaults. Raises :class:`ConfigError` for flags that do not fit together
    and :class:`DriftmapError` for an empty store, before any work."""
    tick = progress or (lambda stage, done, total: None)
    if len(store) == 0:
        raise DriftmapError(f"{store.path}: the store has no frames")
    if gt is None and (kitti_frame != "auto" or calib is not None or gt_format is not None):
        raise ConfigError("--gt-format / --kitti-frame / --calib describe the --gt FILE; give one")
    cfg = diagnose_config(store, config_file, points_per_frame)
    ground_truth = (read_ground_truth(store, gt, gt_format or "tum", kitti_frame=kitti_frame, calib_file=calib)
                    if gt is not None else None)
    t0 = time.perf_counter()
    cloud = DiagnosticCloud.from_store(store, cfg.sampling,
                                       progress=lambda stage, done, total: tick("sampling frames", done, len(store)))
    sampling_s = time.perf_counter() - t0
    tick("diagnosing", 0, None)
    result = diagnose_store(store, revision, config=cfg, cloud=cloud, ground_truth=ground_truth)
    result.seconds["sampling"] = sampling_s
    other = (diagnose_store(store, compare_revision, config=cfg, cloud=cloud, ground_truth=ground_truth)
             if compare_revision is not None else None)
    if verify:
        from driftmap.diagnostics.verify import verify_regions

        tick("verifying", 0, len(result.double_walls.regions))
        t0 = time.perf_counter()
        checks = verify_regions(store, result.revision, result.double_walls.regions)
        result.seconds["verify"] = time.perf_counter() - t0
        result = dataclasses.replace(result, verification=checks)
    data = diagnosis_json(result, other)
    json_path = Path(json_path)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(data, indent=1) + "\n")
    files: dict[str, Path] = {}
    if report_dir is not None:
        compare = {f"revision {other.revision}": other, f"revision {result.revision}": result} if other is not None else None
        files = write_report(report_dir, result, compare=compare)
    return DiagnoseRun(result, other, data, files)


def diagnosis_json(result: Diagnosis, other: Diagnosis | None = None) -> dict[str, Any]:
    """The JSON document of ``driftmap diagnose --json``: the diagnosis and, with ``other``, its ``comparison``."""
    data = result.to_json()
    if other is not None:
        data["comparison"] = {"revision": other.revision, "smearing_score_m": other.to_json()["smearing_score_m"],
                              "fraction_flagged": other.double_walls.fraction_flagged}
    return data
