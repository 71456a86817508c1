"""One log of a batch: ``build`` -> ``diagnose`` -> the exports the config asks for, into a temporary folder that
is renamed to ``DIR/<name>/`` when everything is written (:mod:`driftmap.fleet.folders`).

:func:`run_log` is what a Ray task runs (:mod:`driftmap.fleet.runner`), and a plain function: called in a loop it
is a sequential batch. It never raises for a log that cannot be processed: a :class:`~driftmap.errors.DriftmapError`
(bad input, an unreadable file), an ``OSError`` or any other exception becomes the log's ``failed`` row with the
error's type and message. Only an interruption (``KeyboardInterrupt``, as ``ray.cancel`` delivers it) propagates,
after the temporary folder is removed.

Each log's build and diagnose run with the library's defaults for the sensor, the batch config's tables
(``DIR/fleet_config.json``) and ``threads`` registration threads; with one thread a log gives, to the bit, what
``driftmap build --threads 1 --config DIR/fleet_config.json`` + ``driftmap diagnose --config ...`` give.
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import shutil
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Self

import numpy as np

from driftmap._version import __version__
from driftmap.errors import DriftmapError
from driftmap.fleet.config import BatchConfig, config_hash
from driftmap.fleet.folders import RESULT_FILE, input_fingerprint, publish, temp_folder
from driftmap.fleet.inputs import LogSpec

__all__ = ["LOG_FILE", "LogHook", "empty_row", "failed_row", "run_log"]

LOG_FILE = "log.txt"
"""The warnings of a log's build and diagnose, in its folder."""

LogHook = Callable[[LogSpec, str], None]
"""``hook(spec, stage)``, called in the worker as a log's task reaches each stage: ``start``, ``built`` (the store is
written), ``diagnosed`` (diagnose and exports written, not yet published). Tests use it to kill a worker mid-task."""

logger = logging.getLogger(__name__)


def empty_row(spec: LogSpec, status: str) -> dict[str, Any]:
    """A row of ``fleet.json`` with nothing measured yet: the contract's keys, then the extra ones."""
    return {"name": spec.name, "input": spec.input, "status": status, "error": None, "frames": 0, "time_s": 0.0,
            "ate_rmse_m": None, "drift_percent_per_m": None, "fraction_flagged": None, "smearing_score_m": None,
            "error_type": None, "duration_s": None, "drift_deg_per_m": None, "revisit_fraction": None,
            "smearing_score_before_m": None, "fraction_flagged_before": None, "loops_accepted": None,
            "loop_revision": None, "valid": None, "threads": None, "folder": None, "ground_truth_error": None}


def failed_row(spec: LogSpec, error: str, error_type: str, time_s: float) -> dict[str, Any]:
    row = empty_row(spec, "failed")
    row.update(error=error, error_type=error_type, time_s=round(time_s, 3))
    return row


def _ground_truth(spec: LogSpec, config: BatchConfig) -> tuple[str | None, str | None]:
    """The ground truth of a log: its listed ``--gt``, else (``ground_truth = "auto"``) a ``groundtruth.txt`` in
    its folder (TUM: the synthetic logs and TUM RGB-D folders have one)."""
    if spec.gt is not None:
        return spec.gt, spec.gt_format
    candidate = Path(spec.input) / "groundtruth.txt"
    if config.fleet.ground_truth == "auto" and candidate.is_file():
        return str(candidate), "tum"
    return None, None


def _observed_band(layers: Any) -> tuple[float, float]:
    """Every height the volumetric layers observed (``export --grid2d``'s default band)."""
    g = layers.grid
    observed = np.flatnonzero((layers.state_grid() >= 0).any(axis=(0, 1)))
    z = (np.asarray(g.origin_index[2]) + observed + 0.5) * g.voxel_size_m
    return (float(z.min()), float(z.max())) if len(z) else (float(g.min_m[2]), float(g.max_m[2]))


def _exports(store: Any, folder: Path, config: BatchConfig, layers: Any) -> dict[str, str]:
    """The exports ``[fleet] exports`` asks for, of the store's head revision, as ``driftmap export`` writes them."""
    exports, rev = set(config.fleet.exports), store.head
    files: dict[str, str] = {}
    voxel = config.settings.map.export_voxel_size_m
    if "trajectory" in exports:
        path = folder / f"trajectory.{config.fleet.trajectory_format}"
        store.export_trajectory(path, revision=rev, format=config.fleet.trajectory_format)
        files["trajectory"] = path.name
    if "map" in exports:
        from driftmap.map.view import MapView

        MapView.from_store(store, rev).write(folder / "map.ply", voxel_size_m=voxel, provenance=voxel is not None)
        files["map"] = "map.ply"
    if exports & {"mesh", "octomap", "grid2d", "mcap"}:
        from driftmap.volume import VolumeLayers
        from driftmap.volume.export import write_grid2d, write_mesh, write_octomap

        layers = layers if layers is not None else VolumeLayers.from_store(store, rev, config.settings.volume)
        weight = config.settings.map.mesh_weight_threshold
        if "mesh" in exports:
            write_mesh(layers, folder / "mesh.ply", flag="[fleet] exports mesh", weight_threshold=weight)
            files["mesh"] = "mesh.ply"
        if "octomap" in exports:
            write_octomap(layers, folder / "octomap.bt", flag="[fleet] exports octomap")
            files["octomap"] = "octomap.bt"
        if "grid2d" in exports:
            write_grid2d(layers, folder / "grid2d.yaml", _observed_band(layers), flag="[fleet] exports grid2d")
            files["grid2d"] = "grid2d.yaml"
        if "mcap" in exports:
            from driftmap.export.foxglove import export_foxglove_mcap

            export_foxglove_mcap(store, folder / "foxglove.mcap", revision=rev, volume=layers,
                                 map_voxel_size_m=voxel if voxel is not None else 0.02,
                                 grid2d_band_m=_observed_band(layers), mesh_weight_threshold=weight)
            files["mcap"] = "foxglove.mcap"
    return files


def _measure(row: dict[str, Any], result: Any, data: dict[str, Any]) -> None:
    """The row's figures from the build result and the diagnosis JSON."""
    att = data.get("drift_rate") or {}
    frames = data.get("frames")
    stamps = [f["stamp_ns"] for f in frames if "stamp_ns" in f] if isinstance(frames, list) else []
    comparison = data.get("comparison") or {}
    row.update(
        frames=int(result.n_frames), ate_rmse_m=(data.get("trajectory") or {}).get("ate_rmse_m"),
        drift_percent_per_m=att.get("percent_per_m"), drift_deg_per_m=att.get("deg_per_m"),
        fraction_flagged=data["double_wall"]["fraction_flagged"], smearing_score_m=data.get("smearing_score_m"),
        revisit_fraction=data.get("revisit_fraction"), valid=data.get("valid"),
        smearing_score_before_m=comparison.get("smearing_score_m"),
        fraction_flagged_before=comparison.get("fraction_flagged"),
        duration_s=(max(stamps) - min(stamps)) / 1e9 if len(stamps) > 1 else None,
        loops_accepted=int(result.loops_accepted), loop_revision=result.loop_revision)


def _process(spec: LogSpec, config: BatchConfig, folder: Path, threads: int, config_file: Path | None,
             hook: LogHook) -> dict[str, Any]:
    """Build, diagnose and export one log into ``folder``; its row (status ``ok``)."""
    from driftmap.pipeline.build import build
    from driftmap.pipeline.diagnose import run_diagnose
    from driftmap.store.frame_store import FrameStore

    result = build(spec.input, folder / "store", format=spec.format,
                   config=config.build.model_copy(update={"num_threads": threads}), poses_file=spec.poses,
                   poses_from_source=spec.poses_from_source, loop_closure=config.fleet.loop_closure,
                   frames=spec.frames, depth=config.settings.depth, source_options=spec.source_options())
    hook(spec, "built")
    gt, gt_format = _ground_truth(spec, config)
    compare = 0 if config.fleet.compare_before_loop_closure and result.loop_revision is not None else None
    report = folder / "report" if "report" in config.fleet.exports else None
    gt_error = None
    with FrameStore.open(folder / "store") as store:
        def diagnose(gt: str | None) -> Any:
            return run_diagnose(store, folder / "diagnosis.json", gt=gt, gt_format=gt_format if gt else None,
                                report_dir=report,
                                compare_revision=compare, config_file=config_file,
                                volume_config=config.settings.volume)

        try:
            run = diagnose(gt)
        except DriftmapError as exc:
            if spec.gt is not None or gt is None or gt not in str(exc):
                raise
            # the ground truth "auto" found is optional: the log is diagnosed without it, and the row says why
            # (trial 24 W7: a 1-frame log failed whole over its ATE)
            gt_error = (f"{exc}; this ground truth is the log folder's groundtruth.txt, taken because [fleet] "
                        f"ground_truth = \"auto\": the log was diagnosed without it (no ATE); set [fleet] "
                        f"ground_truth = \"none\" in the --config file to leave it out")
            logger.warning("%s: %s", spec.name, gt_error)
            run = diagnose(None)
        files = _exports(store, folder, config, run.volume)
    hook(spec, "diagnosed")
    row = empty_row(spec, "ok")
    _measure(row, result, run.data)
    row.update(threads=threads, folder=spec.name, exports=files, ground_truth_error=gt_error)
    return row


class _FileLog:
    """The driftmap warnings of one log, written to its ``log.txt`` while it runs."""

    def __init__(self, path: Path):
        self.handler = logging.FileHandler(path, encoding="utf-8")
        self.handler.setLevel(logging.INFO)
        self.handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        self.logger = logging.getLogger("driftmap")

    def __enter__(self) -> Self:
        self.level = self.logger.level
        self.logger.addHandler(self.handler)
        if self.logger.getEffectiveLevel() > logging.INFO:
            self.logger.setLevel(logging.INFO)
        return self

    def __exit__(self, *exc: object) -> None:
        self.logger.removeHandler(self.handler)
        self.logger.setLevel(self.level)
        self.handler.close()


def _limit_threads(threads: int) -> int:
    """Numba's kernels use at most ``threads`` threads (the other workers have the other CPUs); returns the count
    before."""
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    return before


def run_log(spec: LogSpec, config: BatchConfig, out_dir: str | Path, *, threads: int = 1,
            config_file: str | Path | None = None, hook: LogHook | None = None) -> dict[str, Any]:
    """Process one log into ``out_dir/<name>/`` and return its ``fleet.json`` row (``ok`` or ``failed``).

    ``config_file``: the batch's tables (``DIR/fleet_config.json``) for diagnose. ``threads``: registration (and
    numba) threads. ``hook``: called first (see :data:`LogHook`)."""
    out_dir = Path(out_dir)
    t0 = time.perf_counter()
    hook = hook or (lambda spec, stage: None)
    hook(spec, "start")
    numba_threads = _limit_threads(threads)
    folder = temp_folder(out_dir, spec.name)
    fingerprint = input_fingerprint(spec.input_paths())  # before reading: a change while it runs shows next time
    published = False
    try:
        with _FileLog(folder / LOG_FILE):
            row = _process(spec, config, folder, threads, None if config_file is None else Path(config_file), hook)
        row["time_s"] = round(time.perf_counter() - t0, 3)
        record = {"row": row, "config_hash": config_hash(config, spec), "input_fingerprint": fingerprint,
                  "threads": threads, "driftmap": __version__,
                  "finished": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                  "host": socket.gethostname(), "pid": os.getpid()}
        (folder / RESULT_FILE).write_text(json.dumps(record, indent=1) + "\n")
        publish(folder, out_dir / spec.name)
        published = True
        return row
    except Exception as exc:  # noqa: BLE001 - any failure is this log's row; the other logs go on
        # the temporary folder is gone when the row is read: name the log's final folder instead
        message = (str(exc) or repr(exc)).replace(str(folder), str(out_dir / spec.name))
        logger.info("%s: failed: %s: %s", spec.name, type(exc).__name__, message)
        return failed_row(spec, message, type(exc).__name__, time.perf_counter() - t0)
    finally:
        _limit_threads(numba_threads)
        if not published:
            shutil.rmtree(folder, ignore_errors=True)
