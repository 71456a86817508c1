"""``driftmap build``: frames from any source -> validated -> odometry (or given poses) -> stored with the
pose that produced them (revision 0) -> keyframes, verified loop closures -> GTSAM pose graph -> a new
ledger revision (``loop_closure``) -> the map re-transformed through the store's ``apply``.

Library code: progress goes to a callback, numbers into :class:`BuildResult`; the CLI prints.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from driftmap import geometry
from driftmap.config import DepthConfig
from driftmap.errors import ConfigError, DriftmapError, SourceError, StoreError
from driftmap.frame import Frame, PoseEstimate, PoseSource, SensorKind
from driftmap.posegraph import Optimizer, PoseGraph, PoseGraphResult, RobustKernel
from driftmap.preprocess.scene import lidar_frames, sample_positions, scene_reach
from driftmap.registration.loops import (
    CandidateKind,
    Keyframe,
    LoopCandidate,
    LoopClosureConfig,
    find_loops,
    gap_threshold,
    loop_gap,
    make_keyframe,
    select_keyframes,
)
from driftmap.registration.odometry import GicpMapOdometry, KissOdometry, OdometryConfig, OdometryMethod, make_odometry
from driftmap.registration.pairwise import register_prepared, relative_pose
from driftmap.sources.base import BUILD_SOURCE_FILE, FrameSource, accepted_options, open_source, registered_formats
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import detect_trajectory_format, has_stamps, read_trajectory

logger = logging.getLogger(__name__)

#: (stage, done, total) -- total None when unknown
ProgressCallback = Callable[[str, int, int | None], None]


DEFAULT_POSES_MAX_DT_NS = 20_000_000
"""A ``--poses`` TUM row matches a frame within this (20 ms, as TUM's ``associate.py``)."""


class BuildConfig(BaseModel):
    """Everything ``build`` decides; saved next to the store as ``build_config.json``."""

    model_config = ConfigDict(extra="forbid")
    pixel_stride: int | None = Field(None, ge=1, description="depth images: keep every n-th pixel (None: 2 for images >= 640 px wide, else 1)")
    odometry: OdometryConfig | None = Field(None, description="odometry settings (None: defaults for the sensor kind, LiDAR lengths scaled to the scene)")
    loop_closure: LoopClosureConfig = Field(default_factory=LoopClosureConfig)
    loop_kernel: RobustKernel = Field(RobustKernel.CAUCHY, description="robust kernel on loop edges")
    optimizer: Optimizer = Field(Optimizer.LM, description="pose-graph optimiser")
    odometry_edge_max_disagreement_m: float = Field(0.1, gt=0.0, description="GICP may refine an odometry edge by at most this (m)")
    fallback_sigma_translation: float = Field(0.02, gt=0.0, description="odometry edge sigma when registration fails: fraction of the motion + 1 cm")
    fallback_sigma_rotation_deg: float = Field(1.0, gt=0.0, description="odometry edge rotation sigma when registration fails (deg)")
    resume_seed_frames: int = Field(10, ge=1, description="stored frames used to re-seed odometry on --resume")
    odometry_edge_window: int = Field(3, ge=1, description="pose graph: each keyframe is linked to the next this many keyframes")
    odometry_edges: Literal["auto", "trajectory", "registration"] = Field(
        "auto", description="odometry edge measurement: the revision-0 relative pose (trajectory), the keyframe GICP (registration), "
                            "or auto (trajectory for frame-to-map odometry that keeps its whole map, else registration)")
    depth_scale_error: float = Field(1.0, gt=0.0, description="diagnostics experiment: scale every frame's ranges by this factor before odometry and storing (1 = none)")
    focal_length_error: float = Field(1.0, gt=0.0, description="diagnostics experiment: depth cameras as if back-projected with this times the true focal length (1 = none)")
    num_threads: int | None = Field(None, ge=1, description="registration threads of the odometry and the loop closure (overrides odometry.num_threads and loop_closure.num_threads); 1: the same input gives the same poses, every revision, to the bit")
    information_calibration_iterations: int = Field(10, ge=0, description="pose graph: at most this many variance-component re-weighting rounds (they stop once no group's scale changes by more than 5 %)")

    @classmethod
    def load(cls, path: str | Path) -> BuildConfig:
        """A build config file (JSON or TOML): its ``build`` table, next to which only the general tables
        (``depth``, ``map``: :class:`driftmap.config.DriftmapConfig`, read by :meth:`DriftmapConfig.load`) may
        stand; or, without any of these tables, the whole file. Problems are :class:`ConfigError`, one line each,
        naming the file and the key."""
        from pydantic import ValidationError

        from driftmap.config import split_config_file, validation_problems

        _, data, prefix = split_config_file(path)
        try:
            return cls(**data)
        except ValidationError as exc:
            raise ConfigError(validation_problems(exc, str(path), prefix=prefix)) from exc


@dataclass
class BuildResult:
    store: str
    n_frames: int
    n_frames_new: int
    mean_invalid_fraction: float | None
    pose_source: str
    odometry_fps: float | None
    n_keyframes: int = 0
    loops_tried: int = 0
    loops_accepted: int = 0
    loops_rejected_by_graph: int = 0
    graph_error_before: float | None = None
    graph_error_after: float | None = None
    loop_revision: int | None = None
    max_correction_m: float | None = None
    max_correction_deg: float | None = None
    seconds_per_stage: dict[str, float] = field(default_factory=dict)
    loops: list[dict[str, Any]] = field(default_factory=list)
    odometry_edges: int = 0
    information_scale: dict[str, float] = field(default_factory=dict)
    source: dict[str, Any] | None = None
    """What the store was built from (resolved path, format, the path as given); see ``build_source.json``."""
    odometry_config: dict[str, Any] | None = None
    """The odometry settings this run used (``[build.odometry]``, or the defaults for the sensor and scene)."""
    scene_reach: dict[str, Any] | None = None
    """How far the LiDAR scene reaches (:class:`driftmap.preprocess.scene.SceneReach`: the median over frames spread
    across the log of their 99th range percentile, which scaled the odometry's default lengths); None when the
    lengths were not chosen from the scene (depth cameras, a config, a resumed build)."""
    tracking: dict[str, Any] = field(default_factory=lambda: tracking_summary(None))
    """How the odometry's registrations went (:func:`tracking_summary`): counts per status, the flagged and the
    recovered frames with their reasons, fitness and degeneracy, and one record per frame."""
    loop_closure_config: dict[str, Any] | None = None
    """The loop-closure settings this run used: ``[build.loop_closure]``'s explicit ones over the defaults for the
    sensor (LiDAR: :meth:`LoopClosureConfig.for_lidar`); None without loop closure."""

    @property
    def frames_per_second(self) -> float:
        total = sum(self.seconds_per_stage.values())
        return self.n_frames_new / total if total > 0 else float("nan")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["frames_per_second"] = self.frames_per_second
        return d


#: the depth options (``DepthConfig.source_options``) and the setting that names each in messages
_DEPTH_OPTION_SETTINGS = {"min_depth_m": "depth.min_depth_m", "max_depth_m": "depth.max_depth_m",
                          "depth_scale": "depth.depth_scale (--depth-scale)", "sensor_range_m": "depth.check_scale = false",
                          "intrinsics": "depth.intrinsics (--intrinsics)"}


def _detect_format(path: Path, format: str | None) -> str | None:
    if format is not None:
        return format
    for spec in registered_formats().values():
        try:
            if spec.detect(path):
                return spec.name
        except Exception:  # noqa: BLE001 - detectors must not hide each other
            continue
    return None


#: source options the command line offers (``build`` / ``convert``) and the flag that sets each
SOURCE_OPTION_FLAGS = {"sensor": "--sensor", "topic": "--topic", "pose_from_tf": "--pose-from-tf",
                       "pose_from_odometry": "--pose-from-odometry", "lenient": "--lenient", "period_ns": "--period-s"}
#: why a format may not take a source option, added to the refusal
_SOURCE_OPTION_REFUSALS = {"period_ns": "--period-s sets the stamps of a folder of PLY / PCD clouds (cloud_folder) that "
                                        "has none; format {fmt} stamps its frames itself (docs/sources-datasets.md)"}


def show_source_option(name: str, value: Any) -> str:
    """A source option as the command line gives it (``--period-s 0.5`` for ``period_ns=500000000``)."""
    if name == "period_ns":
        return f"--period-s {int(value) / 1e9:g}"
    return f"{SOURCE_OPTION_FLAGS.get(name, name)} {value}"


def source_params(path: Path, format: str | None) -> tuple[str | None, frozenset[str]]:
    """The format of ``path`` (given or detected) and the options its opener takes."""
    fmt = _detect_format(path, format)
    opener = registered_formats()[fmt].open if fmt in registered_formats() else None
    return fmt, accepted_options(opener) if opener is not None else frozenset()


def check_source_options(path: Path, format: str | None, options: dict[str, Any]) -> None:
    """Refuse source options (``SOURCE_OPTION_FLAGS``) the format of ``path`` does not take, naming the flags."""
    fmt, params = source_params(path, format)
    if fmt is None or not options:
        return
    refused = [k for k in options if k not in params]
    if refused:
        takes = [SOURCE_OPTION_FLAGS[k] for k in SOURCE_OPTION_FLAGS if k in params]
        reasons = "".join(f"; {_SOURCE_OPTION_REFUSALS[k].format(fmt=fmt)}" for k in refused if k in _SOURCE_OPTION_REFUSALS)
        raise ConfigError(f"{', '.join(SOURCE_OPTION_FLAGS.get(k, k) for k in refused)}: does not apply to {path} "
                          f"(format {fmt}" + (f", which takes {', '.join(takes)})" if takes else ", which takes none of "
                          f"{', '.join(SOURCE_OPTION_FLAGS.values())})") + reasons)


def _open(source: str | Path, format: str | None, frames: str | None, config: BuildConfig, poses_from_source: bool,
          depth_options: dict[str, Any] | None = None, source_options: dict[str, Any] | None = None) -> FrameSource:
    path = Path(source)
    options: dict[str, Any] = {"frames": frames}
    fmt, params = source_params(path, format)
    if depth_options and fmt in registered_formats():
        refused = [k for k in depth_options if k not in params]
        if refused:
            takes = [_DEPTH_OPTION_SETTINGS[k] for k in _DEPTH_OPTION_SETTINGS if k in params]
            raise ConfigError(
                f"{', '.join(_DEPTH_OPTION_SETTINGS[k] for k in refused)}: does not apply to {path} (format {fmt}"
                + (f", which takes only {', '.join(takes)})" if takes else ", to which build passes no depth options)")
                + "; remove it from the config file, the DRIFTMAP_DEPTH__* environment or the command line")
        options.update(depth_options)
    if source_options:
        check_source_options(path, fmt, source_options)
        options.update(source_options)
    if poses_from_source and "poses_from_ground_truth" in params:
        options["poses_from_ground_truth"] = True  # data sets: their ground truth; logs carry their own poses
    if "pixel_stride" in params:
        options["pixel_stride"] = config.pixel_stride if config.pixel_stride is not None else 0  # 0: decide below
    src = open_source(path, fmt, **{k: v for k, v in options.items() if k != "pixel_stride" or v})
    _require_frames(src, path, fmt, frames, {k: v for k, v in options.items() if k not in ("frames", "pixel_stride")})
    if "pixel_stride" in params and not config.pixel_stride:
        first = src.frame(0)
        stride = 2 if first.intrinsics is not None and first.intrinsics.width >= 640 else 1
        if stride != 1:
            src = open_source(path, fmt, **{**options, "pixel_stride": stride})
    return src


def _require_frames(src: FrameSource, path: Path, fmt: str | None, frames: str | None, options: dict[str, Any]) -> None:
    """An empty selection is an error that names ``--frames`` and the source's length (not a failed index 0)."""
    try:
        n = len(src)
    except SourceError:  # the length is unknown for this source: the frames are counted as they come
        return
    if n:
        return
    if frames is None:
        raise SourceError(f"{path}: the source has no frames")
    total = len(open_source(path, fmt, **options))
    raise ConfigError(f"--frames {frames} selects no frame of {path} (the source has {total} frames"
                      + (f", indices 0..{total - 1})" if total else ")"))


def _source_record(source: str | Path, src: FrameSource, poses: dict[str, Any] | None = None,
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


def _poses_record(poses_file: str | Path | None, poses_from_source: bool, kitti_frame: str,
                  calib_file: str | Path | None) -> dict[str, Any]:
    """Where revision 0's poses come from (the coordinate frame of the stored frames): ``--resume`` must match."""
    if poses_file is not None:
        return {"mode": "file", "file": str(Path(poses_file).resolve()), "kitti_frame": kitti_frame,
                "calib": None if calib_file is None else str(Path(calib_file).resolve())}
    return {"mode": "source" if poses_from_source else "odometry"}


def _describe_poses(poses: dict[str, Any]) -> str:
    if poses.get("mode") == "file":
        extra = "" if poses.get("kitti_frame", "auto") == "auto" else f" --kitti-frame {poses['kitti_frame']}"
        extra += "" if poses.get("calib") is None else f" --calib {poses['calib']}"
        return f"--poses {poses.get('file')}{extra}"
    return {"source": "--poses-from-source (the source's own poses)", "odometry": "odometry (no --poses, no --poses-from-source)"}.get(
        str(poses.get("mode")), str(poses.get("mode")))


def _check_recorded_source(out: Path, record: dict[str, Any]) -> dict[str, Any] | None:
    """``--resume``: refuse a source other than the one the store was built from (its resolved path or format
    differ). The record, or None when the store has none (built before the record existed): see
    :func:`_check_stored_frames`."""
    file = out / BUILD_SOURCE_FILE
    try:
        recorded = json.loads(file.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise StoreError(f"{file}: unreadable build source record ({exc})") from exc
    if recorded.get("path") != record["path"] or recorded.get("format") != record["format"]:
        raise ConfigError(
            f"{out}: cannot --resume from a different source: the store was built from {recorded.get('path')} "
            f"(format {recorded.get('format')}, recorded in {file}), the source given is {record['path']} "
            f"(format {record['format']}); resume with the same source or build into another --out")
    return recorded


def _check_resume_settings(store: FrameStore, src: FrameSource, recorded: dict[str, Any] | None,
                           record: dict[str, Any]) -> None:
    """``--resume``: the poses of the new frames must be in the coordinate frame of the stored ones (the same
    pose mode: odometry, ``--poses FILE`` -- the same file -- or ``--poses-from-source``), and the depth images
    read the same way (the same ``depth.*`` options). A record from before these were recorded: the pose mode
    is checked against revision 0's pose source where that tells them apart."""
    out = store.path
    file = out / BUILD_SOURCE_FILE
    given = record["poses"]
    if recorded is not None and "poses" in recorded:
        if recorded["poses"] != given:
            raise ConfigError(
                f"{out}: cannot --resume with different poses: the stored frames were placed with "
                f"{_describe_poses(recorded['poses'])} (recorded in {file}), this build asks for {_describe_poses(given)}; "
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
                f"'{stored.value}', this build asks for {_describe_poses(given)}; their poses would be in different "
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
            return ", ".join(f"{_DEPTH_OPTION_SETTINGS.get(k, k).split(' ')[0]}={v}" for k, v in options.items()) or "the source's defaults"
        raise ConfigError(
            f"{out}: cannot --resume with different depth settings: the stored frames were read with "
            f"{show(recorded['depth'])} (recorded in {file}), this build with {show(record['depth'])}; resume with "
            f"the same depth.* settings (config file, DRIFTMAP_DEPTH__* environment, --depth-scale) or build into "
            f"another --out")


def _check_stored_frames(store: FrameStore, src: FrameSource, record: dict[str, Any]) -> None:
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


def _check_first_frame_poses(src: FrameSource, pose_of: Callable[[Frame], np.ndarray] | None,
                             poses_from_source: bool) -> None:
    """Before a new store is created: the first selected frame must have a pose (``--poses`` /
    ``--poses-from-source``)."""
    if pose_of is None and not poses_from_source:
        return
    first = src.frame(0)
    if pose_of is not None:
        pose_of(first)  # raises naming the pose file and the frame
    elif first.pose.source is PoseSource.NONE:
        raise SourceError(_no_pose_message(src, first.frame_id))


def _no_pose_message(src: FrameSource, frame_id: int) -> str:
    msg = f"{src.uri}: frame {frame_id} has no pose in the source (--poses-from-source)"
    try:
        has_ground_truth = src.ground_truth() is not None
    except (DriftmapError, OSError):  # only a hint: an unreadable ground truth gives none
        has_ground_truth = False
    if has_ground_truth:
        msg += ("; it holds ground truth on its own (in an MCAP from `driftmap convert`, on the sensor's ground_truth "
                "topic), which is never taken as the pose estimate: build from the original data set with "
                "--poses-from-source, or drop the flag to run odometry")
    return msg


def _remove_new_store(out: Path, out_existed: bool, new_dirs: list[Path]) -> None:
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


def _pose_file_lookup(poses_file: str | Path, source: FrameSource, kitti_frame: str = "auto",
                      calib_file: str | Path | None = None,
                      max_dt_ns: int = DEFAULT_POSES_MAX_DT_NS) -> Callable[[Frame], np.ndarray]:
    fmt = detect_trajectory_format(poses_file)
    traj = read_trajectory(poses_file, fmt)
    if fmt != "kitti" and (kitti_frame != "auto" or calib_file is not None):
        raise ConfigError(f"{poses_file}: not a KITTI pose file (format {fmt}); --kitti-frame / --calib apply to KITTI "
                          f"files only")
    if fmt == "kitti":
        rows = _kitti_rows_in_sensor_frame(Path(poses_file), traj.poses, source, kitti_frame, calib_file)
    else:
        traj = source.pose_file_in_sensor_frame(Path(poses_file), traj)
        rows = traj.poses
    if fmt == "redwood":  # the file names its frames: the 'i' of each 'i j n' line
        row_of = {int(f): k for k, f in enumerate(traj.frame_ids if traj.frame_ids is not None else [])}

        def by_frame_id(frame: Frame) -> np.ndarray:
            if frame.frame_id not in row_of:
                raise SourceError(f"{poses_file}: no pose for frame {frame.frame_id} (the file has frames "
                                  f"{min(row_of)}..{max(row_of)}, {len(row_of)} poses)")
            return rows[row_of[frame.frame_id]]
        return by_frame_id
    if not has_stamps(traj, fmt):  # KITTI, 4x4 without stamps: row i is the pose of frame_id i

        def by_index(frame: Frame) -> np.ndarray:
            if frame.frame_id >= len(rows):
                raise SourceError(f"{poses_file}: {len(rows)} rows, no pose for frame {frame.frame_id} (row {frame.frame_id})")
            return rows[frame.frame_id]
        return by_index
    stamps = traj.stamps_ns

    def by_stamp(frame: Frame) -> np.ndarray:
        i = int(np.clip(np.searchsorted(stamps, frame.stamp_ns), 1, len(stamps) - 1))
        j = i - 1 if abs(stamps[i - 1] - frame.stamp_ns) <= abs(stamps[i] - frame.stamp_ns) else i
        if abs(int(stamps[j]) - frame.stamp_ns) > max_dt_ns:
            raise SourceError(f"{poses_file}: no pose within {max_dt_ns / 1e6:g} ms of frame {frame.frame_id} "
                              f"(stamp {frame.stamp_ns} ns; the nearest is {int(stamps[j]) - frame.stamp_ns:+d} ns away)")
        return traj.poses[j]
    return by_stamp


def _kitti_rows_in_sensor_frame(poses_file: Path, poses: np.ndarray, source: FrameSource, kitti_frame: str = "auto",
                                calib_file: str | Path | None = None) -> np.ndarray:
    """KITTI pose rows as ``T_world_sensor``: the data set's own cam0 ground truth is converted to the Velodyne
    frame, as ``--poses-from-source`` does; see :func:`driftmap.sources.kitti.kitti_rows_as_velodyne` (shared
    with ``correct`` and ``diagnose``)."""
    from driftmap.sources.kitti import kitti_origin_of_source, kitti_rows_as_velodyne

    lidar = len(source) > 0 and source.frame(0).sensor_kind is SensorKind.LIDAR
    return kitti_rows_as_velodyne(poses_file, poses, lambda: kitti_origin_of_source(source), kitti_frame=kitti_frame,
                                  calib_file=calib_file, lidar_frames=lidar)


def build(
    source: str | Path,
    out: str | Path,
    *,
    format: str | None = None,
    config: BuildConfig | None = None,
    poses_file: str | Path | None = None,
    poses_from_source: bool = False,
    loop_closure: bool = True,
    frames: str | None = None,
    resume: bool = False,
    progress: ProgressCallback | None = None,
    inject_wrong_loop: tuple[int, int, np.ndarray] | None = None,
    kitti_frame: str = "auto",
    calib_file: str | Path | None = None,
    poses_max_dt_ns: int = DEFAULT_POSES_MAX_DT_NS,
    depth: DepthConfig | None = None,
    source_options: dict[str, Any] | None = None,
) -> BuildResult:
    """Build (or ``resume``) a store from a source. See the module docstring for the stages.

    ``source_options``: which stream of the source to read (``sensor``, ``topic``, ``pose_from_tf``,
    ``pose_from_odometry``, ``lenient``: the command line's ``SOURCE_OPTION_FLAGS``); one the format does not take
    is a :class:`ConfigError` naming the flag; they are recorded, and ``--resume`` must give the same.
    ``depth``: how a depth-image source reads its images (:class:`driftmap.config.DepthConfig`; None or unset
    fields: the source's own defaults). A set option the format does not take is a :class:`ConfigError`.
    ``--resume`` refuses a different source, pose mode (odometry / ``poses_file`` / ``poses_from_source``, and
    another ``poses_file``) or depth options than the store was built with (``build_source.json``).

    ``kitti_frame`` / ``calib_file``: the frame of a KITTI ``poses_file`` (``auto`` | ``velodyne`` | ``cam0``)
    and the calibration for ``cam0``; see :func:`driftmap.sources.kitti.kitti_rows_as_velodyne`.
    ``poses_max_dt_ns``: a TUM ``poses_file`` row is a frame's pose when it is the nearest within this (20 ms,
    as TUM's ``associate.py``).

    ``inject_wrong_loop=(frame_a, frame_b, T_a_b)`` adds a deliberately wrong loop measurement (for testing
    the robust back end); it is reported like any other loop.
    """
    config = config or BuildConfig()
    if poses_max_dt_ns < 0:
        raise ConfigError(f"the stamp tolerance of --poses must be >= 0, got {poses_max_dt_ns} ns")
    if poses_file is not None and poses_from_source:
        raise ConfigError("give either --poses FILE or --poses-from-source, not both")
    if poses_file is None and (kitti_frame != "auto" or calib_file is not None):
        raise ConfigError("--kitti-frame / --calib describe a KITTI --poses FILE; give one")
    tick = progress or (lambda stage, done, total: None)
    stages: dict[str, float] = {}
    out = Path(out)
    store_exists = (out / "store.json").exists()
    if store_exists and not resume:
        raise StoreError(f"{out}: a store exists already; use --resume to continue it or choose another --out")
    depth_options = (depth or DepthConfig()).source_options()
    source_options = {k: v for k, v in (source_options or {}).items() if v is not None and v is not False}
    src = _open(source, format, frames, config, poses_from_source, depth_options, source_options)
    if config.depth_scale_error != 1.0 or config.focal_length_error != 1.0:
        logger.warning("build: frames perturbed on purpose (depth scale x%g, focal length x%g); recorded in build_config.json",
                       config.depth_scale_error, config.focal_length_error)
    record = _source_record(source, src, _poses_record(poses_file, poses_from_source, kitti_frame, calib_file),
                            depth_options, source_options)
    # inputs are checked before a store is created or opened for appending: a pose file that cannot be read
    # leaves nothing behind
    pose_of = _pose_file_lookup(poses_file, src, kitti_frame, calib_file, poses_max_dt_ns) if poses_file is not None else None
    new_store = not (resume and store_exists)
    out_existed, new_dirs = out.exists(), [p for p in (out, *out.parents) if not p.exists()]  # what create() makes
    recorded: dict[str, Any] | None = None
    if not new_store:
        recorded = _check_recorded_source(out, record)
        store = FrameStore.open(out, "a")
        for event in store.recovery_events:
            logger.warning("resume: %s", event)
        try:
            if recorded is None:
                _check_stored_frames(store, src, record)
            _check_resume_settings(store, src, recorded, record)
        except BaseException:
            store.close()
            raise
    else:
        _check_first_frame_poses(src, pose_of, poses_from_source)
        store = FrameStore.create(out)
    try:
        if recorded is None or set(record) - set(recorded):
            # a new store, or one whose record predates some fields (checked above): write the full record
            (out / BUILD_SOURCE_FILE).write_text(json.dumps({**record, **(recorded or {})}, indent=2) + "\n")
        return _build(src, store, config, pose_of, poses_from_source, loop_closure, tick, stages, inject_wrong_loop,
                      source_record=record)
    except BaseException as exc:
        n_stored = len(store)
        store.close()
        what = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        if new_store and n_stored == 0:
            _remove_new_store(out, out_existed, new_dirs)
        elif n_stored:
            logger.warning("build %s with %d frames stored; %s is kept (continue it with --resume)", what, n_stored, out)
        raise
    finally:
        store.close()


def _build(src: FrameSource, store: FrameStore, config: BuildConfig, pose_of: Callable[[Frame], np.ndarray] | None,
           poses_from_source: bool, loop_closure: bool, tick: ProgressCallback, stages: dict[str, float],
           inject_wrong_loop: tuple[int, int, np.ndarray] | None, *,
           source_record: dict[str, Any] | None = None) -> BuildResult:
    existing = {int(i) for i in store.frame_ids}
    pose_source = PoseSource.EXTERNAL_FILE if pose_of else PoseSource.ODOMETRY
    odometry: KissOdometry | GicpMapOdometry | None = None
    odometry_config: dict[str, Any] | None = None
    scene: dict[str, Any] | None = None
    n_total = len(src)
    invalid: list[float] = []
    n_new = 0
    t_read = t_odom = t_store = 0.0
    t0 = time.perf_counter()
    frame_iter = iter(src)
    done = 0
    while True:
        t_a = time.perf_counter()
        try:
            frame = next(frame_iter)
        except StopIteration:
            break
        t_read += time.perf_counter() - t_a
        done += 1
        if frame.quality is not None:
            invalid.append(frame.quality.invalid_fraction)
        frame = _with_sensor_error(frame, config)
        if done == 1 and loop_closure and frame.sensor_kind is not SensorKind.LIDAR:
            _check_place_descriptor(config.loop_closure, frame)  # before anything is stored
        if frame.frame_id in existing:
            tick("frames", done, n_total)
            continue
        t_b = time.perf_counter()
        health = None
        if pose_of is not None:
            T = pose_of(frame)
        elif poses_from_source:
            if frame.pose.source is PoseSource.NONE:
                raise SourceError(_no_pose_message(src, frame.frame_id))
            T = frame.T_world_sensor
            pose_source = frame.pose.source
        else:
            if odometry is None:
                cfg = config.odometry or (_recorded_odometry(store) if existing else None)
                if cfg is None:
                    sample = _scene_sample(src, store, frame, config)
                    reach = scene_reach(lidar_frames(sample))
                    scene = None if reach is None else reach.to_json()
                    cfg = OdometryConfig.for_frames(sample)
                if config.num_threads is not None:
                    cfg = cfg.model_copy(update={"num_threads": config.num_threads})
                odometry = make_odometry(cfg)
                odometry_config = cfg.model_dump(mode="json")
                if existing:
                    last = sorted(existing)[-config.resume_seed_frames:]
                    odometry.seed((store.frame(fid), store.poses(0)[np.searchsorted(store.frame_ids, fid)]) for fid in last)
            step = odometry.register(frame)
            T, health = step.T_world_sensor, step.health
        t_c = time.perf_counter()
        stored = frame.with_pose(PoseEstimate(T, revision=0, source=pose_source, world_frame=frame.pose.world_frame))
        store.append(stored if health is None else dataclasses.replace(stored, tracking=health))
        t_store += time.perf_counter() - t_c
        t_odom += t_c - t_b
        n_new += 1
        tick("frames", done, n_total)
    stages["read+validate"] = t_read
    stages["odometry" if pose_source is PoseSource.ODOMETRY else "poses"] = t_odom
    stages["store"] = t_store
    logger.info("stored %d new frames in %.1f s", n_new, time.perf_counter() - t0)
    if src.skipped:
        logger.warning("%d frames skipped (lenient): %s", len(src.skipped), src.skipped[:5])
    result = BuildResult(
        store=str(store.path), n_frames=len(store), n_frames_new=n_new,
        mean_invalid_fraction=float(np.mean(invalid)) if invalid else None,
        pose_source=pose_source.value if n_new else store.ledger.revision(0).source.value,
        odometry_fps=odometry.fps if odometry is not None else None, seconds_per_stage=stages, source=source_record,
        odometry_config=odometry_config, tracking=tracking_summary(store), scene_reach=scene,
    )
    if result.tracking["flagged"]:
        logger.warning("odometry: %d of %d frames flagged (tracking lost, poses bridged): %s; loop closure does not "
                       "trust the trajectory across them", len(result.tracking["flagged"]), result.tracking["frames"],
                       ", ".join(f"{f['frame_id']} ({f['status']})" for f in result.tracking["flagged"][:10]))
    if loop_closure and len(store) >= 2:
        _close_loops(store, config, result, tick, stages, inject_wrong_loop,
                     own_odometry=pose_of is None and not poses_from_source)
    (store.path / "build_config.json").write_text(config.model_dump_json(indent=2) + "\n")
    (store.path / "build_summary.json").write_text(json.dumps(result.to_json(), indent=2, default=str) + "\n")
    return result


def tracking_summary(store: FrameStore | None) -> dict[str, Any]:
    """The tracking-health records of a store's frames (:class:`driftmap.frame.TrackingHealth`, kept with each frame
    its odometry registered): ``frames`` (with a record), ``by_status`` counts, ``flagged`` (lost / reinitialised)
    and ``recovered`` frames with their reasons, the median fitness, the smallest degeneracy and ``per_frame``."""
    per_frame = []
    for fid in (store.frame_ids if store is not None else []):
        record = store.frame_info(int(fid)).get("tracking")
        if record is not None:
            per_frame.append({"frame_id": int(fid), **record})
    by_status: dict[str, int] = {}
    for r in per_frame:
        by_status[r["status"]] = by_status.get(r["status"], 0) + 1
    fitness = [r["fitness"] for r in per_frame if r["fitness"] is not None]
    degeneracy = [r["degeneracy"] for r in per_frame if r["degeneracy"] is not None]

    def brief(r: dict[str, Any]) -> dict[str, Any]:
        return {k: r[k] for k in ("frame_id", "status", "hypothesis", "fitness", "reason")}
    return {
        "frames": len(per_frame), "by_status": by_status,
        "flagged": [brief(r) for r in per_frame if r["status"] in ("lost", "reinitialised")],
        "recovered": [brief(r) for r in per_frame if r["status"] == "recovered"],
        "median_fitness": float(np.median(fitness)) if fitness else None,
        "min_degeneracy": float(np.min(degeneracy)) if degeneracy else None,
        "per_frame": per_frame,
    }


def flagged_rows(store: FrameStore) -> dict[int, int]:
    """``{position in the store's frame order: frame id}`` of the frames whose odometry is flagged (lost or
    reinitialised): loop closure does not trust the trajectory across them."""
    out = {}
    for row, fid in enumerate(store.frame_ids):
        record = store.frame_info(int(fid)).get("tracking")
        if record is not None and record["status"] in ("lost", "reinitialised"):
            out[row] = int(fid)
    return out


def _scene_sample(src: FrameSource, store: FrameStore, first: Frame, config: BuildConfig) -> list[Frame]:
    """Frames spread over the log whose reach sets the odometry's lengths (LiDAR; :mod:`driftmap.preprocess.scene`):
    the stored ones and the source's, ``first`` (the frame being registered) among them. A source whose length is
    unknown gives only ``first`` (and the stored frames)."""
    if first.sensor_kind is not SensorKind.LIDAR:
        return [first]
    sample = [store.frame(int(store.frame_ids[k])) for k in sample_positions(len(store))]
    try:
        n = len(src)
    except SourceError:
        n = 0
        logger.warning("%s: the number of frames is unknown, so the LiDAR odometry's lengths come from frame %d%s",
                       src.uri, first.frame_id, " and the stored frames" if sample else " alone")
    for k in sample_positions(n):
        try:
            sample.append(_with_sensor_error(src.frame(k), config))
        except SourceError as exc:  # an unreadable frame is skipped (or fails) when the build reaches it
            logger.info("scene reach: frame index %d not sampled (%s)", k, exc)
    return sample or [first]


def _used_odometry(store: FrameStore, result: BuildResult) -> OdometryConfig:
    """The odometry settings the store's frames were registered with (this run's, or the earlier build's), else the
    defaults for its scene: loop closure scales its LiDAR lengths with the odometry voxel."""
    if result.odometry_config is not None:
        return OdometryConfig.model_validate(result.odometry_config)
    recorded = _recorded_odometry(store) if len(store) else None
    if recorded is not None:
        return recorded
    if len(store) == 0:
        return OdometryConfig()
    return OdometryConfig.for_frames([store.frame(int(store.frame_ids[k])) for k in sample_positions(len(store))],
                                     log=False)


def _recorded_odometry(store: FrameStore) -> OdometryConfig | None:
    """The odometry settings an earlier build of ``store`` used (``build_summary.json``), for ``--resume``:
    defaults chosen from the scene are not chosen again (a store built before they were is resumed with its
    own settings)."""
    try:
        summary = json.loads((store.path / "build_summary.json").read_text())
        if "odometry_config" not in summary:  # written before the settings were recorded: the sensor's defaults
            return OdometryConfig.for_sensor(store.frame(int(store.frame_ids[0])).sensor_kind)
        recorded = summary["odometry_config"]
        return None if recorded is None else OdometryConfig.model_validate(recorded)
    except (OSError, ValueError, AttributeError):
        return None


def _with_sensor_error(frame: Frame, config: BuildConfig) -> Frame:
    """Apply the configured depth-scale / focal-length error (the perturbation harness's build-time part)."""
    if config.depth_scale_error == 1.0 and config.focal_length_error == 1.0:
        return frame
    from driftmap.diagnostics import perturb

    if config.focal_length_error != 1.0:
        if frame.intrinsics is None:
            raise ConfigError(f"frame {frame.frame_id}: focal_length_error needs a depth camera with intrinsics "
                              f"({frame.sensor_kind.value} frames have none)")
        frame = perturb.with_focal_error(frame, config.focal_length_error)
    if config.depth_scale_error != 1.0:
        frame = perturb.with_depth_scale_error(frame, config.depth_scale_error)
    return frame


def _fallback_information(T_a_b: np.ndarray, config: BuildConfig) -> np.ndarray:
    """Odometry-edge information when registration could not provide one: sigma grows with the motion."""
    motion = float(np.linalg.norm(T_a_b[:3, 3]))
    sigma_t = config.fallback_sigma_translation * motion + 0.01
    sigma_r = np.radians(config.fallback_sigma_rotation_deg)
    return np.diag([1 / sigma_t**2] * 3 + [1 / sigma_r**2] * 3)


class _EdgeGroup(enum.Enum):
    ODOMETRY = "odometry"
    FALLBACK = "fallback"
    LOOP = "loop"


def _edge_residual_chi2(T_from_to: np.ndarray, information: np.ndarray, T_world_from: np.ndarray, T_world_to: np.ndarray) -> float:
    """Mahalanobis residual of a between-edge (driftmap [t, r] order, the same as GTSAM's after reordering)."""
    e = geometry.se3_log(geometry.invert(T_from_to) @ geometry.invert(T_world_from) @ T_world_to)
    return float(e @ information @ e)


def _odometry_edges_from_trajectory(config: BuildConfig, store: FrameStore, own_odometry: bool) -> bool:
    """Whether odometry edges take the revision-0 relative pose or the keyframe registration.

    ``auto``: the relative pose when the frames were tracked against a map of *every* frame so far
    (``gicp_map`` without a horizon): such an odometry re-registers a revisited place to its first pass by
    itself, and its relative poses are more accurate than a keyframe-to-keyframe registration. Otherwise
    (KISS-ICP, a windowed ``gicp_map``, given poses) the keyframe registration: a local-map odometry's
    relative poses carry the drift the loops must take out, and as trajectory edges they could not be
    calibrated (they start at zero residual), so their raw GICP information would hold the drift in place
    (measured in docs/build.md)."""
    if config.odometry_edges == "trajectory":
        return True
    if config.odometry_edges == "registration" or not own_odometry or len(store) == 0:
        return False
    cfg = config.odometry or OdometryConfig.for_sensor(store.frame(int(store.frame_ids[0])).sensor_kind)
    return cfg.method is OdometryMethod.GICP_MAP and cfg.gicp_map_horizon_frames is None


def _check_place_descriptor(lc: LoopClosureConfig, frame: Frame) -> None:
    """A Scan Context needs a z-up LiDAR frame: refuse it for a depth camera's frames."""
    if lc.place_descriptor == "scan_context" and frame.sensor_kind is not SensorKind.LIDAR:
        raise ConfigError(f"loop_closure.place_descriptor = 'scan_context' needs LiDAR scans (a z-up sensor frame); "
                          f"frame {frame.frame_id} is from {frame.sensor_name!r}, a {frame.sensor_kind.value}: use 'shape'")


def _close_loops(store: FrameStore, config: BuildConfig, result: BuildResult, tick: ProgressCallback,
                 stages: dict[str, float], inject_wrong_loop: tuple[int, int, np.ndarray] | None, *, own_odometry: bool) -> None:
    t0 = time.perf_counter()
    ids = [int(i) for i in store.frame_ids]
    first = store.frame(ids[0]) if ids else None
    odometry_cfg = config.odometry or _used_odometry(store, result)
    lc = config.loop_closure
    if first is not None and first.sensor_kind is SensorKind.LIDAR:
        odometry_voxel_m = odometry_cfg.voxel_size_m if odometry_cfg.method is OdometryMethod.KISS else odometry_cfg.gicp_map_voxel_m
        stamps = store.ledger.stamps_ns
        period_s = float(np.median(np.diff(stamps))) * 1e-9 if len(stamps) > 1 else None
        lc = lc.over(LoopClosureConfig.for_lidar(odometry_voxel_m, period_s))
    elif first is not None:
        _check_place_descriptor(lc, first)
    if config.num_threads is not None:
        lc = lc.model_copy(update={"num_threads": config.num_threads})
    result.loop_closure_config = lc.model_dump(mode="json")
    poses = store.poses(0)
    key_rows = select_keyframes(poses, lc)
    result.n_keyframes = len(key_rows)
    stamps_ns = store.ledger.stamps_ns
    span_s = 1e-9 * float(stamps_ns[key_rows[-1]] - stamps_ns[key_rows[0]])
    if loop_gap(lc)[0] == "frames":  # in the source's frame numbers
        span, what = ids[key_rows[-1]] - ids[key_rows[0]], f"loop_closure.min_gap_frames = {lc.min_gap_frames} source frames"
    else:
        span, what = span_s, f"loop_closure.min_gap_s = {lc.min_gap_s:g} s"
    if inject_wrong_loop is None and (len(key_rows) < 2 or span < gap_threshold(lc)):
        logger.warning("loop closure skipped: the %d keyframes (of %d stored frames, source frames %d..%d) span "
                       "source frames %d..%d (%.2f s), less than %s (loop candidates are at least that far apart); "
                       "store a longer stretch of the source, or lower it", len(key_rows), len(ids), ids[0], ids[-1],
                       ids[key_rows[0]], ids[key_rows[-1]], span_s, what)
        return
    keyframes: list[Keyframe] = []
    cache: dict[int, np.ndarray] = {}
    max_range_m = lc.max_range_m
    if max_range_m is None and ids and own_odometry:  # the range the odometry trusted; given poses: every point
        max_range_m = odometry_cfg.max_range_m

    def points(row: int) -> np.ndarray:
        if row not in cache:
            pts = store.frame(ids[row]).points_sensor
            if max_range_m is not None:
                pts = pts[np.einsum("ij,ij->i", pts, pts) <= max_range_m**2]
            cache[row] = pts
        return cache[row]

    for n, row in enumerate(key_rows):
        rows = range(max(0, row - lc.submap_radius_frames), min(len(ids), row + lc.submap_radius_frames + 1))
        inv = geometry.invert(poses[row])
        cloud = np.concatenate([geometry.transform_points(inv @ poses[r], points(r)) for r in rows])
        keyframes.append(make_keyframe(ids[row], row, poses[row], cloud, lc, stamp_ns=int(stamps_ns[row])))
        for r in [r for r in cache if r < row - lc.submap_radius_frames]:
            del cache[r]
        tick("keyframes", n + 1, len(key_rows))
    result.n_keyframes = len(keyframes)
    stages["keyframes"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    candidates: list[LoopCandidate] = find_loops(keyframes, lc, progress=lambda d, t: tick("loop candidates", d, t),
                                                 flagged=flagged_rows(store))
    injected_info = None
    if inject_wrong_loop is not None:
        fa, fb, T_wrong = inject_wrong_loop
        by_id = {k.frame_id: k for k in keyframes}
        if fa not in by_id or fb not in by_id:
            raise ConfigError(f"injected loop {fa}<->{fb}: both frames must be keyframes ({[k.frame_id for k in keyframes][:10]}...)")
        accepted_info = [c.result.information_6x6 for c in candidates if c.accepted and c.result is not None]
        injected_info = accepted_info[0] if accepted_info else np.diag([1e4] * 3 + [1e4] * 3)
        candidates.append(LoopCandidate(fa, fb, CandidateKind.INJECTED, True, "deliberately wrong (injected)", None, T_wrong))
    stages["loop candidates"] = time.perf_counter() - t1
    result.loops_tried = len(candidates)
    accepted = [c for c in candidates if c.accepted]
    result.loops_accepted = len(accepted)
    # (group, key_from, key_to, T_from_to, information) -- the graph is rebuilt for the information calibration
    edges: list[tuple[_EdgeGroup, int, int, np.ndarray, np.ndarray]] = []
    for c in accepted:
        info = c.result.information_6x6 if c.result is not None else injected_info
        edges.append((_EdgeGroup.LOOP, c.a, c.b, c.T_a_b, info))
    result.loops = [{"a": c.a, "b": c.b, "kind": c.kind.value, "accepted": c.accepted, "reason": c.reason,
                     "fitness": None if c.result is None else c.result.fitness,
                     "rmse_m": None if c.result is None else c.result.rmse_m} for c in candidates]
    if not accepted:
        logger.info("no loop closure accepted; the odometry stays revision 0")
        return
    t_edges = time.perf_counter()
    from_trajectory = _odometry_edges_from_trajectory(config, store, own_odometry)
    v = lc.registration_voxel_m
    pairs = [(i, i + d) for i in range(len(keyframes)) for d in range(1, config.odometry_edge_window + 1) if i + d < len(keyframes)]
    for n, (i, j) in enumerate(pairs):
        a, b = keyframes[i], keyframes[j]
        odom = relative_pose(a.T_world_sensor, b.T_world_sensor)
        reg = register_prepared(a.cloud, b.cloud, odom, voxel_size_m=v, max_correspondence_m=2.5 * v)
        good = reg.converged and reg.fitness >= lc.min_fitness and \
            geometry.translation_distance_m(odom, reg.T_target_source) <= config.odometry_edge_max_disagreement_m
        if good:
            edges.append((_EdgeGroup.ODOMETRY, a.frame_id, b.frame_id, odom if from_trajectory else reg.T_target_source,
                          reg.information_6x6))
        elif j == i + 1:
            logger.info("odometry edge %d->%d: registration not usable (%s); odometry with fallback information",
                        a.frame_id, b.frame_id, reg.describe())
            edges.append((_EdgeGroup.FALLBACK, a.frame_id, b.frame_id, odom, _fallback_information(odom, config)))
        tick("odometry edges", n + 1, len(pairs))
    result.odometry_edges = sum(group is not _EdgeGroup.LOOP for group, *_ in edges)
    stages["odometry edges"] = time.perf_counter() - t_edges
    t2 = time.perf_counter()
    opt = _optimize_calibrated(keyframes, edges, config, result, calibrate_odometry=not from_trajectory)
    stages["pose graph"] = time.perf_counter() - t2
    result.graph_error_before, result.graph_error_after = opt.initial_error, opt.final_error
    for res in opt.loop_residuals:
        entry = next((x for x in result.loops if x["a"] == res.key_from and x["b"] == res.key_to and x["accepted"]), None)
        if entry is not None:
            entry.update(graph_chi2=res.chi2, graph_weight=res.weight, kept_by_graph=res.accepted)
        if not res.accepted:
            result.loops_rejected_by_graph += 1
            logger.info("loop %d<->%d rejected by the pose graph (chi2 %.1f, weight %.3f)", res.key_from, res.key_to,
                        res.chi2, res.weight if res.weight is not None else float("nan"))
    if result.loops_rejected_by_graph:
        logger.warning("%d of %d loops rejected by the pose graph (chi2 > %.1f)", result.loops_rejected_by_graph,
                       len(opt.loop_residuals), opt.chi2_threshold)
    t3 = time.perf_counter()
    revision = store.add_revision(opt.poses, source=PoseSource.LOOP_CLOSURE, propagate=True,
                                  note=f"{result.loops_accepted} loops, graph error {opt.initial_error:.3g} -> {opt.final_error:.3g}")
    view = store.map(0)
    changes = view.apply(revision.revision_id)
    stages["correction"] = time.perf_counter() - t3
    result.loop_revision = revision.revision_id
    result.max_correction_m = changes.max_translation_m
    result.max_correction_deg = max((c.rotation_deg for c in changes.changes), default=0.0)
    logger.info("loop closure: revision %d moved %d frames (max %.3f m)", revision.revision_id, len(changes.changes),
                result.max_correction_m)


#: median of a chi-square variable with 6 degrees of freedom
_CHI2_6DOF_MEDIAN = 5.348


def _optimize_calibrated(keyframes: list[Keyframe], edges: list[tuple[_EdgeGroup, int, int, np.ndarray, np.ndarray]],
                         config: BuildConfig, result: BuildResult, *, calibrate_odometry: bool) -> PoseGraphResult:
    """Optimise, then rescale the information of each edge group so that its median chi2 at the optimum is the
    chi2(6) median, and optimise again (a robust variance-component estimate, ``information_calibration_iterations``
    times). Registration Hessians know the shape of the uncertainty but not its size: neighbouring points'
    residuals are correlated and the sensor's systematic errors are not in them."""
    scale = dict.fromkeys(_EdgeGroup, 1.0)
    # odometry edges taken from frame-to-map odometry are not independent registrations: only the loops are calibrated
    calibrate = [_EdgeGroup.ODOMETRY, _EdgeGroup.LOOP] if calibrate_odometry else [_EdgeGroup.LOOP]

    def make_graph(kernel: RobustKernel = config.loop_kernel) -> PoseGraph:
        graph = PoseGraph()
        for k in keyframes:
            graph.add_node(k.frame_id, k.T_world_sensor)
        graph.add_prior(keyframes[0].frame_id, keyframes[0].T_world_sensor, np.diag([1e8] * 6))
        for group, a, b, T, info in edges:
            if group is _EdgeGroup.LOOP:
                graph.add_loop(a, b, T, info * scale[group], robust=kernel)
            else:
                graph.add_odometry(a, b, T, info * scale[group])
        return graph

    # the first round is plain least squares: with uncalibrated (over-confident) information a robust kernel
    # would switch every loop off, and the median chi2 is robust to a few wrong loops by itself
    graph = make_graph(RobustKernel.NONE if config.information_calibration_iterations else config.loop_kernel)
    # the rounds before the last are quiet: their rejected loops and convergence say nothing about the result
    opt = graph.optimize(config.optimizer, warn=not config.information_calibration_iterations)
    for _ in range(config.information_calibration_iterations):
        changed = False
        for group in calibrate:
            chi2 = [_edge_residual_chi2(T, info * scale[group], opt.poses[a], opt.poses[b]) for g, a, b, T, info in edges if g is group]
            if len(chi2) < 6:
                continue
            factor = _CHI2_6DOF_MEDIAN / max(float(np.median(chi2)), 1e-9)
            scale[group] *= factor
            changed |= abs(factor - 1.0) > 0.05
        graph = make_graph()
        opt = graph.optimize(config.optimizer, warn=False)
        if not changed:
            break
    if not opt.converged:
        logger.warning("pose graph %s did not converge after the information calibration (%s)", opt.method.name,
                       "; ".join(opt.warnings) or "see the pose graph's log")
    result.information_scale = {g.value: s for g, s in scale.items() if g is not _EdgeGroup.FALLBACK}
    logger.info("information calibration: odometry x%.3g, loops x%.3g", scale[_EdgeGroup.ODOMETRY], scale[_EdgeGroup.LOOP])
    return opt
