"""What a store records about the build that made it (``build_source.json``, the odometry settings in
``build_summary.json``), and the checks that let ``build --resume`` continue only the same build."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Any

from driftmap.errors import ConfigError, StoreError
from driftmap.frame import PoseSource
from driftmap.pipeline.source_options import DEPTH_OPTION_SETTINGS, show_source_option
from driftmap.registration.odometry import OdometryConfig
from driftmap.sources.base import FrameSource
from driftmap.store.frame_store import FrameStore
from driftmap.store.layout import BUILD_SOURCE_FILE, BUILD_SUMMARY_FILE

logger = logging.getLogger(__name__)


def source_record(source: str | Path, src: FrameSource, poses: dict[str, Any] | None = None,
                   depth: dict[str, Any] | None = None, options: dict[str, Any] | None = None) -> dict[str, Any]:
    record = {"path": str(Path(source).resolve()), "format": src.format_name, "given": str(source)}
    if poses is not None:
        record["poses"] = poses
    if depth is not None:
        record["depth"] = {k: v for k, v in sorted(depth.items())}
    if options:  # which sensor / topic / pose stream of the log: a resume must read the same
        record["source_options"] = {k: list(v) if isinstance(v, tuple) else v for k, v in sorted(options.items())
                                    if k != "lenient"}
    return record


def poses_record(poses_file: str | Path | None, poses_from_source: bool, kitti_frame: str,
                  calib_file: str | Path | None) -> dict[str, Any]:
    """Where revision 0's poses come from (the coordinate frame of the stored frames): ``--resume`` must match."""
    if poses_file is not None:
        return {"mode": "file", "file": str(Path(poses_file).resolve()), "kitti_frame": kitti_frame,
                "calib": None if calib_file is None else str(Path(calib_file).resolve()),
                "sha256": _sha256(Path(poses_file))}
    return {"mode": "source" if poses_from_source else "odometry"}


def describe_poses(poses: dict[str, Any]) -> str:
    if poses.get("mode") == "file":
        extra = "" if poses.get("kitti_frame", "auto") == "auto" else f" --kitti-frame {poses['kitti_frame']}"
        extra += "" if poses.get("calib") is None else f" --calib {poses['calib']}"
        return f"--poses {poses.get('file')}{extra}"
    return {"source": "--poses-from-source (the source's own poses)", "odometry": "odometry (no --poses, no --poses-from-source)"}.get(
        str(poses.get("mode")), str(poses.get("mode")))


def check_recorded_source(out: Path, record: dict[str, Any]) -> dict[str, Any] | None:
    """``--resume``: refuse a source other than the one the store was built from (its resolved path or format
    differ). The record, or None when the store has none (built before the record existed): see
    :func:`check_stored_frames`."""
    file = out / BUILD_SOURCE_FILE
    try:
        recorded = json.loads(file.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError, RecursionError) as exc:
        raise StoreError(f"{file}: unreadable build source record ({exc})") from exc
    if recorded.get("path") != record["path"] or recorded.get("format") != record["format"]:
        raise ConfigError(
            f"{out}: cannot --resume from a different source: the store was built from {recorded.get('path')} "
            f"(format {recorded.get('format')}, recorded in {file}), the source given is {record['path']} "
            f"(format {record['format']}); resume with the same source or build into another --out")
    return recorded


def check_resume_settings(store: FrameStore, src: FrameSource, recorded: dict[str, Any] | None,
                           record: dict[str, Any]) -> None:
    """``--resume``: the poses of the new frames must be in the coordinate frame of the stored ones (the same
    pose mode: odometry, ``--poses FILE`` -- the same file -- or ``--poses-from-source``), and the depth images
    read the same way (the same ``depth.*`` options). A record from before these were recorded: the pose mode
    is checked against revision 0's pose source where that tells them apart."""
    out = store.path
    file = out / BUILD_SOURCE_FILE
    given = record["poses"]
    if recorded is not None and "poses" in recorded:
        if "sha256" not in recorded["poses"]:  # a record from before the file's content was recorded
            given = {k: v for k, v in given.items() if k != "sha256"}
        if {k: v for k, v in recorded["poses"].items() if k != "sha256"} == {k: v for k, v in given.items() if k != "sha256"} \
                and recorded["poses"] != given:
            raise ConfigError(
                f"{out}: cannot --resume: the pose file {given.get('file')} changed since the stored frames were placed "
                f"with it (sha256 {str(recorded['poses'].get('sha256'))[:12]}... then, {str(given.get('sha256'))[:12]}... "
                f"now, recorded in {file}); the new frames' poses would not be in the stored frames' coordinate frame. "
                f"Restore the file, or build into another --out")
        if recorded["poses"] != given:
            raise ConfigError(
                f"{out}: cannot --resume with different poses: the stored frames were placed with "
                f"{describe_poses(recorded['poses'])} (recorded in {file}), this build asks for {describe_poses(given)}; "
                f"their poses would be in different coordinate frames. Resume with the same pose option or build "
                f"into another --out")
    elif len(store):
        stored = store.ledger.revision(0).source
        mode = given["mode"]
        if mode == "odometry":
            fits = stored is PoseSource.ODOMETRY
        elif mode == "file":
            fits = stored is PoseSource.EXTERNAL_FILE
        else:
            fits = stored is not PoseSource.EXTERNAL_FILE and (
                stored is not PoseSource.ODOMETRY or src.frame(0).pose.source is PoseSource.ODOMETRY)
        if not fits:
            raise ConfigError(
                f"{out}: cannot --resume with different poses: the stored frames' revision-0 poses are "
                f"'{stored.value}', this build asks for {describe_poses(given)}; their poses would be in different "
                f"coordinate frames. Resume with the same pose option or build into another --out")
    if recorded is not None and recorded.get("source_options", {}) != record.get("source_options", {}):
        def show_options(options: dict[str, Any]) -> str:
            return ", ".join(show_source_option(k, v) for k, v in options.items()) or "none"
        raise ConfigError(
            f"{out}: cannot --resume with different source options: the stored frames were read with "
            f"{show_options(recorded.get('source_options', {}))} (recorded in {file}), this build with "
            f"{show_options(record.get('source_options', {}))}; resume with the same options or build into another --out")
    if recorded is not None and "depth" in recorded and recorded["depth"] != record["depth"]:
        def show(options: dict[str, Any]) -> str:
            return ", ".join(f"{DEPTH_OPTION_SETTINGS.get(k, k).split(' ')[0]}={v}" for k, v in options.items()) or "the source's defaults"
        raise ConfigError(
            f"{out}: cannot --resume with different depth settings: the stored frames were read with "
            f"{show(recorded['depth'])} (recorded in {file}), this build with {show(record['depth'])}; resume with "
            f"the same depth.* settings (config file, DRIFTMAP_DEPTH__* environment, --depth-scale) or build into "
            f"another --out")


def check_stored_frames(store: FrameStore, src: FrameSource, record: dict[str, Any]) -> None:
    """``--resume`` on a store without a source record: its first frame's sensor kind and (when it is a file
    that exists) the file it came from must fit the source given."""
    if len(store) == 0:
        return
    info = store.frame_info(int(store.frame_ids[0]))
    stored_kind = info.get("sensor_kind")
    given_kind = src.frame(0).sensor_kind.value if len(src) else None
    origin = (info.get("provenance") or {}).get("source_uri")
    origin_path = Path(origin) if origin else None
    source_path = Path(record["path"])
    foreign_origin = (origin_path is not None and origin_path.is_absolute() and origin_path.exists()
                      and origin_path.resolve() != source_path and source_path not in origin_path.resolve().parents)
    if (given_kind is not None and stored_kind != given_kind) or foreign_origin:
        raise ConfigError(
            f"{store.path}: cannot --resume from a different source: the store holds {stored_kind} frames from "
            f"{origin} (it has no {BUILD_SOURCE_FILE}), the source given is {record['path']} (format "
            f"{record['format']}, {given_kind} frames); resume with the same source or build into another --out")


def remove_new_store(out: Path, out_existed: bool, new_dirs: list[Path]) -> None:
    """Undo :meth:`FrameStore.create` of a build that failed before storing a frame: the store directory if this
    build made it (and the parents it made, when empty), else only the files it put into the empty folder."""
    try:
        if out_existed:
            for child in out.iterdir():
                shutil.rmtree(child) if child.is_dir() and not child.is_symlink() else child.unlink()
        else:
            shutil.rmtree(out)
            for parent in new_dirs[1:]:
                parent.rmdir()  # only when empty
    except OSError as exc:
        logger.warning("build failed: could not remove the empty store it created at %s (%s)", out, exc)
        return
    logger.warning("build failed before any frame was stored: removed the empty store it created at %s", out)


PRE_DEGENERATE_BRIDGE = {"tracking_degenerate_below": 0.0}
"""The KISS-ICP settings of builds recorded before ``tracking_degenerate_below`` existed: resumed without it."""
PRE_GICP_DEGENERATE_BRIDGE = {"gicp_degenerate_shift_m": None}
"""The ``gicp_map`` settings of builds recorded before ``gicp_degenerate_shift_m`` existed: resumed without it."""
PRE_PLANE_REFINE_KISS = {"kiss_refine_plane": False, "tracking_min_fitness": 0.5, **PRE_DEGENERATE_BRIDGE}
"""The KISS-ICP settings of builds recorded before ``kiss_refine_plane`` existed: resumed as they were built."""


def recorded_odometry(store: FrameStore) -> OdometryConfig | None:
    """The odometry settings an earlier build of ``store`` used (``build_summary.json``), for ``--resume``:
    defaults chosen from the scene are not chosen again (a store built before they were is resumed with its
    own settings)."""
    try:
        summary = json.loads((store.path / "build_summary.json").read_text())
        if "odometry_config" not in summary:  # written before the settings were recorded: the sensor's defaults
            recorded = OdometryConfig.for_sensor(store.frame(int(store.frame_ids[0])).sensor_kind).model_dump(mode="json")
            recorded = {k: v for k, v in recorded.items()
                        if k not in PRE_PLANE_REFINE_KISS and k not in PRE_GICP_DEGENERATE_BRIDGE}
        else:
            recorded = summary["odometry_config"]
        if recorded is None:
            return None
        if recorded.get("method") == "kiss" and "kiss_refine_plane" not in recorded:  # before the refinement
            recorded = {**recorded, **PRE_PLANE_REFINE_KISS}
        if recorded.get("method") == "kiss" and "tracking_degenerate_below" not in recorded:  # before the bridge
            recorded = {**recorded, **PRE_DEGENERATE_BRIDGE}
        if recorded.get("method") == "gicp_map" and "gicp_degenerate_shift_m" not in recorded:  # before its bridge
            recorded = {**recorded, **PRE_GICP_DEGENERATE_BRIDGE}
        return OdometryConfig.model_validate(recorded)
    except (OSError, ValueError, AttributeError):
        return None


def _sha256(path: Path) -> str | None:
    """The hex SHA-256 of a file's bytes (None when it cannot be read: reading it fails later with a clear error)."""
    import hashlib

    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def build_running(store: FrameStore) -> str | None:
    """What a process that holds the store's writer lock now is doing to it (a build, a correction, a merge still
    running), or None when no process writes it: a reader then sees a snapshot, and a store without its summary is
    not an interrupted build (hostile trial 25 W4: it was called interrupted, and the `--resume` it advised was
    refused as another process appending)."""
    from driftmap.store.layout import LOCK_FILE
    from driftmap.store.lock import writer_alive

    if not writer_alive(store.path):
        return None
    try:
        pid = (store.path / LOCK_FILE).read_text().strip()
    except OSError:
        pid = ""
    who = f"process {pid}" if pid.isdigit() else "another process"
    return (f"{who} is writing this store now ({len(store)} frames so far): what is read is a snapshot of it; read it "
            f"again when that process has finished")


def interrupted_build(store: FrameStore) -> str | None:
    """What an interrupted ``build`` left, with the command that finishes it; None for a finished build or a store no
    build made. A build writes ``build_source.json`` first and ``build_summary.json`` (with its frame count) last, after
    loop closure: no summary, or one counting other frames than the store holds (a killed ``--resume``), is an
    unfinished build (hostile trial 17 W2: it read as a finished store everywhere). A build still running is not
    interrupted (:func:`build_running`): None."""
    if build_running(store) is not None:
        return None
    try:
        record = json.loads((store.path / BUILD_SOURCE_FILE).read_text())
    except (OSError, ValueError, RecursionError):
        return None
    try:
        summary = json.loads((store.path / BUILD_SUMMARY_FILE).read_text())
    except FileNotFoundError:
        summary = None
    except (OSError, ValueError, RecursionError):
        summary = {}
    source = record.get("path", "SOURCE") if isinstance(record, dict) else "SOURCE"
    finish = f"finish it with `driftmap build {source} --out {store.path} --resume` (and the options it was started with)"
    if summary is None:
        return (f"its build was interrupted: {len(store)} frames stored, no {BUILD_SUMMARY_FILE} (loop closure and the "
                f"given-pose check did not run); {finish}")
    recorded = summary.get("n_frames") if isinstance(summary, dict) else None
    lost = len(store.loss.frame_ids)
    if lost and isinstance(recorded, int) and len(store) < recorded <= len(store) + lost:  # hostile trial 19 W4
        return None  # not an interrupted build: frames lost to damage (`info` names them; --resume stores them again)
    if recorded != len(store):
        return (f"a build --resume was interrupted: {len(store)} frames stored, the last finished build recorded "
                f"{recorded} in {BUILD_SUMMARY_FILE}; {finish}")
    return None


def recorded_inputs(store_path: str | Path) -> list[tuple[Path, str]]:
    """What the store at ``store_path`` was built from, as ``build_source.json`` records it: ``(path, what)`` for the
    source (a folder or a log) and any pose / calibration file (empty when nothing is recorded or it is unreadable).
    An export must not replace them: ``--resume`` and ``--poses-from-source`` read them again."""
    try:
        record = json.loads((Path(store_path) / BUILD_SOURCE_FILE).read_text())
    except (OSError, ValueError, RecursionError):
        return []
    if not isinstance(record, dict):
        return []
    out = []
    if isinstance(record.get("path"), str):
        out.append((Path(record["path"]), "the source it was built from"))
    poses = record.get("poses") if isinstance(record.get("poses"), dict) else {}
    for key, what in (("file", "the --poses file it was built with"), ("calib", "the --calib file it was built with")):
        if isinstance(poses.get(key), str):
            out.append((Path(poses[key]), what))
    return out
