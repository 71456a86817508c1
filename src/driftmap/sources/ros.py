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
and time ranges; an MCAP written by :func:`driftmap.sources.mcap_export.export_mcap` restores the original
frame ids from its ``driftmap.export`` metadata record.
"""

from __future__ import annotations

import contextlib
import enum
import heapq
import inspect
import json
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import DepthError, DepthScaleError, GeometryError, SourceError
from driftmap.frame import (
    Frame,
    FrameQuality,
    PinholeIntrinsics,
    PointAttributes,
    PoseEstimate,
    PoseSource,
    Provenance,
    SensorKind,
)
from driftmap.preprocess.depth import (
    DEFAULT_MAX_DEPTH_M,
    DEFAULT_MIN_DEPTH_M,
    InvalidFractionMonitor,
    InvalidReason,
    depth_frame,
)
from driftmap.sources.base import FrameSource, register_source
from driftmap.sources.point_fields import (
    POINT_TIME_FIELDS,
    PointTimeReference,
    checked_normals,
    point_time_offsets_ns,
)
from driftmap.sources.redwood import checked_intrinsics
from driftmap.sources.stamps import check_stamp_ns
from driftmap.sources.tf import TfBuffer, TfError, TransformSeries, normalize_frame, transforms_from_tum

logger = logging.getLogger(__name__)

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

#: Name of the MCAP metadata record that :mod:`driftmap.sources.mcap_export` writes.
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
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) -> int nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


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


def _field(msg: Any, *names: str) -> Any:
    """First attribute of ``msg`` among ``names`` (ROS 1 CameraInfo spells ``K``, ROS 2 ``k``)."""
    for name in names:
        if hasattr(msg, name):
            return getattr(msg, name)
    raise AttributeError(f"message has none of the fields {names}")


# ---------------------------------------------------------------------------------------------------------
# format detection
# ---------------------------------------------------------------------------------------------------------


def _read_magic(path: Path, n: int) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(n)
    except OSError:
        return b""


def _rosbag2_dir(path: Path) -> Path | None:
    """The rosbag2 folder of ``path`` (the folder itself, or the folder of its ``.db3`` file)."""
    folder = path if path.is_dir() else path.parent if path.suffix == ".db3" else None
    if folder is None:
        return None
    meta = folder / "metadata.yaml"
    try:
        return folder if meta.is_file() and "rosbag2_bagfile_information" in meta.read_text(errors="replace") else None
    except OSError:
        return None


def _detect_mcap(path: Path) -> bool:
    return path.is_file() and _read_magic(path, len(MCAP_MAGIC)) == MCAP_MAGIC


def _detect_rosbag1(path: Path) -> bool:
    return path.is_file() and _read_magic(path, len(ROSBAG1_MAGIC)) == ROSBAG1_MAGIC


def _detect_rosbag2(path: Path) -> bool:
    return _rosbag2_dir(path) is not None


def detect_format(path: str | Path) -> str | None:
    """``"mcap"``, ``"rosbag1"``, ``"rosbag2"`` or ``None``."""
    path = Path(path)
    for name, detect in (
        (FORMAT_ROSBAG2, _detect_rosbag2),
        (FORMAT_MCAP, _detect_mcap),
        (FORMAT_ROSBAG1, _detect_rosbag1),
    ):
        if detect(path):
            return name
    return None


# ---------------------------------------------------------------------------------------------------------
# message backends: a thin layer over the mcap reader and rosbags' AnyReader
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TopicInfo:
    """A topic of a log: name, message type (ROS 2 spelling), message count and encodings."""

    name: str
    msgtype: str
    count: int | None
    message_encoding: str
    schema_encoding: str


@dataclass(frozen=True, slots=True)
class _Raw:
    """One undecoded message: topic, log time and a backend-specific handle."""

    topic: str
    log_time_ns: int
    handle: Any
    size_bytes: int


class _Backend:
    path: Path
    format_name: str

    def topics(self) -> dict[str, TopicInfo]:
        raise NotImplementedError

    def stream(self, topics: Sequence[str], start_ns: int | None = None, end_ns: int | None = None) -> Iterator[_Raw]:
        raise NotImplementedError

    def decode(self, raw: _Raw) -> Any:
        raise NotImplementedError

    def log_times(self, topic: str) -> NDArray[np.int64]:
        """Log times of every message of ``topic``, in reading order."""
        return np.fromiter((r.log_time_ns for r in self.stream([topic])), dtype=np.int64)

    def fetch(self, topic: str, k: int, log_times: NDArray[np.int64]) -> _Raw:
        """The ``k``-th message of ``topic`` (``log_times`` from :meth:`log_times`)."""
        t = int(log_times[k])
        j = k - int(np.searchsorted(log_times, t, side="left"))
        for n, raw in enumerate(self.stream([topic], t, t + 1)):
            if n == j:
                return raw
        raise SourceError(f"{self.path}: topic {topic}: message {k} (log time {t} ns) not found where the index says")

    def check_decodable(self, topic: str) -> None:
        """Raise :class:`SourceError` naming topic and schema when messages of ``topic`` cannot be decoded."""

    def first_messages(self, topics: Sequence[str]) -> dict[str, _Raw]:
        """An early message of each topic (the first one, or one from the first chunk holding the topic)."""
        out = {}
        for topic in topics:
            for raw in self.stream([topic]):
                out[topic] = raw
                break
        return out

    def metadata(self) -> dict[str, dict[str, str]]:
        return {}

    def close(self) -> None:
        pass


class _McapBackend(_Backend):
    """``mcap`` reader + ``mcap_ros2`` decoder; an in-memory catalogue for files without a usable summary."""

    format_name = FORMAT_MCAP

    def __init__(self, path: Path, *, lenient: bool):
        from mcap.reader import SeekingReader
        from mcap_ros2.decoder import DecoderFactory

        self.path = path
        self.lenient = lenient
        try:
            self._file = open(path, "rb")
        except OSError as exc:
            raise SourceError(f"{path}: cannot open MCAP file ({exc})") from exc
        self._size = path.stat().st_size
        try:
            self._reader = SeekingReader(self._file)
        except Exception as exc:  # McapError, or whatever a damaged magic / header makes the parser raise
            self._file.close()
            raise SourceError(f"{path}: not an MCAP file ({type(exc).__name__}: {exc})") from exc
        self._factory = DecoderFactory()
        self._decoders: dict[int, Any] = {}
        self._summary = None
        self._memory: dict[str, list[tuple[int, int, Any, Any, Any]]] | None = None
        self._mem_channels: dict[int, Any] = {}
        self._mem_schemas: dict[int, Any] = {}
        self._mem_metadata: dict[str, dict[str, str]] = {}
        self.damage: str | None = None
        """Why the file could not be read to its end (lenient mode only)."""
        footer_problem = None
        try:
            self._summary = self._reader.get_summary()
        except Exception as exc:  # no footer / summary: a truncated file, or one written without a summary
            footer_problem = exc
        if self._summary is None:
            try:
                self._scan(footer_problem)
            except BaseException:
                self._file.close()
                raise

    # -- linear scan (no summary, or a damaged/truncated file)
    def _scan(self, footer_problem: Exception | None) -> None:
        from mcap.records import Channel, Message, Metadata, Schema
        from mcap.stream_reader import StreamReader

        memory: dict[str, list[tuple[int, int, Any, Any, Any]]] = {}
        self._file.seek(0)
        reader = StreamReader(self._file, skip_magic=False)
        readable_to = len(MCAP_MAGIC)
        seq = 0
        try:
            for record in reader.records:
                if isinstance(record, Schema):
                    self._mem_schemas[record.id] = record
                elif isinstance(record, Channel):
                    self._mem_channels[record.id] = record
                elif isinstance(record, Message):
                    channel = self._mem_channels.get(record.channel_id)
                    if channel is None:
                        raise SourceError(f"{self.path}: message on unknown channel id {record.channel_id}")
                    schema = self._mem_schemas.get(channel.schema_id)
                    memory.setdefault(channel.topic, []).append((record.log_time, seq, channel, schema, record))
                    seq += 1
                elif isinstance(record, Metadata):
                    self._mem_metadata[record.name] = dict(record.metadata)
                readable_to = self._file.tell()
        except SourceError:
            raise
        except Exception as exc:  # any record that does not parse (short read, bad compression, ...) is damage
            n = sum(len(v) for v in memory.values())
            message = (
                f"{self.path}: truncated or damaged MCAP: nothing readable after byte offset {readable_to} of "
                f"{self._size} ({type(exc).__name__}: {exc}); {n} messages before it are readable"
            )
            if not self.lenient:
                raise SourceError(message + " (open with lenient=True, CLI --lenient, to read them)") from exc
            logger.warning("%s; reading those (lenient)", message)
            self.damage = message
        else:
            if footer_problem is not None:  # pragma: no cover - summary unreadable but records fine
                logger.warning("%s: summary unreadable (%s); read the file linearly", self.path, footer_problem)
            logger.info("%s: no MCAP summary; scanned the file linearly (%d messages)", self.path, seq)
        for entries in memory.values():
            entries.sort(key=lambda e: (e[0], e[1]))
        self._memory = memory

    # -- topics
    def topics(self) -> dict[str, TopicInfo]:
        if self._memory is not None:
            channels = list(self._mem_channels.values())
            schemas = self._mem_schemas
            counts: dict[int, int] = {}
            for entries in self._memory.values():
                for e in entries:
                    counts[e[2].id] = counts.get(e[2].id, 0) + 1
            has_counts = True
        else:
            assert self._summary is not None
            channels = list(self._summary.channels.values())
            schemas = self._summary.schemas
            stats = self._summary.statistics
            has_counts = stats is not None
            counts = dict(stats.channel_message_counts) if stats is not None else {}
        out: dict[str, TopicInfo] = {}
        for ch in channels:
            schema = schemas.get(ch.schema_id)
            count: int | None = counts.get(ch.id, 0) if has_counts else None
            prev = out.get(ch.topic)
            if prev is not None:
                count = None if count is None or prev.count is None else count + prev.count
            out[ch.topic] = TopicInfo(
                ch.topic,
                normalize_type(schema.name) if schema is not None else "",
                count,
                ch.message_encoding,
                schema.encoding if schema is not None else "",
            )
        return out

    # -- reading
    def stream(self, topics: Sequence[str], start_ns: int | None = None, end_ns: int | None = None) -> Iterator[_Raw]:
        if self._memory is not None:
            lists = [self._memory.get(t, []) for t in topics]
            for log_time, _, channel, schema, message in heapq.merge(*lists, key=lambda e: (e[0], e[1])):
                if (start_ns is not None and log_time < start_ns) or (end_ns is not None and log_time >= end_ns):
                    continue
                yield _Raw(channel.topic, log_time, (schema, channel, message), len(message.data))
            return
        try:
            for schema, channel, message in self._reader.iter_messages(
                topics=list(topics), starting_at=start_ns, ending_before=end_ns
            ):
                yield _Raw(channel.topic, message.log_time, (schema, channel, message), len(message.data))
        except SourceError:
            raise
        except Exception as exc:  # a chunk that does not parse or decompress
            raise SourceError(
                f"{self.path}: damaged MCAP data while reading {', '.join(topics)} ({type(exc).__name__}: {exc})"
            ) from exc

    def decoder(self, topic: str, channel: Any, schema: Any) -> Any:
        """The ROS 2 decoder of a channel; :class:`SourceError` naming topic and schema if there is none."""
        decoder = self._decoders.get(channel.id)
        if decoder is not None:
            return decoder
        schema_name = schema.name if schema is not None else "<no schema>"
        schema_encoding = schema.encoding if schema is not None else ""
        try:
            decoder = self._factory.decoder_for(channel.message_encoding, schema)
        except Exception as exc:  # the ros2msg schema text does not parse
            raise SourceError(
                f"{self.path}: topic {topic}: cannot parse schema {schema_name!r} ({schema_encoding}): {exc}"
            ) from exc
        if decoder is None:
            raise SourceError(
                f"{self.path}: topic {topic}: unknown message encoding {channel.message_encoding!r} with schema "
                f"{schema_name!r} (schema encoding {schema_encoding!r}); driftmap reads ROS 2 messages "
                f"(message encoding 'cdr', schema encoding 'ros2msg')"
            )
        self._decoders[channel.id] = decoder
        return decoder

    def check_decodable(self, topic: str) -> None:
        if self._memory is not None:
            entries = self._memory.get(topic)
            if entries:
                self.decoder(topic, entries[0][2], entries[0][3])
            return
        assert self._summary is not None
        for channel in self._summary.channels.values():
            if channel.topic == topic:
                self.decoder(topic, channel, self._summary.schemas.get(channel.schema_id))

    def decode(self, raw: _Raw) -> Any:
        schema, channel, message = raw.handle
        decoder = self.decoder(raw.topic, channel, schema)
        try:
            return decoder(message.data)
        except Exception as exc:
            raise SourceError(
                f"{self.path}: topic {raw.topic}: cannot decode message logged at {raw.log_time_ns} ns as "
                f"{schema.name if schema else '?'} ({type(exc).__name__}: {exc})"
            ) from exc

    @contextlib.contextmanager
    def _records(self, what: str) -> Iterator[None]:
        """Records read directly (chunks, message indexes): whatever a damaged one makes the parser raise is a
        :class:`SourceError` naming the file."""
        try:
            yield
        except SourceError:
            raise
        except Exception as exc:  # the mcap parser raises many types for a damaged record
            raise SourceError(
                f"{self.path}: damaged MCAP data while reading {what} ({type(exc).__name__}: {exc})"
            ) from exc

    def log_times(self, topic: str) -> NDArray[np.int64]:
        """From the message-index records next to every chunk (no chunk is decompressed)."""
        with self._records(f"the message index of {topic}"):
            return self._log_times(topic)

    def _log_times(self, topic: str) -> NDArray[np.int64]:
        from mcap.records import MessageIndex
        from mcap.stream_reader import StreamReader

        if self._memory is not None:
            return np.array([e[0] for e in self._memory.get(topic, [])], dtype=np.int64)
        summary = self._summary
        assert summary is not None
        channel_ids = [cid for cid, ch in summary.channels.items() if ch.topic == topic]
        if not summary.chunk_indexes or any(not ci.message_index_offsets for ci in summary.chunk_indexes):
            return super().log_times(topic)  # no message indexes: read the chunks once
        entries: list[tuple[int, int, int]] = []
        for ci in summary.chunk_indexes:
            for cid in channel_ids:
                offset = ci.message_index_offsets.get(cid)
                if offset is None:
                    continue
                self._file.seek(offset)
                record = next(iter(StreamReader(self._file, skip_magic=True).records))
                if not isinstance(record, MessageIndex):
                    raise SourceError(
                        f"{self.path}: expected a message index at byte offset {offset}, found {type(record).__name__}"
                    )
                entries.extend((t, ci.chunk_start_offset, o) for t, o in record.records)
        entries.sort()
        return np.array([e[0] for e in entries], dtype=np.int64)

    def first_messages(self, topics: Sequence[str]) -> dict[str, _Raw]:
        """One pass over the earliest chunks: every chunk is read at most once, however many topics."""
        with self._records(f"the first messages of {', '.join(topics)}"):
            return self._first_messages(topics)

    def _first_messages(self, topics: Sequence[str]) -> dict[str, _Raw]:
        from mcap.records import Chunk, Message
        from mcap.stream_reader import StreamReader, breakup_chunk

        summary = self._summary
        if (
            self._memory is not None
            or summary is None
            or not summary.chunk_indexes
            or any(not ci.message_index_offsets for ci in summary.chunk_indexes)
        ):
            return super().first_messages(topics)
        wanted = {cid: ch for cid, ch in summary.channels.items() if ch.topic in set(topics)}
        out: dict[str, _Raw] = {}
        for ci in sorted(summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset)):
            if not any(cid in ci.message_index_offsets and wanted[cid].topic not in out for cid in wanted):
                continue
            self._file.seek(ci.chunk_start_offset)
            chunk = next(iter(StreamReader(self._file, skip_magic=True, emit_chunks=True).records))
            if not isinstance(chunk, Chunk):
                raise SourceError(f"{self.path}: expected a chunk at byte offset {ci.chunk_start_offset}")
            for record in breakup_chunk(chunk):
                if isinstance(record, Message) and record.channel_id in wanted:
                    channel = wanted[record.channel_id]
                    if channel.topic not in out:
                        out[channel.topic] = _Raw(
                            channel.topic,
                            record.log_time,
                            (summary.schemas.get(channel.schema_id), channel, record),
                            len(record.data),
                        )
            if len(out) == len({ch.topic for ch in wanted.values()}):
                break
        return out

    def fetch(self, topic: str, k: int, log_times: NDArray[np.int64]) -> _Raw:
        if self._memory is not None:
            log_time, _, channel, schema, message = self._memory[topic][k]
            return _Raw(topic, log_time, (schema, channel, message), len(message.data))
        return super().fetch(topic, k, log_times)

    def metadata(self) -> dict[str, dict[str, str]]:
        if self._memory is not None:
            return dict(self._mem_metadata)
        out = {}
        try:
            for record in self._reader.iter_metadata():
                out[record.name] = dict(record.metadata)
        except Exception as exc:  # metadata is optional; a damaged record must not stop reading
            logger.warning("%s: cannot read MCAP metadata (%s)", self.path, exc)
        return out

    def close(self) -> None:
        self._file.close()


class _RosbagsBackend(_Backend):
    """``rosbags.highlevel.AnyReader`` over a ROS 1 bag or a rosbag2 folder (sqlite3 or mcap storage)."""

    def __init__(self, path: Path, format_name: str):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.format_name = format_name
        target = _rosbag2_dir(path) if format_name == FORMAT_ROSBAG2 else path
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

    def stream(self, topics: Sequence[str], start_ns: int | None = None, end_ns: int | None = None) -> Iterator[_Raw]:
        conns = [c for t in topics for c in self._by_topic.get(t, [])]
        if not conns:
            return
        try:
            for conn, log_time, rawdata in self._reader.messages(connections=conns, start=start_ns, stop=end_ns):
                yield _Raw(conn.topic, int(log_time), (conn, rawdata), len(rawdata))
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

    def decode(self, raw: _Raw) -> Any:
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


def open_backend(path: str | Path, format: str | None = None, *, lenient: bool = False) -> _Backend:
    """The message reader for a log (``format`` as registered: ``mcap``, ``rosbag1``, ``rosbag2``)."""
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    fmt = format or detect_format(path)
    if fmt == FORMAT_MCAP:
        return _McapBackend(path, lenient=lenient)
    if fmt in (FORMAT_ROSBAG1, FORMAT_ROSBAG2):
        return _RosbagsBackend(path, fmt)
    raise SourceError(
        f"{path}: not a ROS log (expected an MCAP file, a ROS 1 .bag or a rosbag2 folder; format={format!r})"
    )


def list_topics(path: str | Path, format: str | None = None) -> dict[str, TopicInfo]:
    """Topics of a log with their message types and counts."""
    backend = open_backend(path, format)
    try:
        return backend.topics()
    finally:
        backend.close()


# ---------------------------------------------------------------------------------------------------------
# message conversions
# ---------------------------------------------------------------------------------------------------------


def _raw_bytes(data: Any) -> Any:
    """A ``uint8[]`` field (bytes from mcap_ros2, a numpy array from rosbags) as a buffer numpy can wrap."""
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data, dtype=np.uint8)
    return data


def pointcloud2_array(msg: Any, what: str = "PointCloud2") -> NDArray[np.void]:
    """All fields of a ``sensor_msgs/PointCloud2`` as a structured array of ``height * width`` points
    (row-major, row padding removed, fields in the message's byte order; nothing is filtered).

    Every size the message states (``width``, ``height``, ``point_step``, ``row_step``, the fields' offsets and
    counts) is checked against the bytes of ``data`` before anything is built: :class:`SourceError` naming
    ``what`` and the field otherwise."""
    data = _raw_bytes(msg.data)
    width, height, point_step, row_step = _checked_cloud_layout(msg, len(data), what)
    dtype = _cloud_dtype(msg, point_step, what)
    n = width * height
    if n == 0:
        return np.empty(0, dtype=dtype)
    if row_step == width * point_step:
        return np.frombuffer(data, dtype=dtype, count=n)
    rows = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    return rows.reshape(-1)


def _checked_cloud_layout(msg: Any, n_bytes: int, what: str) -> tuple[int, int, int, int]:
    """``(width, height, point_step, row_step)`` of a PointCloud2, checked against its ``n_bytes`` of data."""
    point_step = int(msg.point_step)
    width, height = int(msg.width), int(msg.height)
    row_step = int(msg.row_step)
    if point_step <= 0:
        raise SourceError(f"{what}: point_step is {point_step}")
    if width * height == 0:
        if n_bytes:
            raise SourceError(f"{what}: {width}x{height} points, but data has {n_bytes} bytes: width / height do not "
                              f"describe the data")
        if point_step >= 2**31:
            raise SourceError(f"{what}: point_step is {point_step}")
        return width, height, point_step, row_step
    if row_step < width * point_step:
        raise SourceError(f"{what}: row_step {row_step} < width {width} * point_step {point_step}")
    needed = row_step * (height - 1) + width * point_step
    if n_bytes < needed:
        raise SourceError(
            f"{what}: data has {n_bytes} bytes, {width}x{height} points with point_step {point_step} and row_step "
            f"{row_step} need {needed}"
        )
    if n_bytes > row_step * height:
        raise SourceError(
            f"{what}: data has {n_bytes} bytes, more than the height {height} * row_step {row_step} = "
            f"{row_step * height} of {width}x{height} points: width / height / row_step do not describe the data"
        )
    return width, height, point_step, row_step


def _cloud_dtype(msg: Any, point_step: int, what: str) -> np.dtype:
    """The structured dtype of one point (``point_step`` bytes), every field checked to fit in it."""
    endian = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        name = str(f.name)
        if not name or name in names:
            if name:
                logger.debug("%s: duplicate field %r ignored", what, name)
            continue
        code = POINTFIELD_TYPES.get(int(f.datatype))
        if code is None:
            raise SourceError(f"{what}: field {name!r} has unknown PointField datatype {f.datatype}")
        count = max(int(f.count), 1)
        item_bytes = np.dtype(code).itemsize * count
        if int(f.offset) < 0 or int(f.offset) + item_bytes > point_step:  # checked before a dtype of that size is made
            raise SourceError(
                f"{what}: field {name!r} (offset {f.offset}, {item_bytes} bytes) does not fit in "
                f"point_step {point_step}"
            )
        names.append(name)
        formats.append(np.dtype(endian + code) if count == 1 else np.dtype((endian + code, (count,))))
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


#: PointCloud2 fields read as one value per point
_SCALAR_FIELDS = frozenset(("x", "y", "z", "intensity", "rgb", "rgba", "r", "g", "b", "normal_x", "normal_y",
                            "normal_z", "ring", *POINT_TIME_FIELDS))


@dataclass(frozen=True)
class CloudPoints:
    """The usable content of one PointCloud2: finite points, their attributes and the rejection counts."""

    points: NDArray[np.float32]
    attributes: PointAttributes
    n_measurements: int
    invalid_counts: dict[str, int]
    ring: NDArray[np.uint16] | None
    """``ring`` field of the kept points, if present (:class:`PointAttributes` has no slot for it)."""
    time_field: str | None


def pointcloud2_points(
    msg: Any, stamp_ns: int, *, what: str = "PointCloud2", point_time: PointTimeReference = PointTimeReference.AUTO,
    warned: set[str] | None = None,
) -> CloudPoints:
    """Points (float32, sensor frame) and attributes of a PointCloud2; points with a NaN or inf coordinate
    are dropped and counted (whatever ``is_dense`` claims). ``warned``: the reading source's set of warnings given
    once (:func:`driftmap.sources.point_fields.checked_normals`)."""
    arr = pointcloud2_array(msg, what)
    names = arr.dtype.names or ()
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise SourceError(
            f"{what}: PointCloud2 has no {'/'.join(missing)} field (fields present: {', '.join(names) or 'none'})"
        )
    n = len(arr)
    for c in names:  # the fields read below hold one value per point
        if c in _SCALAR_FIELDS and arr.dtype[c].shape:
            raise SourceError(f"{what}: field {c!r} has count {arr.dtype[c].shape[0]}; expected 1 value per point")
    for c in "xyz":
        if arr.dtype[c].kind != "f" and arr.dtype[c].kind not in "iu":
            raise SourceError(f"{what}: field {c!r} has unsupported type {arr.dtype[c]}")
    xyz = np.empty((n, 3), dtype=np.float32)
    xyz[:, 0] = arr["x"]
    xyz[:, 1] = arr["y"]
    xyz[:, 2] = arr["z"]
    finite = np.isfinite(xyz).all(axis=1)
    n_valid = int(np.count_nonzero(finite))
    counts: dict[str, int] = {}
    keep: NDArray[np.bool_] | None = None
    if n_valid < n:
        n_nan = int(np.count_nonzero(np.isnan(xyz).any(axis=1)))
        counts = {InvalidReason.NAN.value: n_nan, InvalidReason.INF.value: n - n_valid - n_nan}
        keep = finite
        xyz = xyz[finite]

    def kept(values: NDArray) -> NDArray:
        return values if keep is None else values[keep]

    intensity = kept(arr["intensity"]).astype(np.float32) if "intensity" in names else None
    color = None
    if "rgb" in names or "rgba" in names:
        packed = kept(arr["rgb" if "rgb" in names else "rgba"])
        packed = (
            np.ascontiguousarray(packed).view(np.uint32) if packed.dtype.itemsize == 4 else packed.astype(np.uint32)
        )
        color = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1).astype(np.uint8)
    elif all(c in names for c in ("r", "g", "b")):
        color = np.stack([kept(arr[c]) for c in ("r", "g", "b")], axis=1).astype(np.uint8)
    normals = None
    if all(c in names for c in ("normal_x", "normal_y", "normal_z")):
        normals = checked_normals(np.stack([kept(arr[c]) for c in ("normal_x", "normal_y", "normal_z")], axis=1), what,
                                  warned)
    time_field = next((f for f in POINT_TIME_FIELDS if f in names), None)
    offsets = None
    if time_field is not None:
        offsets = point_time_offsets_ns(kept(arr[time_field]), stamp_ns, time_field, what, point_time)
    ring = kept(arr["ring"]).astype(np.uint16) if "ring" in names else None
    attributes = PointAttributes(intensity=intensity, color_rgb=color, normal_sensor=normals, time_offset_ns=offsets)
    return CloudPoints(xyz, attributes, n, counts, ring, time_field)


def depth_image_array(msg: Any, what: str = "Image") -> tuple[NDArray, float | None]:
    """A depth ``sensor_msgs/Image`` as a (height, width) array in native byte order, and its depth scale
    (1000 for ``16UC1``/``mono16`` millimetres, ``None`` for ``32FC1`` metres). Row padding is allowed."""
    encoding = str(msg.encoding)
    if encoding not in DEPTH_ENCODINGS:
        raise SourceError(
            f"{what}: image encoding {encoding!r} is not a depth encoding (expected {', '.join(DEPTH_ENCODINGS)})"
        )
    dtype, scale = DEPTH_ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    if width <= 0 or height <= 0:
        raise SourceError(f"{what}: image is {width}x{height}")
    if step < width * item:
        raise SourceError(f"{what}: step {step} < width {width} * {item} bytes")
    data = _raw_bytes(msg.data)
    needed = step * (height - 1) + width * item
    if len(data) < needed:
        raise SourceError(
            f"{what}: data has {len(data)} bytes, a {width}x{height} {encoding} image with step {step} needs {needed}"
        )
    if len(data) > step * height:
        raise SourceError(
            f"{what}: data has {len(data)} bytes, more than the height {height} * step {step} = {step * height} of a "
            f"{width}x{height} {encoding} image: width / height / step do not describe the data"
        )
    wire = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    image = np.ndarray((height, width), dtype=wire, buffer=data, strides=(step, item))
    if not wire.isnative or step != width * item:
        image = np.ascontiguousarray(image, dtype=np.dtype(dtype))
    return image, scale


def camera_info_intrinsics(
    msg: Any, *, what: str = "CameraInfo", ignore_distortion: bool = False
) -> tuple[PinholeIntrinsics, tuple[str, ...]]:
    """``PinholeIntrinsics`` of a ``sensor_msgs/CameraInfo`` and the quality flags to attach.

    Non-zero distortion coefficients raise :class:`SourceError` (depth back-projection here is pinhole)
    unless ``ignore_distortion``, which flags every frame instead. Binning other than 1 and skew are refused.
    """
    K = np.asarray(_field(msg, "k", "K"), dtype=np.float64).reshape(-1)
    D = np.asarray(_field(msg, "d", "D"), dtype=np.float64).reshape(-1)
    if K.size != 9:
        raise SourceError(f"{what}: K has {K.size} entries, expected 9")
    fx, skew, cx, _, fy, cy = K[0], K[1], K[2], K[3], K[4], K[5]
    if fx <= 0 or fy <= 0:
        raise SourceError(f"{what}: camera is not calibrated (K = {K.tolist()})")
    if abs(skew) > 1e-9 * abs(fx):
        raise SourceError(f"{what}: K has skew {skew} (pinhole intrinsics without skew are supported)")
    for name in ("binning_x", "binning_y"):
        value = int(getattr(msg, name, 0) or 0)
        if value > 1:
            raise SourceError(f"{what}: {name}={value} is not supported")
    flags: tuple[str, ...] = ()
    if D.size and np.any(D != 0):
        model = getattr(msg, "distortion_model", "")
        if not ignore_distortion:
            raise SourceError(
                f"{what}: distortion {model!r} D={D.tolist()} is not zero; depth is back-projected with a pinhole "
                f"model (pass ignore_distortion=True to accept and flag the frames)"
            )
        flags = (f"distortion_ignored: {model} D={D.tolist()}",)
    try:
        intrinsics = PinholeIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=int(msg.width), height=int(msg.height))
    except GeometryError as exc:
        raise SourceError(f"{what}: {exc}") from exc
    return checked_intrinsics(intrinsics, what), flags


def transform_msg_matrix(transform: Any) -> NDArray[np.float64]:
    """``geometry_msgs/Transform`` -> 4x4."""
    t, q = transform.translation, transform.rotation
    return transforms_from_tum([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])[0]


def pose_msg_matrix(pose: Any) -> NDArray[np.float64]:
    """``geometry_msgs/Pose`` -> 4x4."""
    p, q = pose.position, pose.orientation
    return transforms_from_tum([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])[0]


# ---------------------------------------------------------------------------------------------------------
# TF and pose topics
# ---------------------------------------------------------------------------------------------------------


def load_tf(
    backend: _Backend,
    *,
    stamp: StampSource = StampSource.HEADER,
    static_only: bool = False,
    buffer: TfBuffer | None = None,
    topics: Sequence[str] = (TOPIC_TF, TOPIC_TF_STATIC),
) -> TfBuffer:
    """Fill a :class:`TfBuffer` from the ``tf2_msgs/TFMessage`` topics of a log (``/tf_static`` as static
    edges). With ``stamp=LOG`` dynamic samples are keyed by the message's log time instead of each
    transform's ``header.stamp``."""
    buffer = TfBuffer() if buffer is None else buffer
    available = backend.topics()
    for topic in topics:
        is_static = topic == TOPIC_TF_STATIC
        if is_static is False and static_only:
            continue
        info = available.get(topic)
        if info is None:
            continue
        if info.msgtype != TF_MESSAGE:
            raise SourceError(f"{backend.path}: topic {topic} has type {info.msgtype}, expected {TF_MESSAGE}")
        samples: dict[tuple[str, str], tuple[list[int], list[list[float]], list[list[float]]]] = {}
        for raw in backend.stream([topic]):
            msg = backend.decode(raw)
            with message_fields(f"{backend.path}: {topic} message logged at {raw.log_time_ns} ns"):
                for tr in msg.transforms:
                    parent, child = normalize_frame(tr.header.frame_id), normalize_frame(tr.child_frame_id)
                    t, q = tr.transform.translation, tr.transform.rotation
                    entry = samples.setdefault((parent, child), ([], [], []))
                    entry[0].append(stamp_ns_of(tr.header.stamp) if stamp is StampSource.HEADER else raw.log_time_ns)
                    entry[1].append([float(t.x), float(t.y), float(t.z)])
                    entry[2].append([float(q.x), float(q.y), float(q.z), float(q.w)])
        for (parent, child), (stamps, trans, quats) in samples.items():
            T = transforms_from_tum(trans, quats, what=f"{backend.path}: {topic} {parent} -> {child}")
            if is_static:
                buffer.add_static(parent, child, T[-1])  # the last one published wins, as in tf2
            else:
                buffer.add_samples(parent, child, stamps, T)
    return buffer


def read_tf(path: str | Path, *, format: str | None = None, stamp: StampSource = StampSource.HEADER) -> TfBuffer:
    """The TF tree of a log (``/tf`` and ``/tf_static``)."""
    backend = open_backend(path, format)
    try:
        return load_tf(backend, stamp=StampSource(stamp))
    finally:
        backend.close()


POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, TRANSFORM_STAMPED)


def load_pose_topic(
    backend: _Backend, topic: str, *, stamp: StampSource = StampSource.HEADER, child_frame: str | None = None
) -> TransformSeries:
    """A pose topic as ``T_parent_child`` samples: ``nav_msgs/Odometry`` (``header.frame_id`` ->
    ``child_frame_id``), ``PoseStamped`` / ``PoseWithCovarianceStamped`` (``header.frame_id`` ->
    ``child_frame``, default the topic name) or ``TransformStamped``."""
    info = backend.topics().get(topic)
    if info is None:
        raise SourceError(f"{backend.path}: no topic {topic} (topics: {', '.join(sorted(backend.topics()))})")
    if info.msgtype not in POSE_TYPES:
        raise SourceError(
            f"{backend.path}: topic {topic} has type {info.msgtype}; expected one of {', '.join(POSE_TYPES)}"
        )
    stamps, trans, quats = [], [], []
    parents, children = set(), set()
    for raw in backend.stream([topic]):
        msg = backend.decode(raw)
        with message_fields(f"{backend.path}: {topic} message logged at {raw.log_time_ns} ns"):
            if info.msgtype == TRANSFORM_STAMPED:
                t, q = msg.transform.translation, msg.transform.rotation
                translation = [float(t.x), float(t.y), float(t.z)]
                children.add(normalize_frame(msg.child_frame_id))
            else:
                pose = msg.pose.pose if info.msgtype in (ODOMETRY, POSE_WITH_COVARIANCE_STAMPED) else msg.pose
                p, q = pose.position, pose.orientation
                translation = [float(p.x), float(p.y), float(p.z)]
                if info.msgtype == ODOMETRY:
                    children.add(normalize_frame(msg.child_frame_id))
            quats.append([float(q.x), float(q.y), float(q.z), float(q.w)])
            trans.append(translation)
            parents.add(normalize_frame(msg.header.frame_id))
            stamps.append(stamp_ns_of(msg.header.stamp) if stamp is StampSource.HEADER else raw.log_time_ns)
    if not stamps:
        raise SourceError(f"{backend.path}: topic {topic} has no messages")
    if len(parents) > 1 or len(children) > 1:
        raise SourceError(
            f"{backend.path}: topic {topic} changes frames (parents {sorted(parents)}, children {sorted(children)})"
        )
    child = children.pop() if children else (child_frame or topic.strip("/"))
    T = transforms_from_tum(trans, quats, what=f"{backend.path}: {topic}")
    series = TransformSeries.from_samples(parents.pop(), child, stamps, T, what=f"{backend.path}#{topic}")
    if len(series) < len(stamps):
        logger.warning(
            "%s: topic %s has %d messages with repeated stamps (the last one is kept)",
            backend.path,
            topic,
            len(stamps) - len(series),
        )
    return series


def read_pose_topic(
    path: str | Path,
    topic: str,
    *,
    format: str | None = None,
    stamp: StampSource = StampSource.HEADER,
    child_frame: str | None = None,
) -> TransformSeries:
    """Odometry / PoseStamped / PoseWithCovarianceStamped / TransformStamped samples of a log topic."""
    backend = open_backend(path, format)
    try:
        return load_pose_topic(backend, topic, stamp=StampSource(stamp), child_frame=child_frame)
    finally:
        backend.close()


# ---------------------------------------------------------------------------------------------------------
# the frame source
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RawMeasurement:
    """One decoded sensor message before back-projection or pose lookup (:meth:`RosLogSource.iter_raw`)."""

    message_index: int
    stamp_ns: int
    log_time_ns: int
    sensor_frame: str
    depth: NDArray | None
    """(height, width) uint16 or float32 depth image (native byte order), for Image topics."""
    depth_scale: float | None
    cloud: NDArray[np.void] | None
    """Structured array of every PointCloud2 field, for PointCloud2 topics."""
    cloud_msg: Any
    intrinsics: PinholeIntrinsics | None
    flags: tuple[str, ...]
    size_bytes: int


def provenance_uri(path: str | Path, topic: str, stamp: StampSource) -> str:
    """``/abs/log.mcap#/topic?stamp=header`` (the message index goes into ``Provenance.index``)."""
    return f"{Path(path).resolve()}#{topic}?stamp={stamp.value}"


def parse_provenance_uri(uri: str) -> tuple[str, str, StampSource]:
    """Inverse of :func:`provenance_uri`: ``(path, topic, stamp source)``."""
    path, _, rest = uri.partition("#")
    topic, _, query = rest.partition("?stamp=")
    return path, topic, StampSource(query or StampSource.HEADER.value)


class RosLogSource(FrameSource):
    """Frames of one PointCloud2 or depth Image topic of an MCAP file, ROS 1 bag or rosbag2 folder.

    Options:
        topic: the sensor topic; required when the log has several PointCloud2 / depth Image topics.
        stamp: :class:`StampSource` (``HEADER`` default, or ``LOG``) for frames and pose samples alike.
        start_ns, end_ns: keep frames with ``start_ns <= stamp < end_ns`` (by the chosen stamp).
        pose_from_tf: ``(world_frame, base_frame)``: pose of ``base_frame`` in ``world_frame`` from the TF
            tree at each frame's stamp (SE(3) interpolation), composed with the TF path to the sensor.
        pose_from_odometry: a ``nav_msgs/Odometry`` topic (``header.frame_id`` is the world frame,
            ``child_frame_id`` the body) interpolated at each frame's stamp.
        base_frame: the frame ``T_base_sensor`` is relative to; default: the pose input's body frame, else
            the sensor's own frame (identity extrinsics, TF not read).
        camera_info_topic: the CameraInfo topic to pair with (default: found by namespace and frame_id).
        min_depth_m, max_depth_m: valid depth range for Image topics.
        pixel_stride: keep every n-th pixel of depth images in both directions (see ``depth_frame``).
        point_time: :class:`PointTimeReference` of float per-point time fields.
        ignore_distortion: accept CameraInfo with non-zero distortion (frames are flagged).
        use_export_metadata: apply the ``driftmap.export`` metadata of MCAP files written by driftmap.
        frames, lenient: as in :class:`~driftmap.sources.base.FrameSource`.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        format: str | None = None,
        topic: str | None = None,
        stamp: StampSource | str = StampSource.HEADER,
        start_ns: int | None = None,
        end_ns: int | None = None,
        pose_from_tf: tuple[str, str] | None = None,
        pose_from_odometry: str | None = None,
        base_frame: str | None = None,
        camera_info_topic: str | None = None,
        min_depth_m: float = DEFAULT_MIN_DEPTH_M,
        max_depth_m: float = DEFAULT_MAX_DEPTH_M,
        pixel_stride: int = 1,
        point_time: PointTimeReference | str = PointTimeReference.AUTO,
        ignore_distortion: bool = False,
        use_export_metadata: bool = True,
        frames: str | slice | None = None,
        lenient: bool = False,
    ):
        super().__init__(str(path), frames=frames, lenient=lenient)
        self.path = Path(path)
        self.stamp = StampSource(stamp)
        self.point_time = PointTimeReference(point_time)
        self.start_ns, self.end_ns = start_ns, end_ns
        self.min_depth_m, self.max_depth_m = min_depth_m, max_depth_m
        self.pixel_stride = int(pixel_stride)
        self.ignore_distortion = ignore_distortion
        if pose_from_tf is not None and pose_from_odometry is not None:
            raise SourceError(f"{path}: give pose_from_tf or pose_from_odometry, not both")
        if pose_from_tf is not None and (
            len(pose_from_tf) != 2 or not all(isinstance(f, str) and f for f in pose_from_tf)
        ):
            raise SourceError(f"{path}: pose_from_tf must be (world_frame, base_frame), got {pose_from_tf!r}")
        self._backend = open_backend(self.path, format, lenient=lenient)
        try:
            self._setup(topic, pose_from_tf, pose_from_odometry, base_frame, camera_info_topic, use_export_metadata)
        except BaseException:
            self._backend.close()
            raise

    def _setup(
        self,
        topic: str | None,
        pose_from_tf: tuple[str, str] | None,
        pose_from_odometry: str | None,
        base_frame: str | None,
        camera_info_topic: str | None,
        use_export_metadata: bool,
    ) -> None:
        """Choose the topic and its CameraInfo, read the export metadata and the TF the options need."""
        self.format_name = self._backend.format_name
        self._topics = self._backend.topics()
        self._firsts: dict[str, _Raw] | None = None
        self._first_decoded: dict[str, Any] = {}
        self.topic = self._choose_topic(topic)
        info = self._topics[self.topic]
        self.msgtype = info.msgtype
        if self.pixel_stride != 1 and self.msgtype != IMAGE:
            raise SourceError(f"{self.path}: pixel_stride applies to depth images; {self.topic} is a {self.msgtype}")
        self._backend.check_decodable(self.topic)
        self._log_times: NDArray[np.int64] | None = None
        self._members: NDArray[np.int64] | None = None
        self._header_stamps: NDArray[np.int64] | None = None
        self._monitor = InvalidFractionMonitor()
        self._no_pose_estimate: PoseEstimate | None = None

        first = self._first_message(self.topic)
        if first is None:
            raise SourceError(f"{self.path}: topic {self.topic} has no messages")
        with message_fields(f"{self.path}: {self.topic} message 0"):
            self.first_sensor_frame = normalize_frame(first.header.frame_id)
            encoding = str(first.encoding) if self.msgtype == IMAGE else None
        if encoding is not None and encoding not in DEPTH_ENCODINGS:
            raise SourceError(
                f"{self.path}: topic {self.topic} is a {encoding!r} image, not a depth image "
                f"(expected {', '.join(DEPTH_ENCODINGS)})"
            )

        # driftmap export metadata (MCAP written by export_mcap)
        self._export: dict[str, Any] | None = self._export_entry() if use_export_metadata else None
        if (
            self._export is not None
            and pose_from_tf is None
            and pose_from_odometry is None
            and any(s != PoseSource.NONE.value for s in self._export.get("pose_sources", []))
        ):
            pose_from_tf = (self._export["world_frame"], self._export["base_frame"])
        if self._export is not None and self._export.get("point_time"):
            self.point_time = PointTimeReference(self._export["point_time"])

        self.camera_info_topic = self._choose_camera_info(camera_info_topic)
        self._caminfo_log_times: NDArray[np.int64] | None = None
        self._caminfo_cache: dict[int, tuple[str, PinholeIntrinsics, tuple[str, ...]]] = {}
        self._caminfo_parsed: dict[tuple, tuple[str, PinholeIntrinsics, tuple[str, ...]]] = {}

        # poses and extrinsics
        self.pose_from_tf = pose_from_tf
        self.pose_from_odometry = pose_from_odometry
        self._odometry: TransformSeries | None = None
        self._tf: TfBuffer | None = None
        self.world_frame: str | None = None
        pose_body: str | None = None
        if pose_from_odometry is not None:
            odom_info = self._topics.get(pose_from_odometry)
            if odom_info is not None and odom_info.msgtype != ODOMETRY:
                raise SourceError(
                    f"{self.path}: pose_from_odometry topic {pose_from_odometry} has type "
                    f"{odom_info.msgtype}, expected {ODOMETRY}"
                )
            self._odometry = load_pose_topic(self._backend, pose_from_odometry, stamp=self.stamp)
            self.world_frame, pose_body = self._odometry.parent_frame, self._odometry.child_frame
        elif pose_from_tf is not None:
            self.world_frame, pose_body = normalize_frame(pose_from_tf[0]), normalize_frame(pose_from_tf[1])
        self.pose_body_frame = pose_body
        if base_frame is None:
            base_frame = pose_body or (self._export or {}).get("base_frame") or self.first_sensor_frame
        self.base_frame = normalize_frame(base_frame)
        self._prepare_tf()

    # ---- setup helpers
    def _choose_topic(self, topic: str | None) -> str:
        sensor_types = (POINTCLOUD2, IMAGE)
        if topic is not None:
            if topic not in self._topics:
                raise SourceError(
                    f"{self.path}: no topic {topic!r}; topics: "
                    + ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(self._topics.items()))
                )
            info = self._topics[topic]
            if info.msgtype not in sensor_types:
                raise SourceError(
                    f"{self.path}: topic {topic} has schema {info.msgtype!r} "
                    f"(encoding {info.message_encoding!r}); expected {POINTCLOUD2} or a depth {IMAGE}"
                )
            return topic
        candidates = []
        for name, info in sorted(self._topics.items()):
            if info.msgtype == POINTCLOUD2:
                candidates.append(name)
            elif info.msgtype == IMAGE:
                try:
                    msg = self._first_message(name)
                    with message_fields(f"{self.path}: {name} message 0"):
                        encoding = None if msg is None else str(msg.encoding)
                except SourceError:
                    continue
                if encoding in DEPTH_ENCODINGS:
                    candidates.append(name)
        if not candidates:
            listed = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(self._topics.items())) or "none"
            raise SourceError(f"{self.path}: no PointCloud2 or depth Image topic to read frames from; topics: {listed}")
        if len(candidates) > 1:
            raise SourceError(f"{self.path}: several sensor topics, choose one with topic=: {', '.join(candidates)}")
        return candidates[0]

    def _first_message(self, topic: str) -> Any:
        """An early decoded message of ``topic`` (``None`` if it has none). The first call peeks at every
        sensor and CameraInfo topic in one pass, so opening reads the first chunk of the log once."""
        if self._firsts is None:
            peek = [t for t, i in self._topics.items() if i.msgtype in (POINTCLOUD2, IMAGE, CAMERA_INFO)]
            self._firsts = self._backend.first_messages(sorted(set(peek) | {topic}))
        if topic not in self._firsts:
            self._firsts.update(self._backend.first_messages([topic]))
        raw = self._firsts.get(topic)
        if raw is None:
            return None
        if topic not in self._first_decoded:
            self._first_decoded[topic] = self._backend.decode(raw)
        return self._first_decoded[topic]

    def export_origin(self) -> dict[str, Any] | None:
        """The data set an MCAP written by ``driftmap convert`` was read from (``{"format", "path",
        "options"}``), if it says so (:mod:`driftmap.sources.mcap_export`)."""
        return _parse_origin(self._backend.metadata().get(EXPORT_METADATA_NAME) or {})

    def _export_entry(self) -> dict[str, Any] | None:
        record = self._backend.metadata().get(EXPORT_METADATA_NAME)
        if not record:
            return None
        try:
            sensors = json.loads(record.get("sensors", "[]"))
        except json.JSONDecodeError as exc:
            logger.warning("%s: unreadable %s metadata (%s); ignored", self.path, EXPORT_METADATA_NAME, exc)
            return None
        entry = next((s for s in sensors if s.get("topic") == self.topic), None)
        if entry is None:
            return None
        count = self._topics[self.topic].count
        if count is not None and len(entry.get("frame_ids", [])) != count:
            logger.warning(
                "%s: %s metadata lists %d frames but %s has %d messages; ignored",
                self.path,
                EXPORT_METADATA_NAME,
                len(entry.get("frame_ids", [])),
                self.topic,
                count,
            )
            return None
        return entry

    def _choose_camera_info(self, explicit: str | None) -> str | None:
        if explicit is not None:
            info = self._topics.get(explicit)
            if info is None or info.msgtype != CAMERA_INFO:
                raise SourceError(f"{self.path}: camera_info_topic {explicit!r} is not a {CAMERA_INFO} topic")
            return explicit
        infos = [t for t, i in sorted(self._topics.items()) if i.msgtype == CAMERA_INFO]
        namespace = self.topic.rsplit("/", 1)[0]
        infos.sort(key=lambda t: (t.rsplit("/", 1)[0] != namespace, t))
        for name in infos:
            try:
                msg = self._first_message(name)
                with message_fields(f"{self.path}: {name} message 0"):
                    frame = None if msg is None else normalize_frame(msg.header.frame_id)
            except SourceError as exc:
                logger.warning("%s: skipping CameraInfo topic %s: %s", self.path, name, exc)
                continue
            if frame == self.first_sensor_frame:
                return name
        if self.msgtype == IMAGE:
            raise SourceError(
                f"{self.path}: depth image topic {self.topic} (frame_id {self.first_sensor_frame!r}) has no "
                f"{CAMERA_INFO} on the same frame_id (CameraInfo topics: {', '.join(infos) or 'none'})"
            )
        return None

    def _prepare_tf(self) -> None:
        """Read the TF the options need and check that the frames are connected (errors name both frames).

        Only ``/tf_static`` is read when static extrinsics are all that is needed; ``/tf`` is read for
        ``pose_from_tf`` or when the extrinsics chain has a dynamic edge.
        """
        pairs = [(self.base_frame, self.first_sensor_frame)]
        if self.pose_body_frame is not None:
            pairs.append((self.pose_body_frame, self.first_sensor_frame))
            if self.pose_from_tf is not None:
                pairs.append((self.world_frame, self.pose_body_frame))
        pairs = [(t, s) for t, s in pairs if t != s]
        if not pairs:
            return
        dynamic_read = self.pose_from_tf is not None
        self._tf = load_tf(self._backend, stamp=self.stamp, static_only=not dynamic_read)
        for target, source in pairs:
            try:
                self._tf.time_range_ns(target, source)  # raises on unknown frames, no path, no common time
                continue
            except TfError as exc:
                problem: TfError = exc
            if not dynamic_read:
                load_tf(self._backend, stamp=self.stamp, buffer=self._tf, topics=(TOPIC_TF,))
                dynamic_read = True
                try:
                    self._tf.time_range_ns(target, source)
                    continue
                except TfError as exc:
                    problem = exc
            raise SourceError(
                f"{self.path}: no TF path from {target!r} to {source!r} (sensor topic {self.topic}): {problem}"
            ) from None

    # ---- index bookkeeping
    def log_times(self) -> NDArray[np.int64]:
        """Log time of every message on the topic (from the MCAP message index where there is one)."""
        if self._log_times is None:
            self._log_times = self._backend.log_times(self.topic)
        return self._log_times

    def header_stamps(self) -> NDArray[np.int64]:
        """``header.stamp`` of every message on the topic (decodes every message once; cached)."""
        if self._header_stamps is None:
            with message_fields(f"{self.path}: {self.topic}"):
                self._header_stamps = np.fromiter(
                    (stamp_ns_of(self._backend.decode(raw).header.stamp) for raw in self._backend.stream([self.topic])),
                    dtype=np.int64,
                )
        return self._header_stamps

    def _stamps(self) -> NDArray[np.int64]:
        return self.log_times() if self.stamp is StampSource.LOG else self.header_stamps()

    def _member_indices(self) -> NDArray[np.int64] | None:
        if self.start_ns is None and self.end_ns is None:
            return None
        if self._members is None:
            stamps = self._stamps()
            keep = np.ones(len(stamps), dtype=bool)
            if self.start_ns is not None:
                keep &= stamps >= self.start_ns
            if self.end_ns is not None:
                keep &= stamps < self.end_ns
            self._members = np.flatnonzero(keep).astype(np.int64)
        return self._members

    def _count(self) -> int:
        members = self._member_indices()
        if members is not None:
            return len(members)
        count = self._topics[self.topic].count
        return int(count) if count is not None else len(self.log_times())

    def _message_index(self, index: int) -> int:
        members = self._member_indices()
        return int(members[index]) if members is not None else int(index)

    def _frame_id(self, index: int) -> int:
        m = self._message_index(index)
        if self._export is not None:
            return int(self._export["frame_ids"][m])
        return m

    def _stamp_ns(self, index: int) -> int | None:
        m = self._message_index(index)
        if self.stamp is StampSource.LOG:
            return int(self.log_times()[m])
        return int(self._header_stamps[m]) if self._header_stamps is not None else None

    # ---- camera info
    def _caminfo_from_msg(self, msg: Any, what: str) -> tuple[str, PinholeIntrinsics, tuple[str, ...]]:
        """``(frame_id, intrinsics, flags)`` of a CameraInfo; parsed once per distinct calibration."""
        with message_fields(what):
            return self._caminfo_fields(msg, what)

    def _caminfo_fields(self, msg: Any, what: str) -> tuple[str, PinholeIntrinsics, tuple[str, ...]]:
        key = (
            msg.header.frame_id,
            tuple(_field(msg, "k", "K")),
            tuple(_field(msg, "d", "D")),
            msg.width,
            msg.height,
            getattr(msg, "binning_x", 0),
            getattr(msg, "binning_y", 0),
            getattr(msg, "distortion_model", ""),
        )
        parsed = self._caminfo_parsed.get(key)
        if parsed is None:
            intrinsics, flags = camera_info_intrinsics(msg, what=what, ignore_distortion=self.ignore_distortion)
            parsed = (normalize_frame(msg.header.frame_id), intrinsics, flags)
            self._caminfo_parsed[key] = parsed
        return parsed

    def _caminfo_at(self, log_time_ns: int) -> tuple[str, PinholeIntrinsics, tuple[str, ...]] | None:
        """The CameraInfo logged last at or before ``log_time_ns`` (else the first one)."""
        if self.camera_info_topic is None:
            return None
        if self._caminfo_log_times is None:
            self._caminfo_log_times = self._backend.log_times(self.camera_info_topic)
        times = self._caminfo_log_times
        if len(times) == 0:
            return None
        j = max(int(np.searchsorted(times, log_time_ns, side="right")) - 1, 0)
        if j not in self._caminfo_cache:
            raw = self._backend.fetch(self.camera_info_topic, j, times)
            self._caminfo_cache[j] = self._caminfo_from_msg(
                self._backend.decode(raw), f"{self.path}: {self.camera_info_topic}"
            )
        return self._caminfo_cache[j]

    # ---- decoding
    def _measure(
        self, raw: _Raw, m: int, info: tuple[str, PinholeIntrinsics, tuple[str, ...]] | None
    ) -> RawMeasurement:
        """Message ``m`` decoded to arrays (no back-projection); its fields checked (:func:`message_fields`)."""
        with message_fields(f"{self.path}: {self.topic} message {m}"):
            return self._measure_fields(raw, m, info)

    def _measure_fields(
        self, raw: _Raw, m: int, info: tuple[str, PinholeIntrinsics, tuple[str, ...]] | None
    ) -> RawMeasurement:
        msg = self._backend.decode(raw)
        what = f"{self.path}: {self.topic} message {m}"
        sensor_frame = normalize_frame(msg.header.frame_id)
        if self.stamp is StampSource.HEADER:
            stamp_ns = check_stamp_ns(stamp_ns_of(msg.header.stamp), f"{what}: header.stamp")
        else:
            stamp_ns = check_stamp_ns(raw.log_time_ns, f"{what}: log time")
        if info is None and self.camera_info_topic is not None:
            info = self._caminfo_at(raw.log_time_ns)
        intrinsics, flags = None, ()
        if info is not None:
            info_frame, intrinsics, flags = info
            if info_frame != sensor_frame:
                if self.msgtype == IMAGE:
                    raise SourceError(
                        f"{what}: frame_id {sensor_frame!r} but CameraInfo on {self.camera_info_topic} "
                        f"has frame_id {info_frame!r}"
                    )
                intrinsics, flags = None, ()
        if self.msgtype == IMAGE:
            if intrinsics is None:
                raise SourceError(f"{what}: depth image (frame_id {sensor_frame!r}) has no CameraInfo")
            depth, scale = depth_image_array(msg, what)
            if (depth.shape[1], depth.shape[0]) != (intrinsics.width, intrinsics.height):
                raise SourceError(
                    f"{what}: image is {depth.shape[1]}x{depth.shape[0]} but CameraInfo on "
                    f"{self.camera_info_topic} says {intrinsics.width}x{intrinsics.height}"
                )
            return RawMeasurement(
                m, stamp_ns, raw.log_time_ns, sensor_frame, depth, scale, None, None, intrinsics, flags, raw.size_bytes
            )
        cloud = pointcloud2_array(msg, what)
        return RawMeasurement(
            m, stamp_ns, raw.log_time_ns, sensor_frame, None, None, cloud, msg, intrinsics, flags, raw.size_bytes
        )

    def _no_pose(self) -> PoseEstimate:
        """The identity ``PoseSource.NONE`` estimate of frames without a pose input. Made (and validated) once
        per source: a PoseEstimate is immutable (frozen, read-only matrix), so frames can share it."""
        if self._no_pose_estimate is None:
            self._no_pose_estimate = PoseEstimate(np.eye(4), source=PoseSource.NONE)
        return self._no_pose_estimate

    def _pose(self, m: int, stamp_ns: int, sensor_frame: str) -> tuple[PoseEstimate, NDArray[np.float64]]:
        """The pose estimate ``T_world_sensor`` and ``T_base_sensor`` of message ``m``."""
        tf = self._tf
        if self.base_frame == sensor_frame:
            T_base_sensor = np.eye(4)
        elif tf is not None:
            T_base_sensor = tf.lookup(self.base_frame, sensor_frame, stamp_ns)
        else:  # the sensor frame changed mid-log to one TF was not read for
            raise SourceError(
                f"{self.path}: {self.topic} message {m}: no TF path from {self.base_frame!r} to "
                f"{sensor_frame!r} (frame_id changed from {self.first_sensor_frame!r})"
            )
        recorded = None
        if self._export is not None:
            recorded = PoseSource(self._export["pose_sources"][m])
            if recorded is PoseSource.NONE:
                return self._no_pose(), T_base_sensor
        if self._odometry is None and self.pose_from_tf is None:
            return self._no_pose(), T_base_sensor
        body = self.pose_body_frame
        assert body is not None and self.world_frame is not None
        if self._odometry is not None:
            T_world_body = self._odometry.at(stamp_ns)
            source = PoseSource.ODOMETRY
        else:
            assert tf is not None
            T_world_body = tf.lookup(self.world_frame, body, stamp_ns)
            source = PoseSource.LOG
        if body == self.base_frame:
            T_body_sensor = T_base_sensor
        elif body == sensor_frame:
            T_body_sensor = np.eye(4)
        else:
            assert tf is not None
            T_body_sensor = tf.lookup(body, sensor_frame, stamp_ns)
        pose = PoseEstimate(
            T_world_body @ T_body_sensor, revision=0, source=recorded or source, world_frame=self.world_frame
        )
        return pose, T_base_sensor

    def _to_frame(self, raw: RawMeasurement, uri: str | None = None) -> Frame:
        """The :class:`Frame` of a measurement; ``uri`` is :func:`provenance_uri` of this source, when the
        caller has it already (it resolves the path on the file system)."""
        m = raw.message_index
        frame_id = int(self._export["frame_ids"][m]) if self._export is not None else m
        pose, T_base_sensor = self._pose(m, raw.stamp_ns, raw.sensor_frame)
        if uri is None:
            uri = provenance_uri(self.path, self.topic, self.stamp)
        provenance = Provenance(uri, m)
        sensor_name = (self._export or {}).get("sensor_name") or self.topic.strip("/")
        if raw.depth is not None:
            assert raw.intrinsics is not None
            frame = depth_frame(
                raw.depth,
                raw.intrinsics,
                frame_id=frame_id,
                stamp_ns=raw.stamp_ns,
                pose=pose,
                sensor_name=sensor_name,
                sensor_frame=raw.sensor_frame,
                T_base_sensor=T_base_sensor,
                depth_scale=raw.depth_scale or 1000.0,
                min_depth_m=self.min_depth_m,
                max_depth_m=self.max_depth_m,
                provenance=provenance,
                monitor=self._monitor,
                pixel_stride=self.pixel_stride,
                base_frame=self.base_frame,
                flags=tuple(raw.flags),
            )
            return frame
        what = f"{self.path}: {self.topic} message {m}"
        with message_fields(what):
            cloud = pointcloud2_points(raw.cloud_msg, raw.stamp_ns, what=what, point_time=self.point_time,
                                       warned=self._warned)
        flags = list(raw.flags)
        if cloud.invalid_counts and getattr(raw.cloud_msg, "is_dense", False):
            flags.append(f"is_dense_but_nonfinite: {sum(cloud.invalid_counts.values())} points with NaN/inf")
        kind = SensorKind.DEPTH_CAMERA if raw.intrinsics is not None else SensorKind.LIDAR
        export = self._export or {}
        if export.get("sensor_kind"):
            kind = SensorKind(export["sensor_kind"])
        return Frame(
            frame_id=frame_id,
            stamp_ns=raw.stamp_ns,
            sensor_name=sensor_name,
            sensor_kind=kind,
            points_sensor=cloud.points,
            pose=pose,
            T_base_sensor=T_base_sensor,
            attributes=cloud.attributes,
            intrinsics=raw.intrinsics,
            depth_scale=export.get("depth_scale"),
            quality=FrameQuality(cloud.n_measurements, len(cloud.points), cloud.invalid_counts, tuple(flags)),
            provenance=provenance,
            sensor_frame=raw.sensor_frame,
            base_frame=self.base_frame,
        )

    # ---- FrameSource
    def _load(self, index: int) -> Frame:
        m = self._message_index(index)
        raw = self._backend.fetch(self.topic, m, self.log_times())
        return self._to_frame(self._measure(raw, m, None))

    def _selected_messages(self) -> list[int]:
        return [self._message_index(i) for i in self._indices()]

    def _iterate(self, build: bool) -> Iterator[Any]:
        wanted = self._selected_messages()
        if not wanted:
            return
        start_ns, k = None, 0
        if wanted[0] > 0:
            times = self.log_times()
            start_ns = int(times[wanted[0]])
            k = int(np.searchsorted(times, start_ns, side="left"))
        topics = [self.topic] + ([self.camera_info_topic] if self.camera_info_topic else [])
        pos = 0
        uri = provenance_uri(self.path, self.topic, self.stamp) if build else None
        info_raw: _Raw | None = None
        info_cache: tuple[_Raw, tuple[str, PinholeIntrinsics, tuple[str, ...]]] | None = None
        previous: tuple[int, int] | None = None  # (message index, stamp) of the last frame given out
        k -= 1
        for raw in self._backend.stream(topics, start_ns):
            if raw.topic != self.topic:
                info_raw = raw
                continue
            k += 1
            if k < wanted[pos]:
                continue
            try:
                info = None
                if info_raw is not None:
                    if info_cache is None or info_cache[0] is not info_raw:
                        decoded = self._caminfo_from_msg(
                            self._backend.decode(info_raw), f"{self.path}: {self.camera_info_topic}"
                        )
                        info_cache = (info_raw, decoded)
                    info = info_cache[1]
                measurement = self._measure(raw, k, info)
                if previous is not None and measurement.stamp_ns <= previous[1]:
                    kind = "duplicate" if measurement.stamp_ns == previous[1] else "non-monotonic"
                    raise SourceError(
                        f"{self.path}: topic {self.topic}: {kind} {self.stamp.value} stamps: message {k} has "
                        f"{measurement.stamp_ns} ns, message {previous[0]} before it has {previous[1]} ns"
                    )
                item = self._to_frame(measurement, uri) if build else measurement
            except (SourceError, DepthError, GeometryError) as exc:
                if not self.lenient or isinstance(exc, DepthScaleError):  # a wrong scale is wrong for every frame
                    raise
                logger.warning("%s: skipping message %d of %s: %s", self.path, k, self.topic, exc)
                self.skipped.append((k, str(exc)))
            else:
                previous = (k, measurement.stamp_ns)
                yield item
            pos += 1
            if pos == len(wanted):
                return

    def __iter__(self) -> Iterator[Frame]:
        """Frames in log order; stamps must increase strictly (else :class:`SourceError` naming both message
        indices, or the later frame is skipped in lenient mode)."""
        return self._iterate(build=True)

    def iter_raw(self) -> Iterator[RawMeasurement]:
        """Decode only: the selected messages as numpy arrays with their stamps and intrinsics, without
        back-projection, point filtering or pose lookups (the same checks on stamps as :meth:`__iter__`)."""
        return self._iterate(build=False)

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        out.update(
            format=self.format_name,
            topic=self.topic,
            msgtype=self.msgtype,
            stamp=self.stamp.value,
            camera_info_topic=self.camera_info_topic,
            base_frame=self.base_frame,
            sensor_frame=self.first_sensor_frame,
            pose_from_tf=list(self.pose_from_tf) if self.pose_from_tf else None,
            pose_from_odometry=self.pose_from_odometry,
            damage=getattr(self._backend, "damage", None),
        )
        return out

    def ground_truth(self):  # type: ignore[override]
        """Ground truth written by :func:`~driftmap.sources.mcap_export.export_mcap` (``PoseStamped`` on the
        sensor's ground-truth topic), else ``None``."""
        from driftmap.trajectory import Trajectory

        topic = (self._export or {}).get("ground_truth_topic")
        if not topic or topic not in self._topics:
            return None
        series = load_pose_topic(self._backend, topic, stamp=StampSource.HEADER)
        ids = self._export.get("ground_truth_frame_ids") if self._export else None
        frame_ids = np.asarray(ids, dtype=np.int64) if ids is not None and len(ids) == len(series) else None
        return Trajectory(np.array(series.stamps_ns), np.array(series.T_parent_child), frame_ids)

    def close(self) -> None:
        self._backend.close()

    def __enter__(self) -> RosLogSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _opener(format_name: str) -> Any:
    """An opener for :func:`register_source`; unknown options raise :class:`SourceError` listing the accepted."""
    params = inspect.signature(RosLogSource.__init__).parameters
    accepted = sorted(n for n, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY and n != "format")

    def open_log(path: Path, **options: Any) -> RosLogSource:
        unknown = sorted(set(options) - set(accepted))
        if unknown:
            raise SourceError(
                f"{path}: unknown option(s) {', '.join(unknown)} for format {format_name!r}; "
                f"accepted: {', '.join(accepted)}"
            )
        return RosLogSource(path, format=format_name, **options)

    open_log.__doc__ = RosLogSource.__doc__
    # the wrapper's signature is ``**options``: declare what it takes, so that what reads an opener's options
    # (sources.base.accepted_options: build / convert checking --topic, --pose-from-tf, ... and depth.* against
    # the format) sees them. Options that apply to depth-image topics only are left out: the format alone cannot
    # tell whether a log's topic is one (build would pass its automatic pixel_stride to PointCloud2 topics, which
    # refuse it); the API takes them.
    open_log.accepted_options = frozenset(accepted) - DEPTH_IMAGE_ONLY_OPTIONS  # type: ignore[attr-defined]
    return open_log


#: :class:`RosLogSource` options that apply to depth-image topics only (not declared as the format's options)
DEPTH_IMAGE_ONLY_OPTIONS = frozenset({"pixel_stride", "min_depth_m", "max_depth_m"})


def _parse_origin(record: dict[str, str]) -> dict[str, Any] | None:
    try:
        origin = json.loads(record.get("origin", "null"))
    except json.JSONDecodeError:
        return None
    ok = isinstance(origin, dict) and isinstance(origin.get("format"), str) and isinstance(origin.get("path"), str)
    if ok and not isinstance(origin.get("options", {}), dict):
        ok = False
    return origin if ok else None


def read_export_origin(path: str | Path) -> dict[str, Any] | None:
    """:meth:`RosLogSource.export_origin` of an MCAP file without opening it as a source: only its metadata
    records are read (milliseconds, whatever the length of the log). ``None`` when it names no origin or cannot
    be read."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as fh:
            for record in make_reader(fh).iter_metadata():
                if record.name == EXPORT_METADATA_NAME:
                    return _parse_origin(dict(record.metadata))
    except Exception as exc:
        logger.debug("%s: no export origin (%s)", path, exc)
    return None


register_source(
    FORMAT_MCAP,
    _detect_mcap,
    _opener(FORMAT_MCAP),
    "MCAP with ROS 2 messages (PointCloud2 or depth Image + CameraInfo, TF, Odometry)",
    origin_of=read_export_origin,
)
register_source(FORMAT_ROSBAG1, _detect_rosbag1, _opener(FORMAT_ROSBAG1), "ROS 1 .bag (via rosbags)")
register_source(
    FORMAT_ROSBAG2, _detect_rosbag2, _opener(FORMAT_ROSBAG2), "rosbag2 folder, sqlite3 or mcap storage (via rosbags)"
)

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
