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

import functools
import json
import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap import __version__, geometry
from driftmap.errors import DriftmapError
from driftmap.frame import Frame, PinholeIntrinsics, PoseSource, SensorKind
from driftmap.sources.base import FrameSource, open_source
from driftmap.sources.ros import (
    CAMERA_INFO,
    EXPORT_METADATA_NAME,
    IMAGE,
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
_UINT32_MAX = 2**32 - 1
_MAX_ROS_SEC = 2**31 - 1


class ExportError(DriftmapError):
    """Frames cannot be written as requested (inconsistent frames, names, stamps)."""


@functools.cache
def ros2_msgdef(typename: str) -> str:
    """The ``ros2msg`` schema text of a standard message (with its dependencies), from rosbags' typestore."""
    from rosbags.typesys import Stores, get_typestore

    text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(typename, ros_version=2)
    return text


def _time(stamp_ns: int, what: str) -> dict[str, int]:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if stamp_ns < 0 or sec > _MAX_ROS_SEC:
        raise ExportError(f"{what}: stamp {stamp_ns} ns is outside ROS time (0 .. 2^31 s)")
    return {"sec": sec, "nanosec": nanosec}


def _header(stamp_ns: int, frame_id: str, what: str) -> dict[str, Any]:
    return {"stamp": _time(stamp_ns, what), "frame_id": frame_id}


def _transform_msg(T: NDArray[np.float64]) -> dict[str, Any]:
    q = Rotation.from_matrix(np.asarray(T[:3, :3])).as_quat()
    return {
        "translation": {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])},
        "rotation": {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])},
    }


def _transform_stamped(stamp_ns: int, parent: str, child: str, T: NDArray[np.float64], what: str) -> dict[str, Any]:
    return {"header": _header(stamp_ns, parent, what), "child_frame_id": child, "transform": _transform_msg(T)}


def camera_info_msg(
    intrinsics: PinholeIntrinsics, stamp_ns: int, frame_id: str, what: str = "CameraInfo"
) -> dict[str, Any]:
    """A ``sensor_msgs/msg/CameraInfo`` dict for pinhole intrinsics (no distortion)."""
    i = intrinsics
    return {
        "header": _header(stamp_ns, frame_id, what),
        "height": i.height,
        "width": i.width,
        "distortion_model": "plumb_bob",
        "d": [0.0] * 5,
        "k": [i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0],
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": [i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


_FLOAT32, _FLOAT64, _UINT32 = 7, 8, 6


def pointcloud2_msg(frame: Frame, what: str = "PointCloud2") -> tuple[dict[str, Any], str | None]:
    """A ``sensor_msgs/msg/PointCloud2`` dict of a frame's sensor-frame points and attributes, and the
    name of the per-point time field written (``t``, ``time`` or ``None``)."""
    n = frame.n_points
    a = frame.attributes
    names: list[str] = ["x", "y", "z"]
    formats: list[Any] = ["<f4", "<f4", "<f4"]
    kinds = [_FLOAT32] * 3
    if a.intensity is not None:
        names.append("intensity"), formats.append("<f4"), kinds.append(_FLOAT32)
    if a.normal_sensor is not None:
        names += ["normal_x", "normal_y", "normal_z"]
        formats += ["<f4"] * 3
        kinds += [_FLOAT32] * 3
    if a.color_rgb is not None:
        names.append("rgb"), formats.append("<u4"), kinds.append(_FLOAT32)  # PCL: packed uint32 read as float32
    time_field = None
    if a.time_offset_ns is not None:
        offsets = a.time_offset_ns
        if n == 0 or (int(offsets.min()) >= 0 and int(offsets.max()) <= _UINT32_MAX):
            time_field = "t"
            names.append("t"), formats.append("<u4"), kinds.append(_UINT32)
        else:
            time_field = "time"
            names.append("time"), formats.append("<f8"), kinds.append(_FLOAT64)
    dtype = np.dtype({"names": names, "formats": formats})  # packed, no padding
    cloud = np.empty(n, dtype=dtype)
    cloud["x"] = frame.points_sensor[:, 0]
    cloud["y"] = frame.points_sensor[:, 1]
    cloud["z"] = frame.points_sensor[:, 2]
    if a.intensity is not None:
        cloud["intensity"] = a.intensity
    if a.normal_sensor is not None:
        for k, c in enumerate(("normal_x", "normal_y", "normal_z")):
            cloud[c] = a.normal_sensor[:, k]
    if a.color_rgb is not None:
        rgb = a.color_rgb.astype(np.uint32)
        cloud["rgb"] = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    if time_field == "t":
        cloud["t"] = a.time_offset_ns
    elif time_field == "time":
        cloud["time"] = a.time_offset_ns.astype(np.float64) / 1e9  # type: ignore[union-attr]
    fields = [
        {"name": name, "offset": dtype.fields[name][1], "datatype": kind, "count": 1}
        for name, kind in zip(names, kinds, strict=True)
    ]
    msg = {
        "header": _header(frame.stamp_ns, frame.sensor_frame, what),
        "height": 1,
        "width": n,
        "fields": fields,
        "is_bigendian": False,
        "point_step": dtype.itemsize,
        "row_step": dtype.itemsize * n,
        "data": cloud.tobytes(),
        "is_dense": bool(np.isfinite(frame.points_sensor).all()),
    }
    return msg, time_field


def depth_image_msg(depth: NDArray, stamp_ns: int, frame_id: str, what: str = "Image") -> dict[str, Any]:
    """A ``sensor_msgs/msg/Image`` dict: uint16 -> ``16UC1`` (millimetres), float32 -> ``32FC1`` (metres)."""
    depth = np.ascontiguousarray(depth)
    if depth.ndim != 2:
        raise ExportError(f"{what}: depth must be (height, width), got shape {depth.shape}")
    if depth.dtype == np.uint16:
        encoding, wire = "16UC1", "<u2"
    elif depth.dtype == np.float32:
        encoding, wire = "32FC1", "<f4"
    else:
        raise ExportError(f"{what}: depth dtype {depth.dtype} (expected uint16 millimetres or float32 metres)")
    data = depth.astype(wire, copy=False).tobytes()
    return {
        "header": _header(stamp_ns, frame_id, what),
        "height": depth.shape[0],
        "width": depth.shape[1],
        "encoding": encoding,
        "is_bigendian": 0,
        "step": depth.shape[1] * depth.itemsize,
        "data": data,
    }


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


class _Schemas:
    def __init__(self, writer: Any):
        self._writer = writer
        self._schemas: dict[str, Any] = {}

    def __getitem__(self, typename: str) -> Any:
        if typename not in self._schemas:
            self._schemas[typename] = self._writer.register_msgdef(typename, ros2_msgdef(typename))
        return self._schemas[typename]


def _ground_truth_lookup(ground_truth: Trajectory | None) -> tuple[dict[int, NDArray], dict[int, NDArray]]:
    if ground_truth is None:
        return {}, {}
    by_id = {}
    if ground_truth.frame_ids is not None:
        by_id = {int(i): T for i, T in zip(ground_truth.frame_ids, ground_truth.poses, strict=True)}
    by_stamp = {int(s): T for s, T in zip(ground_truth.stamps_ns, ground_truth.poses, strict=True)}
    return by_id, by_stamp


def _compression_type(compression: str) -> Any:
    """The ``mcap`` writer's compression for ``"zstd"``, ``"lz4"`` or ``"none"``."""
    from mcap.writer import CompressionType

    compressions = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
    if compression not in compressions:
        raise ExportError(f"compression must be one of {', '.join(compressions)}, got {compression!r}")
    return compressions[compression]


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
    compression_type = _compression_type(compression)
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
        self._schemas = _Schemas(writer)
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
            self._static_edges[state.sensor_frame] = _transform_stamped(
                frame.stamp_ns, state.base_frame, state.sensor_frame, state.T_base_sensor, what
            )
            self._message(TOPIC_TF_STATIC, TF_MESSAGE, {"transforms": list(self._static_edges.values())},
                          frame.stamp_ns)
        return state

    def _write_pose(self, state: _SensorState, frame: Frame, what: str) -> None:
        """``/tf`` ``world_frame -> base_frame`` = ``T_world_sensor @ inv(T_base_sensor)`` at the frame's stamp."""
        T_world_base = frame.pose.T_world_sensor @ geometry.invert(frame.T_base_sensor)
        world = state.world_frame or frame.pose.world_frame
        transform = _transform_stamped(frame.stamp_ns, world, state.base_frame, T_world_base, what)
        self._message(TOPIC_TF, TF_MESSAGE, {"transforms": [transform]}, frame.stamp_ns)
        self.n_poses += 1

    def _write_ground_truth(self, state: _SensorState, frame: Frame, T_gt: NDArray, what: str) -> None:
        """``PoseStamped`` ``T_world_sensor`` on the sensor's ground-truth topic (made at its first pose)."""
        if state.ground_truth_topic is None:
            state.ground_truth_topic = _topic_base(frame.sensor_name) + "/ground_truth"
        t, q = geometry.to_tum(np.asarray(T_gt, dtype=np.float64))
        msg = {
            "header": _header(frame.stamp_ns, frame.pose.world_frame, what),
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


def write_depth_image_mcap(
    out_path: str | Path,
    depths: Iterable[NDArray],
    stamps_ns: Sequence[int],
    intrinsics: PinholeIntrinsics,
    *,
    topic: str = "/camera/depth/image_raw",
    camera_info_topic: str | None = None,
    frame_id: str = "camera_depth_optical_frame",
    base_frame: str = "base_link",
    T_base_sensor: NDArray[np.float64] | None = None,
    T_world_sensor: Sequence[NDArray[np.float64]] | None = None,
    world_frame: str = "odom",
    compression: str = "zstd",
    chunk_size: int = 1024 * 1024,
) -> dict[str, Any]:
    """Write depth images as a ROS-style camera log: ``sensor_msgs/msg/Image`` (``16UC1`` for uint16
    millimetres, ``32FC1`` for float32 metres) + ``CameraInfo`` per image on ``frame_id``, ``/tf_static``
    ``base_frame -> frame_id`` and, with ``T_world_sensor``, ``/tf`` ``world_frame -> base_frame`` per image.
    """
    from mcap_ros2.writer import Writer

    out_path = Path(out_path)
    compression_type = _compression_type(compression)
    camera_info_topic = camera_info_topic or topic.rsplit("/", 1)[0] + "/camera_info"
    T_base_sensor = np.eye(4) if T_base_sensor is None else geometry.as_rigid(T_base_sensor, "T_base_sensor")
    n = 0
    with open(out_path, "wb") as stream:
        writer = Writer(stream, chunk_size=chunk_size, compression=compression_type)
        schemas = _Schemas(writer)
        for k, depth in enumerate(depths):
            stamp = int(stamps_ns[k])
            what = f"{out_path}: image {k}"
            if k == 0 and base_frame != frame_id:
                writer.write_message(
                    TOPIC_TF_STATIC,
                    schemas[TF_MESSAGE],
                    {"transforms": [_transform_stamped(stamp, base_frame, frame_id, T_base_sensor, what)]},
                    log_time=stamp,
                    publish_time=stamp,
                )
            writer.write_message(
                camera_info_topic,
                schemas[CAMERA_INFO],
                camera_info_msg(intrinsics, stamp, frame_id, what),
                log_time=stamp,
                publish_time=stamp,
            )
            writer.write_message(
                topic, schemas[IMAGE], depth_image_msg(depth, stamp, frame_id, what), log_time=stamp, publish_time=stamp
            )
            if T_world_sensor is not None:
                T_ws = geometry.as_rigid(T_world_sensor[k], f"{what}: T_world_sensor")  # projected onto SE(3)
                T_world_base = T_ws @ geometry.invert(T_base_sensor)
                child = base_frame if base_frame != frame_id else frame_id
                writer.write_message(
                    TOPIC_TF,
                    schemas[TF_MESSAGE],
                    {"transforms": [_transform_stamped(stamp, world_frame, child, T_world_base, what)]},
                    log_time=stamp,
                    publish_time=stamp,
                )
            n += 1
        writer.finish()
    return {
        "out": str(out_path),
        "frames": n,
        "topic": topic,
        "camera_info_topic": camera_info_topic,
        "bytes": out_path.stat().st_size,
    }


def convert(
    src_path: str | Path, out_path: str | Path, *, format: str | None = None, frames: str | slice | None = None,
    **options: Any,
) -> dict[str, Any]:
    """``driftmap convert SOURCE OUT.mcap [--format F] [--frames START:STOP[:STEP]]``: open any registered
    source and export its frames (and its ground truth, if it has one, on a separate topic) to MCAP.
    ``options`` go to the source's opener (e.g. ``sensor="lidar"``, ``topic=``).

    Returns the :func:`export_mcap` summary plus ``source``, ``source_format`` and ``skipped``.
    """
    src_path, out_path = Path(src_path), Path(out_path)
    if out_path.exists() and src_path.exists() and out_path.resolve() == src_path.resolve():
        raise ExportError(f"{out_path}: output would overwrite the source")
    source = open_source(src_path, format=format, frames=frames, **options)
    ground_truth = source.ground_truth()
    summary = export_mcap(source, out_path, ground_truth=ground_truth, origin=source_origin(source, options))
    summary.update(source=str(src_path), source_format=source.format_name, skipped=len(source.skipped))
    close = getattr(source, "close", None)
    if callable(close):
        close()
    return summary


__all__ = [
    "ExportError",
    "camera_info_msg",
    "convert",
    "depth_image_msg",
    "export_mcap",
    "pointcloud2_msg",
    "ros2_msgdef",
    "write_depth_image_mcap",
]
