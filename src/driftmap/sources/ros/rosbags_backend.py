"""ROS 1 ``.bag`` files and rosbag2 folders (sqlite3 or mcap storage), read through ``rosbags``' ``AnyReader``."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from driftmap.errors import SourceError
from driftmap.sources.ros.backend import Backend, RawMessage, TopicInfo
from driftmap.sources.ros.msgtypes import FORMAT_ROSBAG1, FORMAT_ROSBAG2, normalize_type


def rosbag2_dir(path: Path) -> Path | None:
    """The rosbag2 folder of ``path`` (the folder itself, or the folder of its ``.db3`` file)."""
    folder = path if path.is_dir() else path.parent if path.suffix == ".db3" else None
    if folder is None:
        return None
    meta = folder / "metadata.yaml"
    try:
        return folder if meta.is_file() and "rosbag2_bagfile_information" in meta.read_text(errors="replace") else None
    except OSError:
        return None


class RosbagsBackend(Backend):
    """``rosbags.highlevel.AnyReader`` over a ROS 1 bag or a rosbag2 folder (sqlite3 or mcap storage)."""

    def __init__(self, path: Path, format_name: str):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.format_name = format_name
        target = rosbag2_dir(path) if format_name == FORMAT_ROSBAG2 else path
        if target is None:
            raise SourceError(f"{path}: not a rosbag2 folder (no metadata.yaml with rosbag2_bagfile_information)")
        self._reader = AnyReader([target], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        try:
            self._reader.open()
        except Exception as exc:  # rosbags raises several error types for damaged or foreign files
            raise SourceError(f"{path}: cannot open {format_name} ({type(exc).__name__}: {exc})") from exc
        self._by_topic: dict[str, list[Any]] = {}
        for conn in self._reader.connections:
            self._by_topic.setdefault(conn.topic, []).append(conn)

    def topics(self) -> dict[str, TopicInfo]:
        out = {}
        for topic, conns in self._by_topic.items():
            ext = conns[0].ext
            encoding = getattr(ext, "serialization_format", "ros1")
            out[topic] = TopicInfo(
                topic,
                normalize_type(conns[0].msgtype),
                sum(c.msgcount for c in conns),
                encoding,
                "ros1msg" if self.format_name == FORMAT_ROSBAG1 else "ros2msg",
            )
        return out

    def stream(
        self, topics: Sequence[str], start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[RawMessage]:
        conns = [c for t in topics for c in self._by_topic.get(t, [])]
        if not conns:
            return
        try:
            for conn, log_time, rawdata in self._reader.messages(connections=conns, start=start_ns, stop=end_ns):
                yield RawMessage(conn.topic, int(log_time), (conn, rawdata), len(rawdata))
        except Exception as exc:
            if isinstance(exc, SourceError):
                raise
            raise SourceError(f"{self.path}: cannot read {', '.join(topics)} ({type(exc).__name__}: {exc})") from exc

    def check_decodable(self, topic: str) -> None:
        for conn in self._by_topic.get(topic, []):
            encoding = getattr(conn.ext, "serialization_format", "ros1")
            if encoding not in ("cdr", "ros1"):
                raise SourceError(f"{self.path}: topic {topic}: unknown message encoding {encoding!r} ({conn.msgtype})")
            if conn.msgtype not in self._reader.typestore.fielddefs:
                raise SourceError(f"{self.path}: topic {topic}: no definition for message type {conn.msgtype!r}")

    def decode(self, raw: RawMessage) -> Any:
        conn, rawdata = raw.handle
        try:
            return self._reader.deserialize(rawdata, conn.msgtype)
        except Exception as exc:
            raise SourceError(
                f"{self.path}: topic {raw.topic}: cannot decode message logged at {raw.log_time_ns} ns as "
                f"{conn.msgtype} ({type(exc).__name__}: {exc})"
            ) from exc

    def close(self) -> None:
        try:
            self._reader.close()
        except Exception:  # pragma: no cover - closing twice
            pass
