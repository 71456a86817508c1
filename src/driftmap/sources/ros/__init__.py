"""ROS logs as frame sources: MCAP with ROS 2 CDR messages, ROS 1 ``.bag`` files and rosbag2 folders.

Formats (registered at import):

* ``mcap``    -- a ``.mcap`` file with ROS 2 messages (``cdr`` encoding, ``ros2msg`` schemas), read with the
  ``mcap`` reader and ``mcap_ros2.decoder.DecoderFactory``. Uses the MCAP index: channel message counts
  for ``len``, message-index records for random access, ``iter_messages(starting_at=...)`` to start
  mid-file. A file without a summary (or truncated) is scanned once, linearly.
* ``rosbag1`` -- a ROS 1 ``.bag`` file, through ``rosbags`` (``AnyReader``).
* ``rosbag2`` -- a rosbag2 folder (``metadata.yaml`` + sqlite3 ``.db3`` or ``.mcap`` storage), through
  ``rosbags``. The ``.mcap`` file inside a rosbag2 folder can also be opened alone as format ``mcap``.

One source reads **one sensor topic**: a ``sensor_msgs/msg/PointCloud2`` topic (any field layout) or a
depth ``sensor_msgs/msg/Image`` topic (``16UC1``/``mono16`` millimetres, ``32FC1`` metres) paired with a
``sensor_msgs/msg/CameraInfo`` on the same ``header.frame_id``. Poses come from ``/tf`` (``pose_from_tf``)
or a ``nav_msgs/msg/Odometry`` topic (``pose_from_odometry``); extrinsics ``T_base_sensor`` from the TF
tree. See ``docs/sources-ros.md`` for every option, the stamp rules and the error behaviour.

Frame ids are the message index on the chosen topic (0 = first message), also after ``frames=`` slicing
and time ranges; an MCAP written by :func:`driftmap.export.mcap.export_mcap` restores the original
frame ids from its ``driftmap.export`` metadata record.

Layout of the package (each module one concept; this one re-exports their public names):

* :mod:`~driftmap.sources.ros.msgtypes` -- format, message type and topic names, :class:`StampSource`, field
  access on decoded messages;
* :mod:`~driftmap.sources.ros.backend`, :mod:`~driftmap.sources.ros.mcap_backend`,
  :mod:`~driftmap.sources.ros.rosbags_backend` -- reading messages from the containers;
  :mod:`~driftmap.sources.ros.containers` -- format detection and opening the right reader;
* :mod:`~driftmap.sources.ros.messages` -- PointCloud2, depth Image and CameraInfo decoding and checks;
* :mod:`~driftmap.sources.ros.poses` -- TF and pose topics, each frame's pose and ``T_base_sensor``;
* :mod:`~driftmap.sources.ros.topics` -- choosing the sensor topic and its CameraInfo;
* :mod:`~driftmap.sources.ros.provenance` -- provenance URIs and the ``driftmap.export`` metadata;
* :mod:`~driftmap.sources.ros.source` -- :class:`RosLogSource`, composing them;
* :mod:`~driftmap.sources.ros.registration` -- the formats in the source registry (registered on import).
"""

# Re-exports only. Besides __all__, the public names of the former single module ros.py stay importable from here
# (driftmap.export.mcap imports the message type and topic names).
# ruff: noqa: F401
from driftmap.sources.point_fields import PointTimeReference
from driftmap.sources.ros.backend import TopicInfo
from driftmap.sources.ros.containers import detect_format, list_topics, open_backend
from driftmap.sources.ros.messages import (
    CloudPoints,
    RawMeasurement,
    camera_info_intrinsics,
    depth_image_array,
    pointcloud2_array,
    pointcloud2_points,
)
from driftmap.sources.ros.msgtypes import (
    CAMERA_INFO,
    DEPTH_ENCODINGS,
    EXPORT_METADATA_NAME,
    FORMAT_MCAP,
    FORMAT_ROSBAG1,
    FORMAT_ROSBAG2,
    IMAGE,
    MCAP_MAGIC,
    ODOMETRY,
    POINTCLOUD2,
    POINTFIELD_TYPES,
    POSE_STAMPED,
    POSE_TYPES,
    POSE_WITH_COVARIANCE_STAMPED,
    ROSBAG1_MAGIC,
    TF_MESSAGE,
    TOPIC_TF,
    TOPIC_TF_STATIC,
    TRANSFORM_STAMPED,
    StampSource,
    message_fields,
    normalize_type,
    stamp_ns_of,
)
from driftmap.sources.ros.poses import (
    load_pose_topic,
    load_tf,
    pose_msg_matrix,
    read_pose_topic,
    read_tf,
    transform_msg_matrix,
)
from driftmap.sources.ros.provenance import parse_provenance_uri, provenance_uri, read_export_origin
from driftmap.sources.ros.registration import DEPTH_IMAGE_ONLY_OPTIONS  # importing it registers the formats
from driftmap.sources.ros.source import RosLogSource

__all__ = [
    "FORMAT_MCAP",
    "FORMAT_ROSBAG1",
    "FORMAT_ROSBAG2",
    "CloudPoints",
    "PointTimeReference",
    "RawMeasurement",
    "RosLogSource",
    "StampSource",
    "TopicInfo",
    "camera_info_intrinsics",
    "depth_image_array",
    "detect_format",
    "list_topics",
    "load_pose_topic",
    "load_tf",
    "open_backend",
    "parse_provenance_uri",
    "pointcloud2_array",
    "pointcloud2_points",
    "provenance_uri",
    "read_pose_topic",
    "read_tf",
]
