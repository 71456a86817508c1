"""Reading one chunk of a segment: its header (sizes, CRC, compression) and its records (channels, and the frame,
revision and event messages), every length checked against the bytes present before it is used. What a scan of
the whole segment does with the result is :mod:`driftmap.store.segment_scan`."""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.opcode import Opcode

from driftmap.errors import GeometryError, StoreError
from driftmap.store.frame_codec import INT64_MAX, check_frame_info, is_int
from driftmap.store.revision import Revision
from driftmap.store.segment_format import (
    EVENT_DATA_LOST,
    MAX_UNCOMPRESSED_CHUNK,
    TOPIC_FRAMES,
    TOPIC_REVISIONS,
    TOPIC_SEGMENT,
)


@dataclass(frozen=True, slots=True)
class StoredFrameRef:
    """Where one frame lives: its metadata and the location of its point payload."""

    info: dict[str, Any]
    segment: Path
    payload_offset: int
    """File offset of the payload in an uncompressed segment, or -1 when the payload was copied."""
    payload_copy: bytes | None = None

    @property
    def frame_id(self) -> int:
        return int(self.info["frame_id"])

    @property
    def n_points(self) -> int:
        return int(self.info["points"]["n_points"])

    @property
    def point_stride(self) -> int:
        return int(self.info["points"]["point_stride"])


@dataclass(slots=True)
class ChunkContent:
    """What one intact chunk holds."""

    frames: list[StoredFrameRef] = field(default_factory=list)
    revisions: list[dict[str, Any]] = field(default_factory=list)
    data_lost: list[dict[str, Any]] = field(default_factory=list)
    store_uuid: str | None = None
    """from its ``segment_start`` event (None: it holds none)"""
    channels: dict[int, str] = field(default_factory=dict)
    """the channels it registers: id -> topic"""
    messages: dict[int, list[tuple[int, int]]] = field(default_factory=dict)
    """channel id -> [(log time, offset in the chunk's records)] of its messages (what its message index must say)"""


def scan_chunk(buf: memoryview, body: int, end: int, path: Path, channels: dict[int, str],
               verify: bool) -> ChunkContent | str:
    """Read the chunk whose body is ``buf[body:end]`` (``channels``: those registered by the chunks before it);
    returns what it holds, or why it is damaged."""
    try:
        found = _chunk_records(buf, body, end, verify)
        if isinstance(found, str):
            return found
        records, base, start_time, end_time = found
        content = _read_records(records, base, path, channels)
        if isinstance(content, str):
            return content
        times = [t for listed in content.messages.values() for t, _ in listed]
        if not times:
            return "chunk without messages"
        if (min(times), max(times)) != (start_time, end_time):
            return "chunk start / end times disagree with its messages"
    except (struct.error, ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError, RecursionError,
            ArithmeticError, MemoryError) as exc:
        return f"unreadable chunk content ({type(exc).__name__}: {exc})"
    return content


def _read_string(buf: memoryview, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    if pos + 4 + n > len(buf):
        raise ValueError(f"string of {n} bytes overruns its record")
    return bytes(buf[pos + 4 : pos + 4 + n]).decode(), pos + 4 + n


def _chunk_records(buf: memoryview, body: int, end: int, verify: bool) -> tuple[memoryview, int, int, int] | str:
    """The chunk's records (decompressed if need be), the file offset they start at (-1: decompressed, payloads are
    not addressable in the file) and the chunk's start and end times; or why the chunk is damaged."""
    if end - body < 8 * 3 + 4 + 4 + 8:
        return "chunk shorter than its header"
    start_time, end_time, uncompressed_size, crc = struct.unpack_from("<QQQI", buf, body)
    compression, pos = _read_string(buf, body + 28)
    if pos + 8 > end:
        return "chunk header overruns the chunk"
    (records_len,) = struct.unpack_from("<Q", buf, pos)
    rec_start = pos + 8
    if rec_start + records_len != end:
        return "chunk length fields disagree"
    if compression:
        if compression not in ("zstd", "lz4"):
            return f"unsupported chunk compression {compression!r}"
        if uncompressed_size > MAX_UNCOMPRESSED_CHUNK:
            return f"chunk claims {uncompressed_size} uncompressed bytes"
        import lz4.frame  # only for segments written by something else: the store writes uncompressed chunks
        import zstandard

        raw = bytes(buf[rec_start:end])
        try:
            if compression == "zstd":
                data = zstandard.ZstdDecompressor().decompress(raw, max_output_size=uncompressed_size)
            else:
                data = lz4.frame.LZ4FrameDecompressor().decompress(raw, max_length=uncompressed_size)
        except (zstandard.ZstdError, RuntimeError) as exc:
            return f"undecodable {compression} chunk ({exc})"
        if len(data) != uncompressed_size:
            return "chunk decompresses to another size than it claims"
        records = memoryview(data)
        base = -1  # payloads are not addressable in the file
    else:
        if uncompressed_size != records_len:
            return "chunk size fields disagree"
        records = buf[rec_start:end]
        base = rec_start
    if verify and crc != 0 and zlib.crc32(records) != crc:
        return "chunk CRC mismatch (damaged data)"
    return records, base, start_time, end_time


def _read_records(records: memoryview, base: int, path: Path, channels: dict[int, str]) -> ChunkContent | str:
    """Every record of a chunk: channels and messages (schemas are skipped); or why the chunk is damaged."""
    content = ChunkContent()
    pending: dict[str, Any] | None = None  # a frame's metadata, waiting for its points
    pos = 0
    n = len(records)
    while pos < n:
        if pos + 9 > n:
            return "record header overruns its chunk"
        opcode = records[pos]
        (length,) = struct.unpack_from("<Q", records, pos + 1)
        body_pos = pos + 9
        if body_pos + length > n:
            return "record overruns its chunk"
        if opcode == Opcode.CHANNEL:
            (channel_id, _schema_id) = struct.unpack_from("<HH", records, body_pos)
            topic, _ = _read_string(records[: body_pos + length], body_pos + 4)
            content.channels[channel_id] = topic
        elif opcode == Opcode.MESSAGE:
            if length < 22:
                return "message record shorter than its header"
            channel_id, _sequence, log_time = struct.unpack_from("<HIQ", records, body_pos)
            content.messages.setdefault(channel_id, []).append((log_time, pos))
            topic = content.channels.get(channel_id, channels.get(channel_id))
            pending = _read_message(content, topic, records, body_pos + 22, body_pos + length, base, path, pending)
            if isinstance(pending, str):
                return pending
        elif opcode != Opcode.SCHEMA:
            return f"unexpected record opcode 0x{opcode:02x} in a chunk"
        pos = body_pos + length
    if pending is not None:
        return f"frame {pending['frame_id']}: metadata without points"
    return content


def _read_message(content: ChunkContent, topic: str | None, records: memoryview, data_start: int, data_end: int,
                  base: int, path: Path, pending: dict[str, Any] | None) -> dict[str, Any] | str | None:
    """Add one message to ``content``. ``pending``: the frame metadata read before it, waiting for its points.
    Returns the frame metadata now pending (None: none), or why the chunk is damaged."""
    if topic == TOPIC_FRAMES:
        if pending is not None:
            return f"frame {pending['frame_id']}: metadata without points"
        info = json.loads(bytes(records[data_start:data_end]))
        problem = check_frame_info(info)
        return info if problem is None else problem
    if topic is not None and topic.endswith("/points"):
        if pending is None:
            return "points without frame metadata"
        nbytes = int(pending["points"]["n_points"]) * int(pending["points"]["point_stride"])
        payload_start = data_end - nbytes
        if payload_start < data_start:
            return f"frame {pending['frame_id']}: point message shorter than its declared payload"
        if base >= 0:
            content.frames.append(StoredFrameRef(pending, path, base + payload_start))
        else:
            content.frames.append(StoredFrameRef(pending, path, -1, bytes(records[payload_start:data_end])))
        return None
    if topic == TOPIC_REVISIONS:
        revision = json.loads(bytes(records[data_start:data_end]))
        problem = _check_revision(revision)
        if problem is not None:
            return problem
        content.revisions.append(revision)
    elif topic == TOPIC_SEGMENT:
        event = json.loads(bytes(records[data_start:data_end]))
        problem = _check_event(event)
        if problem is not None:
            return problem
        if event.get("event") == "segment_start":
            content.store_uuid = str(event["store_uuid"])
        elif event.get("event") == EVENT_DATA_LOST:
            content.data_lost.append(event)
    return pending


def _check_event(event: object) -> str | None:
    if not isinstance(event, dict):
        return "segment event is not a JSON object"
    kind = event.get("event")
    if kind == "segment_start" and not isinstance(event.get("store_uuid"), str):
        return "segment_start event without a store_uuid string"
    if kind == EVENT_DATA_LOST:
        for key in ("frame_ids", "revision_ids"):
            value = event.get(key)
            if not isinstance(value, list) or not all(is_int(i) for i in value):
                return f"{EVENT_DATA_LOST} event: {key} is not a list of integers"
        recovered = event.get("recovered_ns", 0)
        if not is_int(recovered) or not 0 <= recovered <= INT64_MAX:
            return f"{EVENT_DATA_LOST} event: recovered_ns {recovered!r} is not a non-negative 64-bit integer"
    return None


def _check_revision(data: object) -> str | None:
    try:
        rev = Revision.from_json(data)  # type: ignore[arg-type]
    except (StoreError, GeometryError) as exc:
        return f"revision record: {exc}"
    if not 0 <= rev.created_ns <= INT64_MAX:
        return f"revision {rev.revision_id}: created_ns {rev.created_ns} is not a non-negative 64-bit integer"
    return None
