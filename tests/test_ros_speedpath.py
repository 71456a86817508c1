"""The fast path of ``RosLogSource`` over depth-image MCAPs (provenance URI resolved once per pass, one shared
identity pose for frames without a pose input, ``base_frame`` / CameraInfo flags handed to ``depth_frame``
instead of a second validated copy) against a reference decode of the same file:
the plain ``mcap`` reader + ``mcap_ros2`` decoder, ``driftmap.depth_frame`` and ``dataclasses.replace``. Every
field of every frame must be equal. Real 7-Scenes depth images; no timing here (speed is in benchmarks/)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2McapWriter
from PIL import Image

from driftmap import PinholeIntrinsics, PoseEstimate, PoseSource, Provenance, SourceError, depth_frame
from driftmap.export.depth_log import write_depth_image_mcap
from driftmap.export.ros_messages import ros2_msgdef
from driftmap.frame import Frame, FrameQuality
from driftmap.preprocess.depth import InvalidFractionMonitor
from driftmap.sources.ros import RosLogSource, StampSource, provenance_uri

K = PinholeIntrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
STAMP0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 33_333_333
IDS = [0, 40, 80, 120, 160, 200, 240, 280]
TOPIC = "/camera/depth/image_raw"
INFO_TOPIC = "/camera/depth/camera_info"
DISTORTION = [0.05, -0.01, 0.0, 0.0, 0.001]


def load_depths(sevenscenes_dir: Path) -> list[np.ndarray]:
    depths = [np.array(Image.open(sevenscenes_dir / f"frame-{i:06d}.depth.png")) for i in IDS]
    # the last image mostly unreadable: the invalid-fraction monitor flags it (a quality flag of its own)
    blanked = depths[-1].copy()
    blanked[:400] = 0
    depths[-1] = blanked
    return depths


def plain_messages(path: Path) -> list[tuple[int, Any, Any]]:
    """(index on the image topic, image message, last CameraInfo message before it), no driftmap code."""
    out, info, k = [], None, 0
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages(topics=[TOPIC, INFO_TOPIC]):
            if channel.topic == INFO_TOPIC:
                info = msg
                continue
            out.append((k, msg, info))
            k += 1
    return out


def reference_frames(path: Path, *, flags: tuple[str, ...] = ()) -> list[Frame]:
    """The frames as the source made them before the fast path: depth_frame, then dataclasses.replace."""
    monitor = InvalidFractionMonitor()
    uri = provenance_uri(path, TOPIC, StampSource.HEADER)
    frames = []
    for k, msg, info in plain_messages(path):
        assert info is not None and list(info.k) == [585.0, 0, 320.0, 0, 585.0, 240.0, 0, 0, 1]
        depth = np.frombuffer(msg.data, dtype="<u2").reshape(msg.height, msg.width)
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        frame = depth_frame(
            depth,
            K,
            frame_id=k,
            stamp_ns=stamp_ns,
            pose=PoseEstimate(np.eye(4), source=PoseSource.NONE),
            sensor_name=TOPIC.strip("/"),
            sensor_frame=msg.header.frame_id,
            T_base_sensor=np.eye(4),
            depth_scale=1000.0,
            provenance=Provenance(uri, k),
            monitor=monitor,
        )
        changes: dict[str, Any] = {"base_frame": msg.header.frame_id}
        if flags:
            q = frame.quality
            changes["quality"] = FrameQuality(q.n_measurements, q.n_valid, q.invalid_counts, q.flags + flags)
        frames.append(dataclasses.replace(frame, **changes))
    return frames


def assert_equal_frames(ours: list[Frame], ref: list[Frame]) -> None:
    assert len(ours) == len(ref) == len(IDS)
    for a, b in zip(ours, ref, strict=True):
        assert a.points_sensor.tobytes() == b.points_sensor.tobytes(), f"frame {a.frame_id}: points differ"
        assert a.points_sensor.shape == b.points_sensor.shape and not a.points_sensor.flags.writeable
        assert (a.frame_id, a.stamp_ns, a.sensor_name) == (b.frame_id, b.stamp_ns, b.sensor_name)
        assert a.sensor_kind is b.sensor_kind
        assert (a.sensor_frame, a.base_frame, a.intrinsics, a.depth_scale) == (
            b.sensor_frame,
            b.base_frame,
            b.intrinsics,
            b.depth_scale,
        )
        assert a.quality == b.quality, f"frame {a.frame_id}: {a.quality} != {b.quality}"
        assert a.provenance == b.provenance
        assert np.array_equal(a.T_base_sensor, b.T_base_sensor) and not a.T_base_sensor.flags.writeable
        assert np.array_equal(a.pose.T_world_sensor, b.pose.T_world_sensor)
        assert (a.pose.source, a.pose.revision) == (b.pose.source, b.pose.revision)
        assert a.pose.world_frame == b.pose.world_frame
        assert not a.pose.T_world_sensor.flags.writeable  # shared between frames: must be immutable
        assert a.attributes.names() == b.attributes.names() == []


def test_depth_frames_equal_reference_decode(sevenscenes_dir: Path, tmp_path: Path) -> None:
    depths = load_depths(sevenscenes_dir)
    stamps = [STAMP0_NS + k * PERIOD_NS for k in range(len(depths))]
    path = write_depth_image_mcap(
        tmp_path / "depth.mcap", depths, stamps, K, topic=TOPIC, camera_info_topic=INFO_TOPIC, compression="none"
    )["out"]
    ref = reference_frames(path)
    assert any(f.quality.flags for f in ref), "the blanked image should be flagged by the monitor"
    with RosLogSource(path) as source:
        assert_equal_frames(list(source), ref)
    # random access (the provenance URI is resolved per call there), in order so the monitor sees the same history
    with RosLogSource(path) as source:
        assert_equal_frames([source.frame(i) for i in range(len(IDS))], ref)
    # the decode-only path: same images, stamps and intrinsics as the plain reader
    with RosLogSource(path) as source:
        raws = list(source.iter_raw())
    for raw, (_, msg, _), depth, stamp in zip(raws, plain_messages(path), depths, stamps, strict=True):
        assert np.array_equal(raw.depth, depth) and raw.depth.tobytes() == bytes(msg.data)
        assert raw.stamp_ns == stamp and raw.intrinsics == K and raw.flags == ()


def _header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000}, "frame_id": frame_id}


def test_distortion_flags_equal_reference_decode(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """CameraInfo flags (ignored distortion) are appended to the monitor's flags, as with dataclasses.replace."""
    depths = load_depths(sevenscenes_dir)
    path = tmp_path / "distorted.mcap"
    with open(path, "wb") as f:  # written with mcap_ros2 alone
        writer = Ros2McapWriter(f)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", ros2_msgdef("sensor_msgs/msg/CameraInfo"))
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", ros2_msgdef("sensor_msgs/msg/Image"))
        for k, depth in enumerate(depths):
            stamp = STAMP0_NS + k * PERIOD_NS
            info = {
                "header": _header(stamp, "cam"),
                "height": 480,
                "width": 640,
                "distortion_model": "plumb_bob",
                "d": DISTORTION,
                "k": [585.0, 0, 320.0, 0, 585.0, 240.0, 0, 0, 1],
                "r": [1.0, 0, 0, 0, 1, 0, 0, 0, 1],
                "p": [585.0, 0, 320.0, 0, 0, 585.0, 240.0, 0, 0, 0, 1, 0],
            }
            image = {
                "header": _header(stamp, "cam"),
                "height": 480,
                "width": 640,
                "encoding": "16UC1",
                "is_bigendian": False,
                "step": 1280,
                "data": depth.astype("<u2").tobytes(),
            }
            writer.write_message(INFO_TOPIC, info_schema, info, log_time=stamp, publish_time=stamp)
            writer.write_message(TOPIC, image_schema, image, log_time=stamp + 1, publish_time=stamp + 1)
        writer.finish()
    with pytest.raises(SourceError, match="distortion 'plumb_bob'"):
        RosLogSource(path).frame(0)
    flags = (f"distortion_ignored: plumb_bob D={DISTORTION}",)
    ref = reference_frames(path, flags=flags)
    with RosLogSource(path, ignore_distortion=True) as source:
        ours = list(source)
    assert all(f.quality.flags[-1] == flags[0] for f in ours)
    assert_equal_frames(ours, ref)
