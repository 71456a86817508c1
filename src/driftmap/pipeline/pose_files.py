"""Pose files read for a store's frames (``correct --poses``, ``diagnose --gt``): which data set the frames come
from, and the sensor frame its files' rows are in.

A pose file's rows are ``T_world_x`` of some frame ``x``; the store keeps ``T_world_sensor`` of its frames. Where
the two differ the data set decides: a KITTI sequence's own ``poses.txt`` holds the left camera (cam0), not the
Velodyne (:func:`driftmap.sources.kitti.kitti_rows_as_velodyne`), the synthetic log's ``groundtruth.txt`` its depth
camera, not its LiDAR (:meth:`FrameSource.pose_file_in_sensor_frame`), and an MCAP written by ``driftmap convert``
names the data set it came from. Those rules need both the store (its frames' provenance and
``build_source.json``) and the sources, so they live here, above both: the store imports rows that are already
``T_world_sensor`` (:meth:`FrameStore.import_poses`'s ``rows_in_sensor_frame``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.diagnostics.ground_truth import GT_FORMATS, MIN_GT_FRAMES
from driftmap.errors import ConfigError, DriftmapError, StoreError
from driftmap.frame import PoseSource
from driftmap.sources.base import registered_formats
from driftmap.sources.kitti import KittiOrigin, kitti_origin_named, kitti_origin_of_frame_infos, kitti_rows_as_velodyne
from driftmap.store.frame_store import FrameStore, PoseMatch, TrajectoryFormat
from driftmap.store.layout import BUILD_SOURCE_FILE, MERGE_SUMMARY_FILE
from driftmap.store.ledger import PoseMatchMode, Revision, match_pose_rows, stamp_ranges_text
from driftmap.trajectory import Trajectory, has_stamps, read_trajectory

logger = logging.getLogger(__name__)



def store_origin(store_dir: str | Path) -> dict[str, Any] | None:
    """The data set a store's frames come from, ``{"format", "path", "options"}``: the source in its
    ``build_source.json``, or, when that is a log converted from another data set (an MCAP ``driftmap convert``
    wrote), the data set it names. ``None`` without a (readable) record."""
    try:
        record = json.loads((Path(store_dir) / BUILD_SOURCE_FILE).read_text())
        fmt = registered_formats().get(str(record.get("format")))
        path = Path(record["path"])
    except (OSError, ValueError, RecursionError, KeyError, TypeError, AttributeError):
        return None
    if fmt is not None and fmt.origin_of is not None:
        named = fmt.origin_of(path)
        if named is not None:
            return named
    return {"format": str(record.get("format")), "path": str(path), "options": record.get("source_options") or {}}


def pose_file_in_store_sensor_frame(store_dir: str | Path, poses_file: str | Path, trajectory: Trajectory) -> Trajectory:
    """:meth:`FrameSource.pose_file_in_sensor_frame` for a store's frames: asked of the data set the store's frames
    come from (:func:`store_origin`), when its format converts pose files and it can still be opened; otherwise the
    rows as they are."""
    origin = store_origin(store_dir)
    fmt = registered_formats().get(origin["format"]) if origin else None
    if origin is None or fmt is None or not fmt.converts_pose_files:
        return trajectory
    try:
        source = fmt.open(Path(origin["path"]), **(origin.get("options") or {}))
    except (OSError, KeyError, TypeError, DriftmapError) as exc:
        logger.warning("%s: rows taken as they are; the data set %s (%s) that store %s comes from could not be opened "
                       "to check whether the file holds another of its sensors' poses (%s)", poses_file,
                       origin.get("path"), fmt.name, store_dir, exc)
        return trajectory
    try:
        return source.pose_file_in_sensor_frame(Path(poses_file), trajectory)
    finally:
        close = getattr(source, "close", None)
        if callable(close):
            close()


def store_holds_lidar_scans(store: FrameStore) -> bool:
    """Every frame of ``store`` is a LiDAR scan (and there is one)."""
    ids = store.frame_ids
    return len(ids) > 0 and all(store.frame_info(int(f)).get("sensor_kind") == "lidar" for f in ids)


def kitti_origin_of_store(store: FrameStore) -> KittiOrigin | None:
    """The KITTI sequence a store's frames come from (their provenance), or that the log it was built from was
    converted from (:func:`store_origin`), or ``None``."""
    origin = kitti_origin_of_frame_infos([store.frame_info(int(f)) for f in store.frame_ids])
    if origin is not None or not store_holds_lidar_scans(store):
        return origin
    return kitti_origin_named(store_origin(store.path), f"store {store.path}")


def pose_rows_in_sensor_frame(store: FrameStore, file: str | Path, trajectory: Trajectory, format: str, *,
                              kitti_frame: str = "auto", calib_file: str | Path | None = None) -> Trajectory:
    """The rows of a pose file read for ``store``'s frames as their ``T_world_sensor``: KITTI rows by
    :func:`~driftmap.sources.kitti.kitti_rows_as_velodyne` (a KITTI data set's cam0 ``poses.txt`` on its Velodyne
    scans), the rows of other formats by the data set the frames come from (:func:`pose_file_in_store_sensor_frame`:
    the synthetic log's camera files on its LiDAR scans); anything else as it is."""
    if format != TrajectoryFormat.KITTI.value:
        return pose_file_in_store_sensor_frame(store.path, file, trajectory)
    rows = kitti_rows_as_velodyne(file, trajectory.poses, lambda: kitti_origin_of_store(store), kitti_frame=kitti_frame,
                                  calib_file=calib_file, lidar_frames=store_holds_lidar_scans(store))
    return replace(trajectory, poses=rows)


def import_pose_file(store: FrameStore, file: str | Path, *, format: TrajectoryFormat | str = TrajectoryFormat.TUM,
                     match: str | None = None, max_dt_ns: int = 10_000_000, source: PoseSource | str = PoseSource.EXTERNAL_FILE,
                     propagate: bool = True, kitti_frame: str = "auto",
                     calib_file: str | Path | None = None) -> tuple[Revision, PoseMatch]:
    """``driftmap correct``: a pose file as a new revision of ``store``, its rows converted to the frames' sensor
    frame (:func:`pose_rows_in_sensor_frame`) before :meth:`FrameStore.import_poses` matches and stores them."""
    if (Path(store.path) / MERGE_SUMMARY_FILE).is_file():
        raise ConfigError(f"{store.path}: is a merged store, whose poses are not corrected from a file yet: its "
                          f"sessions may share stamps (a row of {Path(file).name} could be taken for another "
                          f"session's frame) and propagation would run across sessions; correct the session's own "
                          f"store and merge again (rollback works on a merged store)")

    def converter(trajectory: Trajectory, fmt: str) -> Trajectory:
        rows = pose_rows_in_sensor_frame(store, file, trajectory, fmt, kitti_frame=kitti_frame, calib_file=calib_file)
        refuse_another_sensors_rows(store, file, rows, fmt, match=match, max_dt_ns=max_dt_ns)
        return rows

    return store.import_poses(file, format=format, match=match, max_dt_ns=max_dt_ns, source=source, propagate=propagate,
                              kitti_frame=kitti_frame, calib_file=calib_file, rows_in_sensor_frame=converter)


OTHER_SENSOR_MIN_DEG = 20.0
"""A pose file whose rows differ from the store's latest poses by one rigid transform *about each frame's sensor* of at
least this rotation, for most frames, holds another sensor's poses: no calibration fix turns a sensor this far."""


def refuse_another_sensors_rows(store: FrameStore, file: str | Path, trajectory: Trajectory, format: str, *,
                                match: str | None = None, max_dt_ns: int = 10_000_000) -> None:
    """Raise :class:`ConfigError` when the rows of ``file`` (already ``T_world_sensor`` as far as the data set's
    rules know) look like the poses of *another* sensor on the same rig: for at least a quarter of the matched frames
    (and 3, spread over at least 50 cm: not a stationary start re-anchored by a yaw) ``inv(T_file) @ T_latest`` is one
    and the same transform (within 1 deg and 5 cm) rotating at least :data:`OTHER_SENSOR_MIN_DEG` -- the extrinsic
    between the two sensors. A correction moves frames in the world
    (a global re-anchoring changes positions too), never every sensor about itself by one large rotation. Trial 11: a
    perturbed *copy* of the synthetic log's camera ``groundtruth.txt`` corrected a LiDAR store by 129 deg at every
    frame without a word (the log's own file is recognised and converted; a copy is not)."""
    fmt = str(format)
    mode = PoseMatchMode(match) if match is not None else (
        PoseMatchMode.STAMP if has_stamps(trajectory, fmt) else PoseMatchMode.INDEX)
    try:
        matched = match_pose_rows(trajectory, fmt, store.ledger.frame_ids, store.ledger.stamps_ns, match=mode,
                                  max_dt_ns=max_dt_ns, where=str(file))
    except DriftmapError:
        return  # the import reports what does not match, with its own message
    ids = np.array(sorted(matched.poses), dtype=np.int64)
    if len(ids) < 3:
        return
    latest = store.poses(store.head)[np.searchsorted(store.frame_ids, ids)]
    given = np.array([matched.poses[int(i)] for i in ids])
    offsets = np.linalg.inv(given) @ latest  # T_file_sensor^-1 T_latest_sensor: the extrinsic, if one sensor is another

    def agreeing(reference: NDArray[np.float64]) -> NDArray[np.bool_]:
        return np.array([geometry.rotation_angle_deg(o, reference) < 1.0
                         and np.linalg.norm(o[:3, 3] - reference[:3, 3]) < 0.05 for o in offsets])

    candidates = offsets[np.unique(np.linspace(0, len(offsets) - 1, 9).round().astype(np.int64))]
    median = max(candidates, key=lambda c: int(agreeing(c).sum()))  # the offset most frames share
    same = agreeing(median)
    turn = geometry.rotation_angle_deg(np.eye(4), median)
    spread_m = float(np.linalg.norm(np.ptp(latest[same, :3, 3], axis=0))) if same.any() else 0.0
    if same.sum() >= 3 and same.mean() >= 0.25 and spread_m >= 0.5 and turn >= OTHER_SENSOR_MIN_DEG:
        raise ConfigError(
            f"{file}: {int(same.sum())} of {len(ids)} matched rows differ from the store's revision {store.head} by "
            f"one and the same {turn:.0f} deg rotation about each frame's sensor (and {np.linalg.norm(median[:3, 3]):.2f} m): "
            f"they look like the poses of another sensor on the rig (a log's ground truth is often its camera's or its "
            f"body's, not the LiDAR's); convert them to this store's sensor frame, or start from the store's own poses "
            f"(driftmap export STORE --trajectory FILE)")


def read_ground_truth(store: FrameStore, path: str | Path, format: str = "tum", *,
                      max_dt_ns: int = 10_000_000, kitti_frame: str = "auto",
                      calib_file: str | Path | None = None) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Ground-truth poses for the store's frames (``diagnose --gt``): TUM rows (and 4x4 blocks with stamps) matched
    by stamp, KITTI rows (and 4x4 blocks without stamps) row i = ``frame_id`` i, Redwood ``.log`` blocks by the frame
    id they name; the rows converted to the frames' sensor frame (:func:`pose_rows_in_sensor_frame`). Returns the
    matched frame ids and their poses."""
    fmt = format.lower()
    if fmt not in GT_FORMATS:
        raise ConfigError(f"--gt-format must be one of {', '.join(GT_FORMATS)}, got {format!r}")
    if fmt != "kitti" and (kitti_frame != "auto" or calib_file is not None):
        raise ConfigError(f"{path}: --kitti-frame / --calib apply to KITTI ground truth only (--gt-format kitti)")
    traj = pose_rows_in_sensor_frame(store, path, read_trajectory(path, fmt), fmt, kitti_frame=kitti_frame,
                                     calib_file=calib_file)
    mode = PoseMatchMode.STAMP if has_stamps(traj, fmt) else PoseMatchMode.INDEX
    matched = match_pose_rows(traj, fmt, store.ledger.frame_ids, store.ledger.stamps_ns, match=mode, max_dt_ns=max_dt_ns,
                              where=str(path))
    if not matched.poses:
        why = f" ({stamp_ranges_text(traj, store.ledger.stamps_ns)})" if mode is PoseMatchMode.STAMP else ""
        raise StoreError(f"{path}: no ground-truth row matched a stored frame (by {mode.value}){why}")
    if len(matched.poses) < MIN_GT_FRAMES:  # found before the costly diagnosis, not after it
        raise StoreError(f"{path}: ground truth matched only {len(matched.poses)} of the {len(store.ledger.frame_ids)} "
                         f"stored frames (by {mode.value}); ATE/RPE need at least {MIN_GT_FRAMES}")
    if matched.unmatched_frames:
        logger.warning("%s: %d stored frames have no ground-truth pose; they are left out of ATE/RPE", path,
                       len(matched.unmatched_frames))
    ids = np.array(sorted(matched.poses), dtype=np.int64)
    return ids, np.array([matched.poses[int(i)] for i in ids])


RowsConverter = Callable[[Trajectory, str], Trajectory]
