"""Names a ROS log is read by (formats, message types, standard topics), the clock that stamps frames, and field
access on decoded messages."""

from __future__ import annotations

import contextlib
import enum
from collections.abc import Iterator
from typing import Any

import numpy as np

from driftmap.errors import SourceError
from driftmap.sources.stamps import check_stamp_ns

FORMAT_MCAP = "mcap"
FORMAT_ROSBAG1 = "rosbag1"
FORMAT_ROSBAG2 = "rosbag2"

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROSBAG1_MAGIC = b"#ROSBAG V2.0"

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TOPIC_TF = "/tf"
TOPIC_TF_STATIC = "/tf_static"
#: Message types read as poses (:func:`~driftmap.sources.ros.poses.load_pose_topic`).
POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, TRANSFORM_STAMPED)

#: Name of the MCAP metadata record that :mod:`driftmap.export.mcap` writes.
EXPORT_METADATA_NAME = "driftmap.export"

#: Depth image encodings: numpy dtype and depth scale (units per metre; ``None`` = already metres).
DEPTH_ENCODINGS: dict[str, tuple[Any, float | None]] = {
    "16UC1": (np.uint16, 1000.0),
    "mono16": (np.uint16, 1000.0),
    "32FC1": (np.float32, None),
}

#: ``sensor_msgs/PointField`` datatype -> numpy type code.
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


class StampSource(enum.Enum):
    """Which clock stamps a frame (and the TF/odometry samples it is posed with)."""

    HEADER = "header"
    """``header.stamp`` of the message (the sensor's acquisition time)."""
    LOG = "log"
    """The time the recorder logged the message (MCAP ``log_time``, bag receive time)."""


def normalize_type(name: str) -> str:
    """``"sensor_msgs/PointCloud2"`` -> ``"sensor_msgs/msg/PointCloud2"`` (ROS 1 names to ROS 2 names)."""
    parts = name.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name.strip()


def stamp_ns_of(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) -> int nanoseconds (unchecked: :func:`header_stamp_ns`)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header_stamp_ns(stamp: Any, where: str) -> int:
    """A sensor message's ``header.stamp`` as a frame's stamp, checked: ``nanosec`` is the fraction of the second
    (``0 .. 999999999``: a larger one is not carried into ``sec``, it is a publisher's bug) and the stamp must be one
    a frame can carry (:func:`~driftmap.sources.stamps.check_stamp_ns`: ``sec >= 0``, within int64 ns).
    :class:`SourceError` naming ``where`` (the log, topic and message index) and the field otherwise."""
    nanosec = int(stamp.nanosec)
    if not 0 <= nanosec < 1_000_000_000:
        raise SourceError(f"{where}: header.stamp.nanosec is {nanosec}, not a fraction of a second (0 .. 999999999; "
                          f"header.stamp.sec is {int(stamp.sec)}): the publisher did not carry whole seconds into sec")
    return check_stamp_ns(stamp_ns_of(stamp), f"{where}: header.stamp")


@contextlib.contextmanager
def message_fields(what: str) -> Iterator[None]:
    """Field access on decoded messages: a message whose schema lacks a standard field of its type, or holds one of
    another type (a damaged or foreign schema decodes into such objects), is a :class:`SourceError` naming ``what``
    (the log, topic and message), not an ``AttributeError`` / ``TypeError`` from deep inside."""
    try:
        yield
    except (AttributeError, TypeError, ValueError, KeyError, IndexError, OverflowError) as exc:
        raise SourceError(f"{what}: the message does not have the fields of its type ({type(exc).__name__}: {exc}); "
                          f"is its schema damaged or not the standard one?") from exc


def first_field(msg: Any, *names: str) -> Any:
    """First attribute of ``msg`` among ``names`` (ROS 1 CameraInfo spells ``K``, ROS 2 ``k``)."""
    for name in names:
        if hasattr(msg, name):
            return getattr(msg, name)
    raise AttributeError(f"message has none of the fields {names}")
