"""One MCAP segment of a frame store: how frames and pose revisions are written, and how they are found
again without reading the point payloads.

Every frame is one uncompressed MCAP chunk holding three messages, in this order:

1. ``/driftmap/frames`` -- ``driftmap.FrameInfo`` (JSON): every piece of metadata (stamp, sensor,
   intrinsics, extrinsics, quality, provenance, the revision-0 pose) and the point layout. Trailing
   whitespace pads it so that the point payload of message 2 starts on a 16-byte boundary in the file.
2. ``/driftmap/<sensor>/points`` -- ``foxglove.PointCloud`` (protobuf): sensor-frame points, ``x y z``
   float32 first, then optional attributes, interleaved with ``point_stride``. ``data`` is the last
   protobuf field, so the payload is the last ``n_points * point_stride`` bytes of the message.
3. ``/tf`` -- ``foxglove.FrameTransform`` (protobuf): the revision-0 pose ``world -> <sensor>@<frame_id>``,
   so Foxglove places every cloud where the estimate that produced it put it.

A pose revision is one chunk with one ``/driftmap/revisions`` message (``driftmap.PoseRevision``, JSON).
Segment events (``/driftmap/segment``, ``driftmap.SegmentEvent``, JSON) are chunks of their own too:
``segment_start`` (the store the segment belongs to), ``sensor`` (a new points channel) and ``data_lost``
(written by recovery: the frames and revisions a damaged or missing segment took with it, see
``driftmap.store.frame_store``).

The writer flushes after every frame and revision: a chunk on disk is a committed frame; a writer killed
mid-append leaves at most one incomplete chunk at the end of the file.

Chunks are uncompressed so that the point payloads can be memory-mapped straight from the file: a map
reads sensor points without copying them into the process.
"""

from __future__ import annotations

import json
import logging
import mmap
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from mcap.opcode import Opcode
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap import __version__
from driftmap.errors import StoreError
from driftmap.frame import (
    Frame,
    FrameQuality,
    PinholeIntrinsics,
    PointAttributes,
    PoseEstimate,
    PoseSource,
    Provenance,
    SensorKind,
    TrackingHealth,
)

logger = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
PAYLOAD_ALIGNMENT = 16
TOPIC_SEGMENT = "/driftmap/segment"
TOPIC_FRAMES = "/driftmap/frames"
TOPIC_REVISIONS = "/driftmap/revisions"
TOPIC_TF = "/tf"
WORLD_FRAME = "world"
EVENT_DATA_LOST = "data_lost"
_CHUNK_HEADER_BYTES = 1 + 8 + 8 + 8 + 8 + 4 + 4 + 8  # opcode, length, start, end, size, crc, "" compression, records length
_MESSAGE_HEADER_BYTES = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel, sequence, log_time, publish_time

_NUMERIC = PackedElementField.NumericType
#: point attribute -> (component field names, numeric type, numpy dtype of one component)
_ATTRIBUTE_FIELDS: dict[str, tuple[tuple[str, ...], int, Any]] = {
    "intensity": (("intensity",), _NUMERIC.FLOAT32, np.float32),
    "color_rgb": (("red", "green", "blue", "alpha"), _NUMERIC.UINT8, np.uint8),
    "normal_sensor": (("normal_x", "normal_y", "normal_z"), _NUMERIC.FLOAT32, np.float32),
    "time_offset_ns": (("time_offset_ns",), _NUMERIC.FLOAT64, np.float64),
}
_NUMERIC_DTYPE = {_NUMERIC.FLOAT32: np.float32, _NUMERIC.FLOAT64: np.float64, _NUMERIC.UINT8: np.uint8}

_JSON_SCHEMA_FRAME_INFO = {
    "title": "driftmap.FrameInfo",
    "description": "Metadata of one stored frame; its points are the next message in the same chunk.",
    "type": "object",
}
_JSON_SCHEMA_REVISION = {"title": "driftmap.PoseRevision", "description": "A pose revision of the ledger.", "type": "object"}
_JSON_SCHEMA_SEGMENT = {"title": "driftmap.SegmentEvent", "description": "Segment start and sensor registration.", "type": "object"}


def point_layout(attributes: PointAttributes) -> tuple[int, list[dict[str, Any]]]:
    """Interleaved layout: ``x y z`` float32, then each present attribute; returns (stride, fields)."""
    fields = [{"name": n, "offset": 4 * i, "type": int(_NUMERIC.FLOAT32)} for i, n in enumerate("xyz")]
    offset = 12
    for attr in attributes.names():
        names, numeric, dtype = _ATTRIBUTE_FIELDS[attr]
        size = np.dtype(dtype).itemsize
        for name in names:
            fields.append({"name": name, "offset": offset, "type": int(numeric)})
            offset += size
    return offset, fields


def pack_points(points: NDArray[np.float32], attributes: PointAttributes) -> tuple[bytes, int, list[dict[str, Any]]]:
    """Interleave points and attributes into one little-endian payload."""
    stride, fields = point_layout(attributes)
    n = len(points)
    if stride == 12:
        return np.ascontiguousarray(points, dtype="<f4").tobytes(), stride, fields
    buf = np.zeros((n, stride), dtype=np.uint8)
    buf[:, :12] = np.ascontiguousarray(points, dtype="<f4").view(np.uint8).reshape(n, 12)
    offset = 12
    for attr in attributes.names():
        names, _, dtype = _ATTRIBUTE_FIELDS[attr]
        value = getattr(attributes, attr)
        if attr == "color_rgb":
            value = np.concatenate([value, np.full((n, 1), 255, np.uint8)], axis=1)
        comp = np.ascontiguousarray(value, dtype=np.dtype(dtype).newbyteorder("<")).reshape(n, len(names))
        width = comp.itemsize * len(names)
        buf[:, offset : offset + width] = comp.view(np.uint8).reshape(n, width)
        offset += width
    return buf.tobytes(), stride, fields


def unpack_attributes(payload: NDArray[np.uint8], n: int, stride: int, fields: list[dict[str, Any]]) -> PointAttributes:
    """Copy the attribute columns out of an interleaved payload (``payload`` is ``n * stride`` bytes)."""
    rows = payload.reshape(n, stride) if n else payload.reshape(0, stride)
    by_name = {f["name"]: f for f in fields}
    values: dict[str, NDArray] = {}
    for attr, (names, numeric, dtype) in _ATTRIBUTE_FIELDS.items():
        if names[0] not in by_name:
            continue
        start = by_name[names[0]]["offset"]
        width = np.dtype(dtype).itemsize * len(names)
        comp = np.ascontiguousarray(rows[:, start : start + width]).view(np.dtype(dtype).newbyteorder("<"))
        comp = comp.reshape(n, len(names)).astype(dtype)
        if attr == "color_rgb":
            values[attr] = comp[:, :3]
        elif attr == "time_offset_ns":
            values[attr] = comp[:, 0].astype(np.int64)
        elif len(names) == 1:
            values[attr] = comp[:, 0]
        else:
            values[attr] = comp
    return PointAttributes(**values)


def _matrix(T: NDArray[np.float64] | None) -> list[float] | None:
    return None if T is None else [float(v) for v in np.asarray(T, dtype=np.float64).ravel()]


def frame_info(frame: Frame, stride: int, fields: list[dict[str, Any]], payload_crc32: int) -> dict[str, Any]:
    """JSON-ready metadata of a frame (everything except the point payload)."""
    q = frame.quality
    return {
        "frame_id": frame.frame_id,
        "stamp_ns": frame.stamp_ns,
        "sensor_name": frame.sensor_name,
        "sensor_kind": frame.sensor_kind.value,
        "sensor_frame": frame.sensor_frame,
        "base_frame": frame.base_frame,
        "T_base_sensor": _matrix(frame.T_base_sensor),
        "pose": {
            "T_world_sensor": _matrix(frame.pose.T_world_sensor),
            "revision": frame.pose.revision,
            "source": frame.pose.source.value,
            "covariance_6x6": _matrix(frame.pose.covariance_6x6),
            "world_frame": frame.pose.world_frame,
        },
        "intrinsics": None if frame.intrinsics is None else frame.intrinsics.to_dict(),
        "depth_scale": frame.depth_scale,
        "quality": None
        if q is None
        else {"n_measurements": q.n_measurements, "n_valid": q.n_valid, "invalid_counts": dict(q.invalid_counts), "flags": list(q.flags)},
        "provenance": None if frame.provenance is None else {"source_uri": frame.provenance.source_uri, "index": frame.provenance.index},
        "points": {"n_points": frame.n_points, "point_stride": stride, "fields": fields, "crc32": payload_crc32},
        "tracking": None if frame.tracking is None else frame.tracking.to_dict(),
    }


def frame_from_info(info: dict[str, Any], points: NDArray[np.float32], attributes: PointAttributes) -> Frame:
    """Rebuild a :class:`Frame` from its stored metadata and points."""
    pose = info["pose"]
    cov = pose.get("covariance_6x6")
    q = info.get("quality")
    prov = info.get("provenance")
    intr = info.get("intrinsics")
    return Frame(
        frame_id=info["frame_id"],
        stamp_ns=info["stamp_ns"],
        sensor_name=info["sensor_name"],
        sensor_kind=SensorKind(info["sensor_kind"]),
        points_sensor=points,
        pose=PoseEstimate(
            np.asarray(pose["T_world_sensor"]).reshape(4, 4),
            revision=pose["revision"],
            source=PoseSource(pose["source"]),
            covariance_6x6=None if cov is None else np.asarray(cov).reshape(6, 6),
            world_frame=pose.get("world_frame", WORLD_FRAME),
        ),
        T_base_sensor=np.asarray(info["T_base_sensor"]).reshape(4, 4),
        attributes=attributes,
        intrinsics=None if intr is None else PinholeIntrinsics(**intr),
        depth_scale=info.get("depth_scale"),
        quality=None if q is None else FrameQuality(q["n_measurements"], q["n_valid"], q["invalid_counts"], tuple(q["flags"])),
        provenance=None if prov is None else Provenance(prov["source_uri"], prov["index"]),
        sensor_frame=info["sensor_frame"],
        base_frame=info["base_frame"],
        tracking=None if info.get("tracking") is None else TrackingHealth.from_dict(info["tracking"]),
    )


def cloud_frame_name(sensor_frame: str, frame_id: int) -> str:
    """The coordinate-frame name a stored frame's cloud uses in Foxglove: one per frame."""
    return f"{sensor_frame}@{frame_id:06d}"


def _json_bytes(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


@dataclass
class SegmentWriter:
    """Appends frames and revisions to one new MCAP segment; every append is flushed as its own chunk."""

    path: Path
    segment_index: int
    store_uuid: str
    fsync: bool = False
    _fh: IO[bytes] = field(init=False, repr=False)
    _writer: Writer = field(init=False, repr=False)
    _channels: dict[str, int] = field(init=False, default_factory=dict, repr=False)
    _schemas: dict[str, int] = field(init=False, default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.path.exists():
            raise StoreError(f"{self.path}: segment already exists")
        self._fh = open(self.path, "xb")
        self._writer = Writer(self._fh, chunk_size=1 << 62, compression=CompressionType.NONE, use_chunking=True)
        self._writer.start(profile="", library=f"driftmap {__version__}")
        json_schemas = {
            "driftmap.SegmentEvent": _JSON_SCHEMA_SEGMENT,
            "driftmap.FrameInfo": _JSON_SCHEMA_FRAME_INFO,
            "driftmap.PoseRevision": _JSON_SCHEMA_REVISION,
        }
        for name, schema in json_schemas.items():
            self._schemas[name] = self._writer.register_schema(name, "jsonschema", json.dumps(schema).encode())
        for cls in (PointCloud, FrameTransform):
            fds = build_file_descriptor_set(cls).SerializeToString()
            self._schemas[cls.DESCRIPTOR.full_name] = self._writer.register_schema(cls.DESCRIPTOR.full_name, "protobuf", fds)
        self._channel(TOPIC_SEGMENT, "json", "driftmap.SegmentEvent")
        self._channel(TOPIC_FRAMES, "json", "driftmap.FrameInfo")
        self._channel(TOPIC_REVISIONS, "json", "driftmap.PoseRevision")
        self._channel(TOPIC_TF, "protobuf", "foxglove.FrameTransform")
        self._event({"event": "segment_start", "segment_index": self.segment_index, "store_uuid": self.store_uuid,
                     "driftmap_version": __version__}, 0)

    def _channel(self, topic: str, encoding: str, schema: str) -> int:
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(topic, encoding, self._schemas[schema])
        return self._channels[topic]

    def _event(self, payload: dict[str, Any], log_time_ns: int) -> None:
        self._writer.add_message(self._channels[TOPIC_SEGMENT], log_time_ns, _json_bytes(payload), log_time_ns)
        self._commit()

    def append_event(self, payload: dict[str, Any], log_time_ns: int) -> None:
        """Write one segment event (``payload["event"]`` names its kind) as a chunk of its own."""
        self._event(payload, log_time_ns)

    def _commit(self) -> None:
        self._writer.flush()  # finishes the chunk and flushes Python's buffer: the chunk is in the kernel
        if self.fsync:
            os.fsync(self._fh.fileno())

    def points_topic(self, sensor_name: str) -> str:
        return f"/driftmap/{sensor_name}/points"

    def append_frame(self, frame: Frame) -> tuple[int, dict[str, Any]]:
        """Write one frame as one chunk; returns the file offset of its point payload and its metadata."""
        topic = self.points_topic(frame.sensor_name)
        if topic not in self._channels:
            # a new sensor: register its channel in a chunk of its own, so frame chunks have a fixed layout
            self._channel(topic, "protobuf", "foxglove.PointCloud")
            self._event({"event": "sensor", "sensor_name": frame.sensor_name, "sensor_kind": frame.sensor_kind.value,
                         "topic": topic}, frame.stamp_ns)
        payload, stride, fields = pack_points(frame.points_sensor, frame.attributes)
        crc = zlib.crc32(payload)
        cloud_name = cloud_frame_name(frame.sensor_frame, frame.frame_id)
        cloud = PointCloud(frame_id=cloud_name, point_stride=stride, data=payload)
        cloud.timestamp.FromNanoseconds(frame.stamp_ns)
        cloud.pose.orientation.w = 1.0
        for f in fields:
            cloud.fields.add(name=f["name"], offset=f["offset"], type=f["type"])
        cloud_bytes = cloud.SerializeToString()
        prefix = len(cloud_bytes) - len(payload)
        if cloud_bytes[prefix:] != payload:  # data must be the last field of the serialised message
            raise StoreError("foxglove.PointCloud serialisation does not end with the point payload")
        info_dict = frame_info(frame, stride, fields, crc)
        info = _json_bytes(info_dict)
        chunk_start = self._fh.tell()
        payload_offset = chunk_start + _CHUNK_HEADER_BYTES + 2 * _MESSAGE_HEADER_BYTES + len(info) + prefix
        info += b" " * (-payload_offset % PAYLOAD_ALIGNMENT)
        payload_offset = chunk_start + _CHUNK_HEADER_BYTES + 2 * _MESSAGE_HEADER_BYTES + len(info) + prefix
        tf = FrameTransform(parent_frame_id=frame.pose.world_frame, child_frame_id=cloud_name)
        tf.timestamp.FromNanoseconds(frame.stamp_ns)
        T = frame.pose.T_world_sensor
        tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in T[:3, 3])
        qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = float(qx), float(qy), float(qz), float(qw)
        t = frame.stamp_ns
        self._writer.add_message(self._channels[TOPIC_FRAMES], t, info, t)
        self._writer.add_message(self._channels[topic], t, cloud_bytes, t)
        self._writer.add_message(self._channels[TOPIC_TF], t, tf.SerializeToString(), t)
        self._commit()
        return payload_offset, info_dict

    def append_revision(self, revision_json: dict[str, Any], log_time_ns: int) -> None:
        self._writer.add_message(self._channels[TOPIC_REVISIONS], log_time_ns, _json_bytes(revision_json), log_time_ns)
        self._commit()

    def close(self) -> int:
        """Write the summary and footer; returns the final size in bytes."""
        self._writer.finish()
        self._fh.flush()
        os.fsync(self._fh.fileno())
        size = self._fh.tell()
        self._fh.close()
        return size

    def abandon(self) -> None:
        """Close the file without a summary (used when the store is being torn down after an error)."""
        try:
            self._fh.close()
        except OSError:  # pragma: no cover
            pass


# ----------------------------------------------------------------------------------------------- reading


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


@dataclass
class SegmentScan:
    """What a scan of one segment found."""

    path: Path
    size: int
    frames: list[StoredFrameRef] = field(default_factory=list)
    revisions: list[dict[str, Any]] = field(default_factory=list)
    complete: bool = False
    """True when the data section ended with DataEnd (the segment was closed by its writer)."""
    valid_bytes: int = 0
    """End offset of the last complete record: everything after it is an unfinished or damaged tail."""
    problem: str | None = None
    problem_offset: int | None = None
    damaged_chunks: list[tuple[int, str]] = field(default_factory=list)
    """(offset, reason) of damaged chunks skipped with ``stop_on_error=False``."""
    damaged_bytes: int = 0
    """Bytes of the damaged chunks skipped with ``stop_on_error=False``."""
    store_uuid: str | None = None
    """The store this segment belongs to, from its ``segment_start`` event (None: that chunk was not read)."""
    data_lost: list[dict[str, Any]] = field(default_factory=list)
    """The ``data_lost`` events recovery wrote into this segment (frames and revisions the store lost)."""


def _read_string(buf: memoryview, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    return bytes(buf[pos + 4 : pos + 4 + n]).decode(), pos + 4 + n


def scan_segment(path: Path, *, verify: bool = True, stop_on_error: bool = True) -> SegmentScan:
    """Walk a segment's records without decoding point payloads.

    Complete chunks yield frames (metadata + payload offset) and revisions. A truncated tail stops the
    scan and is reported (``problem``, ``problem_offset``); with ``verify`` every chunk's CRC is checked,
    and a mismatch is reported the same way. With ``stop_on_error=False`` a chunk whose framing is intact
    but whose content is damaged is skipped and the scan goes on (used by recovery).
    """
    size = path.stat().st_size
    scan = SegmentScan(path, size)
    if size < len(MCAP_MAGIC):
        scan.problem, scan.problem_offset = "file shorter than the MCAP magic", 0
        return scan
    with open(path, "rb") as fh:
        mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    try:
        buf = memoryview(mm)
        try:
            if bytes(buf[:8]) != MCAP_MAGIC:
                scan.problem, scan.problem_offset = "not an MCAP file (bad magic)", 0
                return scan
            channels: dict[int, str] = {}
            pos = 8
            scan.valid_bytes = pos
            while pos < size:
                if pos + 9 > size:
                    scan.problem, scan.problem_offset = "truncated record header", pos
                    break
                opcode = buf[pos]
                (length,) = struct.unpack_from("<Q", buf, pos + 1)
                body = pos + 9
                end = body + length
                if end > size:
                    scan.problem, scan.problem_offset = f"truncated record (opcode 0x{opcode:02x}, {length} bytes)", pos
                    break
                if opcode == Opcode.DATA_END:
                    scan.complete = True
                    scan.valid_bytes = end
                    break
                if opcode == Opcode.CHUNK:
                    err = _scan_chunk(buf, body, end, path, channels, scan, verify)
                    if err is not None:
                        if stop_on_error:
                            scan.problem, scan.problem_offset = err, pos
                            break
                        logger.warning("%s: skipping damaged chunk at offset %d: %s", path, pos, err)
                        scan.damaged_chunks.append((pos, err))
                        scan.damaged_bytes += end - pos
                elif opcode not in (Opcode.HEADER, Opcode.MESSAGE_INDEX, Opcode.METADATA, Opcode.ATTACHMENT):
                    if opcode == 0 or opcode > 0x0F:
                        scan.problem, scan.problem_offset = f"unknown record opcode 0x{opcode:02x}", pos
                        break
                pos = end
                scan.valid_bytes = pos
        finally:
            buf.release()
    finally:
        mm.close()
    return scan


def _scan_chunk(buf: memoryview, body: int, end: int, path: Path, channels: dict[int, str], scan: SegmentScan,
                verify: bool) -> str | None:
    """Read one chunk's inner records; returns an error string if the chunk is damaged."""
    try:
        _start, _end, uncompressed_size, crc = struct.unpack_from("<QQQI", buf, body)
        compression, pos = _read_string(buf, body + 28)
        (records_len,) = struct.unpack_from("<Q", buf, pos)
        rec_start = pos + 8
        if rec_start + records_len != end:
            return "chunk length fields disagree"
        if compression:
            import lz4.frame
            import zstandard

            raw = bytes(buf[rec_start:end])
            data = zstandard.ZstdDecompressor().decompress(raw, max_output_size=uncompressed_size) if compression == "zstd" \
                else lz4.frame.decompress(raw) if compression == "lz4" else None
            if data is None:
                return f"unsupported chunk compression {compression!r}"
            records = memoryview(data)
            base = -1  # payloads are not addressable in the file
        else:
            records = buf[rec_start:end]
            base = rec_start
        if verify and crc != 0 and zlib.crc32(records) != crc:
            return "chunk CRC mismatch (damaged data)"
        frames: list[StoredFrameRef] = []
        revisions: list[dict[str, Any]] = []
        pending: dict[str, Any] | None = None
        start_uuid: str | None = None
        lost: list[dict[str, Any]] = []
        pos = 0
        n = len(records)
        while pos < n:
            opcode = records[pos]
            (length,) = struct.unpack_from("<Q", records, pos + 1)
            body_pos = pos + 9
            if body_pos + length > n:
                return "record overruns its chunk"
            if opcode == Opcode.CHANNEL:
                (channel_id, _schema_id) = struct.unpack_from("<HH", records, body_pos)
                topic, _ = _read_string(records, body_pos + 4)
                channels[channel_id] = topic
            elif opcode == Opcode.MESSAGE:
                (channel_id,) = struct.unpack_from("<H", records, body_pos)
                data_start = body_pos + 22
                data_end = body_pos + length
                topic = channels.get(channel_id)
                if topic == TOPIC_FRAMES:
                    pending = json.loads(bytes(records[data_start:data_end]))
                elif topic is not None and topic.endswith("/points") and pending is not None:
                    nbytes = int(pending["points"]["n_points"]) * int(pending["points"]["point_stride"])
                    payload_start = data_end - nbytes
                    if payload_start < data_start:
                        return f"frame {pending['frame_id']}: point message shorter than its declared payload"
                    if base >= 0:
                        frames.append(StoredFrameRef(pending, path, base + payload_start))
                    else:
                        frames.append(StoredFrameRef(pending, path, -1, bytes(records[payload_start:data_end])))
                    pending = None
                elif topic == TOPIC_REVISIONS:
                    revisions.append(json.loads(bytes(records[data_start:data_end])))
                elif topic == TOPIC_SEGMENT:
                    event = json.loads(bytes(records[data_start:data_end]))
                    if event.get("event") == "segment_start":
                        start_uuid = str(event["store_uuid"])
                    elif event.get("event") == EVENT_DATA_LOST:
                        lost.append(event)
            pos = body_pos + length
        if pending is not None:
            return f"frame {pending['frame_id']}: metadata without points"
    except (struct.error, ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as exc:
        return f"unreadable chunk content ({exc})"
    scan.frames.extend(frames)
    scan.revisions.extend(revisions)
    scan.data_lost.extend(lost)
    if start_uuid is not None:
        scan.store_uuid = start_uuid
    return None


def iter_payload_bytes(ref: StoredFrameRef, mm: mmap.mmap | None) -> memoryview | bytes:
    """The raw payload of a frame from a mapped segment (or its copied bytes)."""
    if ref.payload_copy is not None:
        return ref.payload_copy
    if mm is None:
        raise StoreError(f"{ref.segment}: segment not mapped")
    nbytes = ref.n_points * ref.point_stride
    return memoryview(mm)[ref.payload_offset : ref.payload_offset + nbytes]

