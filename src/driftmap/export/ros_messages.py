"""Standard ROS 2 messages as the dicts ``mcap_ros2`` writes (:mod:`driftmap.export.mcap`): headers, transforms,
``CameraInfo``, ``PointCloud2`` and depth ``Image`` messages, and their schemas from rosbags' typestore."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap.errors import ExportError
from driftmap.frame import Frame, PinholeIntrinsics

_UINT32_MAX = 2**32 - 1
_MAX_ROS_SEC = 2**31 - 1


@functools.cache
def ros2_msgdef(typename: str) -> str:
    """The ``ros2msg`` schema text of a standard message (with its dependencies), from rosbags' typestore."""
    from rosbags.typesys import Stores, get_typestore

    text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(typename, ros_version=2)
    return text


def ros_time(stamp_ns: int, what: str) -> dict[str, int]:
    """``builtin_interfaces/msg/Time`` of a stamp; :class:`~driftmap.errors.ExportError` outside ROS time."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if stamp_ns < 0 or sec > _MAX_ROS_SEC:
        raise ExportError(f"{what}: stamp {stamp_ns} ns is outside ROS time (0 .. 2^31 s)")
    return {"sec": sec, "nanosec": nanosec}


def ros_header(stamp_ns: int, frame_id: str, what: str) -> dict[str, Any]:
    """A ``std_msgs/msg/Header`` dict; ``what`` names the message in an error about its stamp."""
    return {"stamp": ros_time(stamp_ns, what), "frame_id": frame_id}


def _transform_msg(T: NDArray[np.float64]) -> dict[str, Any]:
    q = Rotation.from_matrix(np.asarray(T[:3, :3])).as_quat()
    return {
        "translation": {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])},
        "rotation": {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])},
    }


def transform_stamped(stamp_ns: int, parent: str, child: str, T: NDArray[np.float64], what: str) -> dict[str, Any]:
    """A ``geometry_msgs/msg/TransformStamped`` dict ``parent -> child`` = ``T``."""
    return {"header": ros_header(stamp_ns, parent, what), "child_frame_id": child, "transform": _transform_msg(T)}


def camera_info_msg(
    intrinsics: PinholeIntrinsics, stamp_ns: int, frame_id: str, what: str = "CameraInfo"
) -> dict[str, Any]:
    """A ``sensor_msgs/msg/CameraInfo`` dict for pinhole intrinsics (no distortion)."""
    i = intrinsics
    return {
        "header": ros_header(stamp_ns, frame_id, what),
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
        "header": ros_header(frame.stamp_ns, frame.sensor_frame, what),
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
        "header": ros_header(stamp_ns, frame_id, what),
        "height": depth.shape[0],
        "width": depth.shape[1],
        "encoding": encoding,
        "is_bigendian": 0,
        "step": depth.shape[1] * depth.itemsize,
        "data": data,
    }


class MsgdefSchemas:
    """The schemas registered with an ``mcap_ros2`` writer, by message type (registered on first use)."""

    def __init__(self, writer: Any):
        self._writer = writer
        self._schemas: dict[str, Any] = {}

    def __getitem__(self, typename: str) -> Any:
        if typename not in self._schemas:
            self._schemas[typename] = self._writer.register_msgdef(typename, ros2_msgdef(typename))
        return self._schemas[typename]


def mcap_compression(compression: str) -> Any:
    """The ``mcap`` writer's compression for ``"zstd"``, ``"lz4"`` or ``"none"``."""
    from mcap.writer import CompressionType

    compressions = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
    if compression not in compressions:
        raise ExportError(f"compression must be one of {', '.join(compressions)}, got {compression!r}")
    return compressions[compression]


__all__ = [
    "MsgdefSchemas",
    "camera_info_msg",
    "depth_image_msg",
    "mcap_compression",
    "pointcloud2_msg",
    "ros2_msgdef",
    "ros_header",
    "ros_time",
    "transform_stamped",
]
