"""Export frames to an MCAP file of standard ROS 2 messages (opens in Foxglove, reads back with
:class:`~driftmap.sources.ros.RosLogSource`).

Why ROS 2 messages rather than Foxglove schemas: ``sensor_msgs/msg/PointCloud2``, ``CameraInfo`` and
``tf2_msgs/msg/TFMessage`` in CDR are what ROS tools (``ros2 bag``, rviz, rosbags, ``mcap_ros2``) read, and
Foxglove opens ROS 2 MCAP natively -- one file serves both worlds. (driftmap's own frame store uses
Foxglove protobuf schemas because it memory-maps point payloads; an export is for exchange.)

Layout, per sensor (``<s>`` = the frame's ``sensor_name``):

* ``/<s>/points`` -- ``sensor_msgs/msg/PointCloud2`` per frame, ``header.stamp`` = ``frame.stamp_ns``,
  ``header.frame_id`` = ``frame.sensor_frame``; fields ``x y z`` float32 (the frame's sensor-frame points,
  bit for bit), then the attributes the frame has: ``intensity`` float32, ``normal_x/y/z`` float32,
  ``rgb`` (PCL packed float32), per-point time ``t`` uint32 ns (Ouster convention) when every offset fits,
  else ``time`` float64 seconds relative to the stamp.
* ``/<s>/camera_info`` -- ``sensor_msgs/msg/CameraInfo`` per depth-camera frame (K, P, zero plumb_bob
  distortion, width/height) on the same ``frame_id`` and stamp, written before the cloud.
* ``/tf_static`` -- ``base_frame -> sensor_frame`` = ``T_base_sensor`` (one message per new sensor,
  repeating every static edge so far, like a tf2 static broadcaster).
* ``/tf`` -- per frame with a pose, ``world_frame -> base_frame`` = ``T_world_sensor @ inv(T_base_sensor)``
  at the frame's stamp. Reading it back with ``pose_from_tf=(world_frame, base_frame)`` composes
  ``T_world_base @ T_base_sensor`` at that exact stamp, which reproduces ``T_world_sensor`` to ~1e-15.
  Frames whose pose source is ``NONE`` get no ``/tf`` sample.
* ``/<s>/ground_truth`` -- ``geometry_msgs/msg/PoseStamped`` (``T_world_sensor``) per frame that has one,
  only when ``ground_truth`` is given. It is never the estimate.
* a ``driftmap.export`` metadata record (JSON) with, per sensor: topics, names, frames, ``frame_ids``,
  per-frame pose sources, depth scale; :class:`RosLogSource` uses it to restore frame ids, the sensor name
  and kind, and to default ``pose_from_tf``; and, when written from a source, its ``origin`` (format and
  resolved path: a KITTI store built from the MCAP still finds the sequence's ``calib.txt`` and ``poses.txt``).

Log time = publish time = the frame's stamp. Stamps must be non-negative (ROS time).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap import __version__, geometry
from driftmap.errors import ConfigError, ExportError
from driftmap.export.ros_messages import (
    MsgdefSchemas,
    camera_info_msg,
    mcap_compression,
    pointcloud2_msg,
    ros_header,
    transform_stamped,
)
from driftmap.frame import Frame, PoseSource, SensorKind
from driftmap.sources.base import FrameSource, auto_pixel_stride, first_depth_frame, open_source, reads_depth_pixels
from driftmap.sources.ros import (
    CAMERA_INFO,
    EXPORT_METADATA_NAME,
    POINTCLOUD2,
    POSE_STAMPED,
    TF_MESSAGE,
    TOPIC_TF,
    TOPIC_TF_STATIC,
    PointTimeReference,
)
from driftmap.trajectory import Trajectory

logger = logging.getLogger(__name__)

EXPORT_FORMAT_VERSION = "1"


def _topic_base(sensor_name: str) -> str:
    name = sensor_name.strip("/") or "sensor"
    return "/" + name


@dataclass
class _SensorState:
    sensor_name: str
    sensor_kind: SensorKind
    topic: str
    camera_info_topic: str | None
    ground_truth_topic: str | None
    sensor_frame: str
    base_frame: str
    world_frame: str | None
    T_base_sensor: NDArray[np.float64]
    depth_scale: float | None
    frame_ids: list[int] = field(default_factory=list)
    pose_sources: list[str] = field(default_factory=list)
    ground_truth_frame_ids: list[int] = field(default_factory=list)
    n_points: int = 0
    time_fields: set[str] = field(default_factory=set)
    last_stamp_ns: int | None = None


def _ground_truth_lookup(ground_truth: Trajectory | None) -> tuple[dict[int, NDArray], dict[int, NDArray]]:
    if ground_truth is None:
        return {}, {}
    by_id = {}
    if ground_truth.frame_ids is not None:
        by_id = {int(i): T for i, T in zip(ground_truth.frame_ids, ground_truth.poses, strict=True)}
    by_stamp = {int(s): T for s, T in zip(ground_truth.stamps_ns, ground_truth.poses, strict=True)}
    return by_id, by_stamp


def export_mcap(
    source_or_frames: FrameSource | Iterable[Frame],
    out_path: str | Path,
    *,
    ground_truth: Trajectory | None = None,
    compression: str = "zstd",
    chunk_size: int = 1024 * 1024,
    origin: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write frames as ROS 2 messages to ``out_path`` (see the module docstring for the layout).

    ``origin`` (``{"format", "path", "options"}``): the data set the frames were read from, recorded in the
    ``driftmap.export`` metadata; by default that of ``source_or_frames`` when it is a source (an MCAP that
    names an origin itself passes it on).

    ``ground_truth``: ``T_world_sensor`` poses (matched by ``frame_ids`` when it has them, else by stamp)
    written on ``/<sensor>/ground_truth``. ``compression``: ``"zstd"``, ``"lz4"`` or ``"none"``.
    The file is written next to ``out_path`` and renamed into place when complete.

    Returns a summary: frames and points written, per-sensor topics, poses and ground-truth poses written.
    """
    from mcap_ros2.writer import Writer

    out_path = Path(out_path)
    compression_type = mcap_compression(compression)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    partial = out_path.with_name(out_path.name + ".partial")
    gt_by_id, gt_by_stamp = _ground_truth_lookup(ground_truth)
    try:
        with open(partial, "wb") as stream:
            export = _FrameExport(Writer(stream, chunk_size=chunk_size, compression=compression_type), gt_by_id,
                                  gt_by_stamp)
            for frame in source_or_frames:
                export.write(frame)
            if export.n_frames == 0:
                uri = getattr(source_or_frames, "uri", "the frames")
                raise ExportError(
                    f"{uri}: no frame to write to {out_path} (an empty --frames selection?); nothing written"
                )
            export.finish(_origin_metadata(source_or_frames, origin))
        os.replace(partial, out_path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    summary = export.summary(out_path)
    logger.info("%s: wrote %d frames (%d points, %d poses)", out_path, export.n_frames, summary["points"],
                export.n_poses)
    return summary


class _FrameExport:
    """The messages of :func:`export_mcap`, frame by frame: per frame, in this order, ``/tf_static`` (a sensor's
    first frame), ``camera_info``, ``points``, ``/tf`` (frames with a pose), ``ground_truth`` (frames that have
    one); then the ``driftmap.export`` metadata. Log time = publish time = the frame's stamp."""

    def __init__(self, writer: Any, gt_by_id: dict[int, NDArray], gt_by_stamp: dict[int, NDArray]):
        self._writer = writer
        self._schemas = MsgdefSchemas(writer)
        self._gt_by_id, self._gt_by_stamp = gt_by_id, gt_by_stamp
        self.sensors: dict[str, _SensorState] = {}
        self._static_edges: dict[str, dict[str, Any]] = {}
        self.n_frames = self.n_poses = self.n_gt = 0

    def _message(self, topic: str, typename: str, msg: dict[str, Any], stamp_ns: int) -> None:
        self._writer.write_message(topic, self._schemas[typename], msg, log_time=stamp_ns, publish_time=stamp_ns)

    def write(self, frame: Frame) -> None:
        what = f"frame {frame.frame_id} ({frame.sensor_name})"
        state = self.sensors.get(frame.sensor_name)
        if state is None:
            state = self._add_sensor(frame, what)
        _check_consistent(state, frame, what)
        if frame.sensor_kind is SensorKind.DEPTH_CAMERA and frame.intrinsics is not None:
            assert state.camera_info_topic is not None
            self._message(state.camera_info_topic, CAMERA_INFO,
                          camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.sensor_frame, what), frame.stamp_ns)
        cloud, time_field = pointcloud2_msg(frame, what)
        if time_field:
            state.time_fields.add(time_field)
        self._message(state.topic, POINTCLOUD2, cloud, frame.stamp_ns)
        if frame.pose.source is not PoseSource.NONE:
            self._write_pose(state, frame, what)
        T_gt = self._gt_by_id.get(frame.frame_id) if self._gt_by_id else self._gt_by_stamp.get(frame.stamp_ns)
        if T_gt is not None:
            self._write_ground_truth(state, frame, T_gt, what)
        state.frame_ids.append(frame.frame_id)
        state.pose_sources.append(frame.pose.source.value)
        state.n_points += frame.n_points
        state.last_stamp_ns = frame.stamp_ns
        self.n_frames += 1

    def _add_sensor(self, frame: Frame, what: str) -> _SensorState:
        """The state of a new sensor; its ``base_frame -> sensor_frame`` edge joins ``/tf_static`` (every static
        edge so far is repeated, like a tf2 static broadcaster)."""
        state = _new_sensor(frame, self.sensors, what)
        self.sensors[frame.sensor_name] = state
        if state.base_frame != state.sensor_frame:
            self._static_edges[state.sensor_frame] = transform_stamped(
                frame.stamp_ns, state.base_frame, state.sensor_frame, state.T_base_sensor, what
            )
            self._message(TOPIC_TF_STATIC, TF_MESSAGE, {"transforms": list(self._static_edges.values())},
                          frame.stamp_ns)
        return state

    def _write_pose(self, state: _SensorState, frame: Frame, what: str) -> None:
        """``/tf`` ``world_frame -> base_frame`` = ``T_world_sensor @ inv(T_base_sensor)`` at the frame's stamp."""
        T_world_base = frame.pose.T_world_sensor @ geometry.invert(frame.T_base_sensor)
        world = state.world_frame or frame.pose.world_frame
        transform = transform_stamped(frame.stamp_ns, world, state.base_frame, T_world_base, what)
        self._message(TOPIC_TF, TF_MESSAGE, {"transforms": [transform]}, frame.stamp_ns)
        self.n_poses += 1

    def _write_ground_truth(self, state: _SensorState, frame: Frame, T_gt: NDArray, what: str) -> None:
        """``PoseStamped`` ``T_world_sensor`` on the sensor's ground-truth topic (made at its first pose)."""
        if state.ground_truth_topic is None:
            state.ground_truth_topic = _topic_base(frame.sensor_name) + "/ground_truth"
        t, q = geometry.to_tum(np.asarray(T_gt, dtype=np.float64))
        msg = {
            "header": ros_header(frame.stamp_ns, frame.pose.world_frame, what),
            "pose": {
                "position": {"x": float(t[0]), "y": float(t[1]), "z": float(t[2])},
                "orientation": {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])},
            },
        }
        self._message(state.ground_truth_topic, POSE_STAMPED, msg, frame.stamp_ns)
        state.ground_truth_frame_ids.append(frame.frame_id)
        self.n_gt += 1

    def finish(self, origin_metadata: dict[str, str]) -> None:
        """The ``driftmap.export`` metadata record, then the MCAP summary and footer."""
        self._writer.add_metadata(
            EXPORT_METADATA_NAME,
            {
                "version": EXPORT_FORMAT_VERSION,
                "driftmap_version": __version__,
                "sensors": json.dumps([_sensor_metadata(s) for s in self.sensors.values()]),
                **origin_metadata,
            },
        )
        self._writer.finish()

    def summary(self, out_path: Path) -> dict[str, Any]:
        """What :func:`export_mcap` returns."""
        return {
            "out": str(out_path),
            "frames": self.n_frames,
            "points": sum(s.n_points for s in self.sensors.values()),
            "poses_written": self.n_poses,
            "ground_truth_poses": self.n_gt,
            "bytes": out_path.stat().st_size,
            "sensors": {
                name: {
                    "topic": s.topic,
                    "camera_info_topic": s.camera_info_topic,
                    "ground_truth_topic": s.ground_truth_topic,
                    "frames": len(s.frame_ids),
                    "sensor_frame": s.sensor_frame,
                    "base_frame": s.base_frame,
                    "world_frame": s.world_frame,
                }
                for name, s in self.sensors.items()
            },
        }


def _new_sensor(frame: Frame, sensors: dict[str, _SensorState], what: str) -> _SensorState:
    base = _topic_base(frame.sensor_name)
    taken = {s.topic for s in sensors.values()}
    if base + "/points" in taken:
        raise ExportError(f"{what}: sensor names {frame.sensor_name!r} and another map to the same topic {base}/points")
    sensor_frame, base_frame = frame.sensor_frame, frame.base_frame
    if sensor_frame == base_frame and not np.array_equal(frame.T_base_sensor, np.eye(4)):
        raise ExportError(
            f"{what}: sensor_frame and base_frame are both {sensor_frame!r} but T_base_sensor is not identity"
        )
    world = frame.pose.world_frame if frame.pose.source is not PoseSource.NONE else None
    if world is not None and world in (base_frame, sensor_frame):
        raise ExportError(f"{what}: world frame {world!r} is also the base or sensor frame")
    for other in sensors.values():
        if other.sensor_frame == sensor_frame and other.base_frame != base_frame:
            raise ExportError(
                f"{what}: sensor frame {sensor_frame!r} has two parents ({other.base_frame!r}, {base_frame!r})"
            )
    return _SensorState(
        sensor_name=frame.sensor_name,
        sensor_kind=frame.sensor_kind,
        topic=base + "/points",
        camera_info_topic=base + "/camera_info" if frame.sensor_kind is SensorKind.DEPTH_CAMERA else None,
        ground_truth_topic=None,
        sensor_frame=sensor_frame,
        base_frame=base_frame,
        world_frame=world,
        T_base_sensor=np.array(frame.T_base_sensor),
        depth_scale=frame.depth_scale,
    )


def _check_consistent(state: _SensorState, frame: Frame, what: str) -> None:
    if frame.sensor_frame != state.sensor_frame or frame.base_frame != state.base_frame:
        raise ExportError(
            f"{what}: frames {frame.base_frame!r} -> {frame.sensor_frame!r} differ from the sensor's "
            f"first frame ({state.base_frame!r} -> {state.sensor_frame!r})"
        )
    if not np.array_equal(frame.T_base_sensor, state.T_base_sensor):
        raise ExportError(f"{what}: T_base_sensor differs from the sensor's first frame (written once on /tf_static)")
    if frame.pose.source is not PoseSource.NONE:
        if state.world_frame is None:
            state.world_frame = frame.pose.world_frame
        elif frame.pose.world_frame != state.world_frame:
            raise ExportError(f"{what}: world frame {frame.pose.world_frame!r} differs from {state.world_frame!r}")
    if state.last_stamp_ns is not None and frame.stamp_ns <= state.last_stamp_ns:
        raise ExportError(
            f"{what}: stamp {frame.stamp_ns} ns is not after the previous frame's {state.last_stamp_ns} ns"
        )


def source_origin(source: FrameSource, options: dict[str, Any] | None = None) -> dict[str, Any]:
    """The data set ``source`` reads: ``{"format", "path" (resolved), "options"}`` (the opener's options that
    choose the frames' sensor, e.g. ``sensor``, ``topic``; not ``frames`` / ``lenient``), or the ``origin`` an
    MCAP written by :func:`export_mcap` names itself."""
    export_origin = getattr(source, "export_origin", None)
    passed_on = export_origin() if callable(export_origin) else None
    if passed_on:
        return passed_on
    kept = {k: list(v) if isinstance(v, tuple) else v for k, v in (options or {}).items()
            if k not in ("frames", "lenient") and v is not None}
    return {"format": source.format_name, "path": str(Path(source.uri).resolve()), "options": kept}


def _origin_metadata(source_or_frames: object, origin: dict[str, Any] | None) -> dict[str, str]:
    """``origin``: the data set the frames were read from (:func:`source_origin`), so that what is known about it
    (a KITTI sequence's calibration and ground truth, the synthetic log's sensor frames) is not lost."""
    if origin is None and isinstance(source_or_frames, FrameSource):
        origin = source_origin(source_or_frames)
    return {} if origin is None else {"origin": json.dumps(origin, default=str)}  # e.g. a Path option


def _sensor_metadata(s: _SensorState) -> dict[str, Any]:
    return {
        "topic": s.topic,
        "camera_info_topic": s.camera_info_topic,
        "ground_truth_topic": s.ground_truth_topic,
        "sensor_name": s.sensor_name,
        "sensor_kind": s.sensor_kind.value,
        "sensor_frame": s.sensor_frame,
        "base_frame": s.base_frame,
        "world_frame": s.world_frame,
        "depth_scale": s.depth_scale,
        "frame_ids": s.frame_ids,
        "pose_sources": s.pose_sources,
        "ground_truth_frame_ids": s.ground_truth_frame_ids,
        "point_time": PointTimeReference.RELATIVE.value,
    }


def convert(
    src_path: str | Path, out_path: str | Path, *, format: str | None = None, frames: str | slice | None = None,
    pixel_stride: int | None = None, **options: Any,
) -> dict[str, Any]:
    """``driftmap convert SOURCE OUT.mcap [--format F] [--frames START:STOP[:STEP]] [--pixel-stride N]``: open any
    registered source and export its frames (and its ground truth, if it has one, on a separate topic) to MCAP.
    ``options`` go to the source's opener (e.g. ``sensor="lidar"``, ``topic=``).

    Depth images are back-projected at ``pixel_stride`` (None: as ``build`` reads them, every second pixel from 640 px
    wide on: :func:`~driftmap.sources.base.auto_pixel_stride`), so that a build of the MCAP stores the points a build
    of the source does (it keeps every point of a PointCloud2; before, a 640 px data set converted held 4x the points
    of its folder's build). A ``pixel_stride`` for a source of point clouds is a :class:`ConfigError`.

    Returns the :func:`export_mcap` summary plus ``source``, ``source_format``, ``skipped`` and, for depth images,
    ``pixel_stride``.
    """
    src_path, out_path = Path(src_path), Path(out_path)
    if out_path.exists() and src_path.exists() and out_path.resolve() == src_path.resolve():
        raise ExportError(f"{out_path}: output would overwrite the source")
    if pixel_stride is not None and (isinstance(pixel_stride, bool) or not isinstance(pixel_stride, int)
                                     or not 1 <= pixel_stride <= 64):
        raise ConfigError(f"pixel_stride: a whole number of pixels from 1 to 64, got {pixel_stride!r}")
    source = open_source(src_path, format=format, frames=frames, **options)
    stride = None
    if reads_depth_pixels(source):
        stride = pixel_stride if pixel_stride is not None else auto_pixel_stride(first_depth_frame(source))
        if stride != int(getattr(source, "pixel_stride", 1)):
            close = getattr(source, "close", None)
            if callable(close):
                close()
            options = {**options, "pixel_stride": stride}
            source = open_source(src_path, format=format, frames=frames, **options)
    elif pixel_stride is not None:
        raise ConfigError(f"--pixel-stride: {src_path} holds point clouds, not depth images (format "
                          f"{source.format_name}): there are no pixels to skip")
    ground_truth = source.ground_truth()
    summary = export_mcap(source, out_path, ground_truth=ground_truth, origin=source_origin(source, options))
    summary.update(source=str(src_path), source_format=source.format_name, skipped=len(source.skipped))
    if stride is not None:
        summary["pixel_stride"] = stride
    close = getattr(source, "close", None)
    if callable(close):
        close()
    return summary


__all__ = [
    "EXPORT_FORMAT_VERSION",
    "convert",
    "export_mcap",
    "source_origin",
]
