"""The topics a ROS log source reads: the sensor topic (PointCloud2 or depth Image), the CameraInfo topic paired
with it on the same ``frame_id``, and the CameraInfo in force at each message (parsed once per calibration)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import SourceError
from driftmap.frame import PinholeIntrinsics
from driftmap.sources.ros.backend import Backend, RawMessage, TopicInfo
from driftmap.sources.ros.messages import camera_info_intrinsics
from driftmap.sources.ros.msgtypes import CAMERA_INFO, DEPTH_ENCODINGS, IMAGE, POINTCLOUD2, first_field, message_fields
from driftmap.sources.tf import normalize_frame

logger = logging.getLogger(__name__)

CameraInfo = tuple[str, PinholeIntrinsics, tuple[str, ...]]
"""A parsed CameraInfo: ``(frame_id, intrinsics, quality flags)``."""


class FirstMessages:
    """An early decoded message of each topic of a log (``None`` if it has none). The first call peeks at every
    sensor and CameraInfo topic in one pass, so opening reads the first chunk of the log once."""

    def __init__(self, backend: Backend, topics: dict[str, TopicInfo]):
        self._backend = backend
        self._topics = topics
        self._firsts: dict[str, RawMessage] | None = None
        self._decoded: dict[str, Any] = {}

    def __call__(self, topic: str) -> Any:
        if self._firsts is None:
            peek = [t for t, i in self._topics.items() if i.msgtype in (POINTCLOUD2, IMAGE, CAMERA_INFO)]
            self._firsts = self._backend.first_messages(sorted(set(peek) | {topic}))
        if topic not in self._firsts:
            self._firsts.update(self._backend.first_messages([topic]))
        raw = self._firsts.get(topic)
        if raw is None:
            return None
        if topic not in self._decoded:
            self._decoded[topic] = self._backend.decode(raw)
        return self._decoded[topic]


def choose_sensor_topic(path: Path, topics: dict[str, TopicInfo], first_message: FirstMessages,
                        topic: str | None) -> str:
    """``topic`` checked to be a PointCloud2 or Image topic, or, without one, the log's only PointCloud2 or depth
    Image topic (:class:`SourceError` listing the topics otherwise)."""
    sensor_types = (POINTCLOUD2, IMAGE)
    if topic is not None:
        if topic not in topics:
            raise SourceError(
                f"{path}: no topic {topic!r}; topics: "
                + ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(topics.items()))
            )
        info = topics[topic]
        if info.msgtype not in sensor_types:
            raise SourceError(
                f"{path}: topic {topic} has schema {info.msgtype!r} "
                f"(encoding {info.message_encoding!r}); expected {POINTCLOUD2} or a depth {IMAGE}"
            )
        return topic
    candidates = []
    for name, info in sorted(topics.items()):
        if info.msgtype == POINTCLOUD2:
            candidates.append(name)
        elif info.msgtype == IMAGE:
            try:
                msg = first_message(name)
                with message_fields(f"{path}: {name} message 0"):
                    encoding = None if msg is None else str(msg.encoding)
            except SourceError:
                continue
            if encoding in DEPTH_ENCODINGS:
                candidates.append(name)
    if not candidates:
        listed = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(topics.items())) or "none"
        view = any(str(i.msgtype).startswith("foxglove") for i in topics.values())
        hint = ("; it looks like a Foxglove view (foxglove.* messages, e.g. what `driftmap export --mcap` writes: "
                "voxel-downsampled points to look at, not a log to read); read the log or data set it was made from"
                if view else "")
        raise SourceError(f"{path}: no PointCloud2 or depth Image topic to read frames from; topics: {listed}{hint}")
    if len(candidates) > 1:
        raise SourceError(f"{path}: several sensor topics, choose one with topic=: {', '.join(candidates)}")
    return candidates[0]


def choose_camera_info(path: Path, topics: dict[str, TopicInfo], first_message: FirstMessages, explicit: str | None,
                       *, sensor_topic: str, sensor_frame: str, msgtype: str) -> str | None:
    """The CameraInfo topic of ``sensor_topic``: ``explicit`` (checked), else the first CameraInfo topic on
    ``sensor_frame`` (those in the sensor topic's namespace first); ``None`` for a PointCloud2 topic without one."""
    if explicit is not None:
        info = topics.get(explicit)
        if info is None or info.msgtype != CAMERA_INFO:
            raise SourceError(f"{path}: camera_info_topic {explicit!r} is not a {CAMERA_INFO} topic")
        return explicit
    infos = [t for t, i in sorted(topics.items()) if i.msgtype == CAMERA_INFO]
    namespace = sensor_topic.rsplit("/", 1)[0]
    infos.sort(key=lambda t: (t.rsplit("/", 1)[0] != namespace, t))
    for name in infos:
        try:
            msg = first_message(name)
            with message_fields(f"{path}: {name} message 0"):
                frame = None if msg is None else normalize_frame(msg.header.frame_id)
        except SourceError as exc:
            logger.warning("%s: skipping CameraInfo topic %s: %s", path, name, exc)
            continue
        if frame == sensor_frame:
            return name
    if msgtype == IMAGE:
        raise SourceError(
            f"{path}: depth image topic {sensor_topic} (frame_id {sensor_frame!r}) has no "
            f"{CAMERA_INFO} on the same frame_id (CameraInfo topics: {', '.join(infos) or 'none'})"
        )
    return None


class CameraInfoTrack:
    """The CameraInfo messages of ``topic`` (``None``: the sensor has none): each parsed once per distinct
    calibration, and the one in force at a log time."""

    def __init__(self, backend: Backend, topic: str | None, *, ignore_distortion: bool):
        self._backend = backend
        self.topic = topic
        self.ignore_distortion = ignore_distortion
        self._log_times: NDArray[np.int64] | None = None
        self._by_index: dict[int, CameraInfo] = {}
        self._parsed: dict[tuple, CameraInfo] = {}

    def decode(self, raw: RawMessage) -> CameraInfo:
        """A CameraInfo message of the topic, decoded and parsed."""
        return self.parse(self._backend.decode(raw), f"{self._backend.path}: {self.topic}")

    def parse(self, msg: Any, what: str) -> CameraInfo:
        """``(frame_id, intrinsics, flags)`` of a CameraInfo; parsed once per distinct calibration."""
        with message_fields(what):
            return self._parse_fields(msg, what)

    def _parse_fields(self, msg: Any, what: str) -> CameraInfo:
        key = (
            msg.header.frame_id,
            tuple(first_field(msg, "k", "K")),
            tuple(first_field(msg, "d", "D")),
            msg.width,
            msg.height,
            getattr(msg, "binning_x", 0),
            getattr(msg, "binning_y", 0),
            getattr(msg, "distortion_model", ""),
        )
        parsed = self._parsed.get(key)
        if parsed is None:
            intrinsics, flags = camera_info_intrinsics(msg, what=what, ignore_distortion=self.ignore_distortion)
            parsed = (normalize_frame(msg.header.frame_id), intrinsics, flags)
            self._parsed[key] = parsed
        return parsed

    def at(self, log_time_ns: int) -> CameraInfo | None:
        """The CameraInfo logged last at or before ``log_time_ns`` (else the first one)."""
        if self.topic is None:
            return None
        if self._log_times is None:
            self._log_times = self._backend.log_times(self.topic)
        times = self._log_times
        if len(times) == 0:
            return None
        j = max(int(np.searchsorted(times, log_time_ns, side="right")) - 1, 0)
        if j not in self._by_index:
            self._by_index[j] = self.decode(self._backend.fetch(self.topic, j, times))
        return self._by_index[j]
