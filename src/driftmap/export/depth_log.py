"""A depth camera's images as a ROS-style MCAP log (``sensor_msgs/msg/Image`` + ``CameraInfo``, ``/tf_static`` and,
with poses, ``/tf``): the input of a ROS depth-camera source, written from arrays (tests, benchmarks, examples)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.export.ros_messages import (
    MsgdefSchemas,
    camera_info_msg,
    depth_image_msg,
    mcap_compression,
    transform_stamped,
)
from driftmap.frame import PinholeIntrinsics
from driftmap.sources.ros import CAMERA_INFO, IMAGE, TF_MESSAGE, TOPIC_TF, TOPIC_TF_STATIC


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
    compression_type = mcap_compression(compression)
    camera_info_topic = camera_info_topic or topic.rsplit("/", 1)[0] + "/camera_info"
    T_base_sensor = np.eye(4) if T_base_sensor is None else geometry.as_rigid(T_base_sensor, "T_base_sensor")
    n = 0
    with open(out_path, "wb") as stream:
        writer = Writer(stream, chunk_size=chunk_size, compression=compression_type)
        schemas = MsgdefSchemas(writer)
        for k, depth in enumerate(depths):
            stamp = int(stamps_ns[k])
            what = f"{out_path}: image {k}"
            if k == 0 and base_frame != frame_id:
                writer.write_message(
                    TOPIC_TF_STATIC,
                    schemas[TF_MESSAGE],
                    {"transforms": [transform_stamped(stamp, base_frame, frame_id, T_base_sensor, what)]},
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
                    {"transforms": [transform_stamped(stamp, world_frame, child, T_world_base, what)]},
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


__all__ = ["write_depth_image_mcap"]
