"""Where a build's revision-0 poses come from when they are not odometry: a pose file (``--poses``), the source's
own poses or its ground truth (``--poses-from-source``), each frame matched by stamp or frame id."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from driftmap.errors import ConfigError, DriftmapError, SourceError
from driftmap.frame import Frame, PoseSource, SensorKind
from driftmap.pipeline.build_config import DEFAULT_POSES_MAX_DT_NS
from driftmap.pipeline.source_options import source_params
from driftmap.sources.base import FrameSource
from driftmap.store.pose_match import refuse_conflicting_rows
from driftmap.trajectory import detect_trajectory_format, has_stamps, read_trajectory

logger = logging.getLogger(__name__)


def check_first_frame_poses(src: FrameSource, pose_of: Callable[[Frame], np.ndarray] | None,
                             poses_from_source: bool) -> None:
    """Before a new store is created: the first selected frame must have a pose (``--poses`` /
    ``--poses-from-source``)."""
    if pose_of is None and not poses_from_source:
        return
    first = _first_readable(src)
    if pose_of is not None:
        pose_of(first)  # raises naming the pose file and the frame
    elif first.pose.source is PoseSource.NONE:
        raise SourceError(no_pose_message(src, first.frame_id))


def _first_readable(src: FrameSource) -> Frame:
    """The first selected frame; in lenient mode the first one that reads (the build skips the others with their
    reasons, so the check must too)."""
    if not src.lenient:
        return src.frame(0)
    problem: SourceError | None = None
    for index in range(len(src)):
        try:
            return src.frame(index)
        except SourceError as exc:
            problem = problem or exc
    raise problem if problem is not None else SourceError(f"{src.uri}: no frame to read")


def log_ground_truth_lookup(src: FrameSource, path: Path, format: str | None) -> Callable[[Frame], np.ndarray] | None:
    """``--poses-from-source`` on a log whose frames carry no pose but which holds the ground truth of the data set it
    was converted from (an MCAP of ``driftmap convert``, its sensor's ground_truth topic): the ground truth, as the
    same flag takes it from the original data set folder (one flag, one meaning). None for data sets (their opener
    takes ``poses_from_ground_truth``), logs whose frames have poses (TF, odometry) and logs without ground truth."""
    if "poses_from_ground_truth" in source_params(path, format)[1]:
        return None
    try:
        if src.frame(0).pose.source is not PoseSource.NONE:
            return None
    except SourceError:  # no first frame: the build says so itself
        return None
    try:
        truth = src.ground_truth()
    except (DriftmapError, OSError) as exc:
        logger.debug("%s: no ground truth to take as the source's poses (%s)", src.uri, exc)
        return None
    if truth is None or len(truth) == 0:
        return None
    by_id = truth.frame_ids is not None
    keys = (truth.frame_ids if by_id else truth.stamps_ns).tolist()
    rows = dict(zip(keys, range(len(keys))))
    logger.info("%s: --poses-from-source takes the log's ground truth (%d poses, matched by %s): its frames carry "
                "no pose of their own", src.uri, len(truth), "frame id" if by_id else "stamp")

    def pose_of(frame: Frame) -> np.ndarray:
        row = rows.get(int(frame.frame_id) if by_id else int(frame.stamp_ns))
        if row is None:
            raise SourceError(f"{src.uri}: frame {frame.frame_id} (stamp {frame.stamp_ns} ns) has no pose in the "
                              f"log's ground truth (--poses-from-source)")
        return truth.poses[row]
    return pose_of


def no_pose_message(src: FrameSource, frame_id: int) -> str:
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


def pose_file_lookup(poses_file: str | Path, source: FrameSource, kitti_frame: str = "auto",
                      calib_file: str | Path | None = None,
                      max_dt_ns: int = DEFAULT_POSES_MAX_DT_NS) -> Callable[[Frame], np.ndarray]:
    fmt = detect_trajectory_format(poses_file)
    traj = read_trajectory(poses_file, fmt)
    if fmt != "kitti" and (kitti_frame != "auto" or calib_file is not None):
        raise ConfigError(f"{poses_file}: not a KITTI pose file (format {fmt}); --kitti-frame / --calib apply to KITTI "
                          f"files only")
    if fmt == "kitti":
        rows = kitti_rows_in_sensor_frame(Path(poses_file), traj.poses, source, kitti_frame, calib_file)
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
    refuse_conflicting_rows(traj, str(poses_file), SourceError)  # two poses for one instant: which is the frame's?
    stamps = traj.stamps_ns
    frame_stamps = _source_stamps(source)

    def by_stamp(frame: Frame) -> np.ndarray:
        j = _nearest(stamps, frame.stamp_ns)
        if abs(int(stamps[j]) - frame.stamp_ns) > max_dt_ns:
            first_s, last_s = int(stamps.min()) / 1e9, int(stamps.max()) / 1e9
            outside = not first_s <= frame.stamp_ns / 1e9 <= last_s
            raise SourceError(
                f"{poses_file}: no pose within {max_dt_ns / 1e6:g} ms of frame {frame.frame_id} (stamp "
                f"{frame.stamp_ns} ns; the nearest is {int(stamps[j]) - frame.stamp_ns:+d} ns away, "
                f"{abs(int(stamps[j]) - frame.stamp_ns) / 1e9:.3f} s {'after' if stamps[j] > frame.stamp_ns else 'before'} "
                f"it); the file's {len(stamps)} rows span stamps {first_s:.3f} .. {last_s:.3f} s"
                + (" and the frame lies outside them (a file that ends before the log, or whose clock is offset from "
                   "the frames'): build only the frames the file covers (--frames), or build with our odometry and "
                   "import the file with `driftmap correct STORE --poses FILE` (frames without a row follow the "
                   "nearest ones)" if outside else
                   ": a file with a row per frame, or --max-dt-ms for rows that lag the frames"))
        if frame_stamps is not None:  # a row is the pose of its nearest frame only (TUM's associate.py)
            other = int(frame_stamps[_nearest(frame_stamps, int(stamps[j]))])
            if abs(other - int(stamps[j])) < abs(frame.stamp_ns - int(stamps[j])):
                raise SourceError(
                    f"{poses_file}: no pose of its own for frame {frame.frame_id} (stamp {frame.stamp_ns} ns): the nearest "
                    f"row ({int(stamps[j]) - frame.stamp_ns:+d} ns) belongs to the frame at {other} ns; a pose file "
                    f"needs a row per frame (or import a sparser one with `driftmap correct`, which propagates)")
        return traj.poses[j]
    return by_stamp


def _nearest(sorted_stamps: np.ndarray, stamp_ns: int) -> int:
    """Index of the stamp nearest ``stamp_ns`` in a sorted array (the earlier one on a tie)."""
    if len(sorted_stamps) == 1:
        return 0
    i = int(np.clip(np.searchsorted(sorted_stamps, stamp_ns), 1, len(sorted_stamps) - 1))
    return i - 1 if abs(int(sorted_stamps[i - 1]) - stamp_ns) <= abs(int(sorted_stamps[i]) - stamp_ns) else i


def _source_stamps(source: FrameSource) -> np.ndarray | None:
    """The sorted stamps of the source's selected frames, when it can list them without reading frames."""
    try:
        stamps = source.stamps_ns()
    except (SourceError, NotImplementedError):
        return None
    if not stamps or any(s is None for s in stamps):
        return None
    return np.sort(np.asarray(stamps, dtype=np.int64))


def kitti_rows_in_sensor_frame(poses_file: Path, poses: np.ndarray, source: FrameSource, kitti_frame: str = "auto",
                                calib_file: str | Path | None = None) -> np.ndarray:
    """KITTI pose rows as ``T_world_sensor``: the data set's own cam0 ground truth is converted to the Velodyne
    frame, as ``--poses-from-source`` does; see :func:`driftmap.sources.kitti.kitti_rows_as_velodyne` (shared
    with ``correct`` and ``diagnose``)."""
    from driftmap.sources.kitti import kitti_origin_of_source, kitti_rows_as_velodyne

    lidar = len(source) > 0 and source.frame(0).sensor_kind is SensorKind.LIDAR
    return kitti_rows_as_velodyne(poses_file, poses, lambda: kitti_origin_of_source(source), kitti_frame=kitti_frame,
                                  calib_file=calib_file, lidar_frames=lidar)
