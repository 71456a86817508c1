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

import contextlib
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
from driftmap.errors import FrameRejectedError, GeometryError, StoreError
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


UINT64_MAX = 2**64 - 1
INT64_MAX = 2**63 - 1


def check_log_time(value: object, what: str, *, frame_id: int | None = None, field_name: str = "stamp_ns") -> int:
    """``value`` as an MCAP log time: an integer number of nanoseconds in ``0 .. 2**63 - 1`` (MCAP log times are
    unsigned 64-bit; the ledger keeps them as signed 64-bit). Anything else is a
    :class:`~driftmap.errors.FrameRejectedError` naming ``what`` (nothing has been written)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise FrameRejectedError(f"{what}: {field_name} must be an integer number of nanoseconds, got {value!r}",
                                 frame_id=frame_id, field=field_name)
    out = int(value)
    if not 0 <= out <= INT64_MAX:
        why = ("negative: MCAP log times are unsigned (a data set whose times start before 0 needs its stamps "
               "shifted)") if out < 0 else "beyond 2**63 - 1 ns"
        raise FrameRejectedError(f"{what}: {field_name} = {out} ns is {why}", frame_id=frame_id, field=field_name)
    return out


def _finite_matrix(T: object, what: str, frame_id: int | None, field_name: str) -> None:
    arr = np.asarray(T, dtype=np.float64) if T is not None else None
    if arr is None or arr.shape != (4, 4) or not np.all(np.isfinite(arr)):
        raise FrameRejectedError(f"{what}: {field_name} must be a finite 4x4 matrix", frame_id=frame_id, field=field_name)


def check_frame_for_store(frame: Frame, what: str) -> None:
    """Every value of ``frame`` the store writes, checked before anything is written (a
    :class:`~driftmap.errors.FrameRejectedError` naming the frame and the field):

    - ``frame_id``: an integer that fits int64; ``stamp_ns``: see :func:`check_log_time` (stamps need not increase);
    - ``pose.T_world_sensor``, ``T_base_sensor`` and the covariance: finite (``Frame`` also checks that the poses
      are rigid);
    - ``points_sensor``: float32 (N, 3) without an infinite coordinate. NaN coordinates are accepted: they mark
      points without a measurement, which the map leaves out (docs/store.md);
    - attributes: the dtypes and lengths ``Frame`` guarantees.
    """
    if not isinstance(frame, Frame):
        raise FrameRejectedError(f"{what}: expected a Frame, got {type(frame).__name__}", frame_id=None, field="frame")
    fid = frame.frame_id
    if isinstance(fid, bool) or not isinstance(fid, (int, np.integer)) or not -(2**63) <= int(fid) <= INT64_MAX:
        raise FrameRejectedError(f"{what}: frame_id must be a 64-bit integer, got {fid!r}", frame_id=None, field="frame_id")
    fid = int(fid)
    where = f"{what}: frame {fid}"
    check_log_time(frame.stamp_ns, where, frame_id=fid)
    if not isinstance(frame.pose, PoseEstimate):
        raise FrameRejectedError(f"{where}: pose must be a PoseEstimate", frame_id=fid, field="pose")
    _finite_matrix(frame.pose.T_world_sensor, where, fid, "pose.T_world_sensor")
    _finite_matrix(frame.T_base_sensor, where, fid, "T_base_sensor")
    cov = frame.pose.covariance_6x6
    if cov is not None and not (np.shape(cov) == (6, 6) and np.all(np.isfinite(cov))):
        raise FrameRejectedError(f"{where}: pose.covariance_6x6 must be a finite 6x6 matrix", frame_id=fid,
                                 field="pose.covariance_6x6")
    pts = frame.points_sensor
    if not isinstance(pts, np.ndarray) or pts.dtype != np.float32 or pts.ndim != 2 or pts.shape[1] != 3:
        raise FrameRejectedError(f"{where}: points_sensor must be a float32 (N, 3) array", frame_id=fid,
                                 field="points_sensor")
    if pts.size and np.isinf(pts).any():
        row = int(np.flatnonzero(np.isinf(pts).any(axis=1))[0])
        raise FrameRejectedError(
            f"{where}: points_sensor[{row}] = {pts[row].tolist()} has an infinite coordinate ({int(np.isinf(pts).any(axis=1).sum())} "
            f"such points); drop them before storing (NaN marks a point without a measurement, inf is refused)",
            frame_id=fid, field="points_sensor")
    for name in frame.attributes.names():
        value = getattr(frame.attributes, name)
        if not isinstance(value, np.ndarray) or len(value) != len(pts):
            raise FrameRejectedError(f"{where}: attributes.{name} must hold one value per point", frame_id=fid,
                                     field=f"attributes.{name}")


def open_new_segment_file(path: Path) -> IO[bytes]:
    """The file a new segment is written to (created exclusively). A seam for tests that inject I/O errors."""
    return open(path, "xb")


@dataclass
class SegmentWriter:
    """Appends frames and revisions to one new MCAP segment; every append is flushed as its own chunk.

    Every value is checked before the first byte of a record is handed to the MCAP writer (a refused frame leaves
    the segment as it was). If writing fails after that (a full disk, an I/O error), the writer is *broken*: the
    partial record is cut off the file (``os.truncate`` to the end of the last complete chunk, which needs no
    space), later appends are refused, and :meth:`close` cannot finish the segment (:meth:`abandon` it: it stays
    ``open`` in the manifest and is rewritten as a closed segment by the next writer or ``driftmap recover``).
    """

    path: Path
    segment_index: int
    store_uuid: str
    fsync: bool = False
    _fh: IO[bytes] = field(init=False, repr=False)
    _writer: Writer = field(init=False, repr=False)
    _channels: dict[str, int] = field(init=False, default_factory=dict, repr=False)
    _schemas: dict[str, int] = field(init=False, default_factory=dict, repr=False)
    good_size: int = field(init=False, default=0)
    """Bytes of the file up to the end of the last complete chunk."""
    broken: BaseException | None = field(init=False, default=None)
    """The error that broke this writer (None: healthy)."""

    def __post_init__(self) -> None:
        if self.path.exists():
            raise StoreError(f"{self.path}: segment already exists")
        self._fh = open_new_segment_file(self.path)
        with self._writing("starting the segment"):
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
            self._add_event({"event": "segment_start", "segment_index": self.segment_index, "store_uuid": self.store_uuid,
                             "driftmap_version": __version__}, 0)

    @contextlib.contextmanager
    def _writing(self, what: str) -> Iterator[None]:
        """Run one write; any error in it breaks the writer (the MCAP writer's state no longer matches the file)
        and cuts the partial record off the file."""
        if self.broken is not None:
            raise StoreError(f"{self.path}: cannot write ({what}): an earlier write to this segment failed "
                             f"({self.broken}); close the store and reopen it (the segment is recovered)")
        try:
            yield
        except BaseException as exc:
            self.broken = exc
            self._cut_partial_record()
            raise

    def _cut_partial_record(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self._fh.close()  # flushing what is left may fail again: the raw file is closed all the same
        try:
            if os.path.getsize(self.path) > self.good_size:
                os.truncate(self.path, self.good_size)
        except OSError as exc:
            logger.warning("%s: could not cut the unfinished record after a failed write (%s); readers drop it as "
                           "an unfinished tail", self.path, exc)

    def _channel(self, topic: str, encoding: str, schema: str) -> int:
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(topic, encoding, self._schemas[schema])
        return self._channels[topic]

    def _add_event(self, payload: dict[str, Any], log_time_ns: int) -> None:
        self._writer.add_message(self._channels[TOPIC_SEGMENT], log_time_ns, _json_bytes(payload), log_time_ns)
        self._commit()

    def append_event(self, payload: dict[str, Any], log_time_ns: int) -> None:
        """Write one segment event (``payload["event"]`` names its kind) as a chunk of its own."""
        t = check_log_time(log_time_ns, f"{self.path}: segment event {payload.get('event')!r}", field_name="log_time_ns")
        data = _json_bytes(payload)
        with self._writing(f"event {payload.get('event')!r}"):
            self._writer.add_message(self._channels[TOPIC_SEGMENT], t, data, t)
            self._commit()

    def _commit(self) -> None:
        self._writer.flush()  # finishes the chunk and flushes Python's buffer: the chunk is in the kernel
        if self.fsync:
            os.fsync(self._fh.fileno())
        self.good_size = self._fh.tell()

    def points_topic(self, sensor_name: str) -> str:
        return f"/driftmap/{sensor_name}/points"

    def append_frame(self, frame: Frame, *, check: bool = True) -> tuple[int, dict[str, Any]]:
        """Write one frame as one chunk; returns the file offset of its point payload and its metadata.

        Everything is checked (:func:`check_frame_for_store`; ``check=False``: only the stamp, for frames copied
        bit for bit out of a store) and serialised before the first byte goes to the file (see :meth:`_writing`)."""
        if check:
            check_frame_for_store(frame, str(self.path))
        t = check_log_time(frame.stamp_ns, f"{self.path}: frame {frame.frame_id}", frame_id=frame.frame_id)
        topic = self.points_topic(frame.sensor_name)
        payload, stride, fields = pack_points(frame.points_sensor, frame.attributes)
        crc = zlib.crc32(payload)
        cloud_name = cloud_frame_name(frame.sensor_frame, frame.frame_id)
        cloud = PointCloud(frame_id=cloud_name, point_stride=stride, data=payload)
        cloud.timestamp.FromNanoseconds(t)
        cloud.pose.orientation.w = 1.0
        for f in fields:
            cloud.fields.add(name=f["name"], offset=f["offset"], type=f["type"])
        cloud_bytes = cloud.SerializeToString()
        prefix = len(cloud_bytes) - len(payload)
        if cloud_bytes[prefix:] != payload:  # data must be the last field of the serialised message
            raise StoreError("foxglove.PointCloud serialisation does not end with the point payload")
        info_dict = frame_info(frame, stride, fields, crc)
        try:
            info_core = _json_bytes(info_dict)
        except ValueError as exc:  # NaN / inf in the metadata (quality, tracking, intrinsics): JSON cannot hold it
            raise FrameRejectedError(f"{self.path}: frame {frame.frame_id}: metadata holds a value JSON cannot store "
                                     f"({exc})", frame_id=frame.frame_id, field="metadata") from exc
        tf = FrameTransform(parent_frame_id=frame.pose.world_frame, child_frame_id=cloud_name)
        tf.timestamp.FromNanoseconds(t)
        T = frame.pose.T_world_sensor
        tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in T[:3, 3])
        qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = float(qx), float(qy), float(qz), float(qw)
        tf_bytes = tf.SerializeToString()
        with self._writing(f"frame {frame.frame_id}"):
            if topic not in self._channels:
                # a new sensor: register its channel in a chunk of its own, so frame chunks have a fixed layout
                self._channel(topic, "protobuf", "foxglove.PointCloud")
                self._add_event({"event": "sensor", "sensor_name": frame.sensor_name,
                                 "sensor_kind": frame.sensor_kind.value, "topic": topic}, t)
            chunk_start = self._fh.tell()
            payload_offset = chunk_start + _CHUNK_HEADER_BYTES + 2 * _MESSAGE_HEADER_BYTES + len(info_core) + prefix
            info = info_core + b" " * (-payload_offset % PAYLOAD_ALIGNMENT)
            payload_offset = chunk_start + _CHUNK_HEADER_BYTES + 2 * _MESSAGE_HEADER_BYTES + len(info) + prefix
            self._writer.add_message(self._channels[TOPIC_FRAMES], t, info, t)
            self._writer.add_message(self._channels[topic], t, cloud_bytes, t)
            self._writer.add_message(self._channels[TOPIC_TF], t, tf_bytes, t)
            self._commit()
        return payload_offset, info_dict

    def append_revision(self, revision_json: dict[str, Any], log_time_ns: int) -> None:
        t = check_log_time(log_time_ns, f"{self.path}: revision {revision_json.get('revision_id')}",
                           field_name="created_ns")
        try:
            data = _json_bytes(revision_json)
        except (TypeError, ValueError) as exc:
            raise FrameRejectedError(f"{self.path}: revision {revision_json.get('revision_id')}: not storable as JSON "
                                     f"({exc})", frame_id=None, field="revision") from exc
        with self._writing(f"revision {revision_json.get('revision_id')}"):
            self._writer.add_message(self._channels[TOPIC_REVISIONS], t, data, t)
            self._commit()

    def close(self) -> int:
        """Write the summary and footer; returns the final size in bytes."""
        with self._writing("finishing the segment (summary and footer)"):
            self._writer.finish()
            self._fh.flush()
            os.fsync(self._fh.fileno())
            size = self._fh.tell()
            self._fh.close()
        return size

    def abandon(self) -> None:
        """Close the file without a summary (the store is torn down after an error, or the writer broke): the
        segment keeps its complete chunks and stays ``open`` for recovery."""
        if self.broken is not None:
            return  # already closed and cut back to its last complete chunk
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
    if pos + 4 + n > len(buf):
        raise ValueError(f"string of {n} bytes overruns its record")
    return bytes(buf[pos + 4 : pos + 4 + n]).decode(), pos + 4 + n


#: the largest uncompressed chunk a compressed chunk may claim (the store writes uncompressed chunks only)
_MAX_UNCOMPRESSED_CHUNK = 1 << 32
_FIELD_SIZES = {_NUMERIC.FLOAT32: 4, _NUMERIC.FLOAT64: 8, _NUMERIC.UINT8: 1}
_SENSOR_KINDS = frozenset(k.value for k in SensorKind)
_POSE_SOURCES = frozenset(p.value for p in PoseSource)


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _numbers(value: object, n: int) -> bool:
    """A list of ``n`` finite JSON numbers."""
    return (isinstance(value, list) and len(value) == n
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in value))


def check_frame_info(info: object) -> str | None:
    """What is wrong with a stored frame's metadata as far as the store relies on it when opening (ids, stamp,
    revision-0 pose, point layout), or None. Cheap: run for every frame of every scanned segment. (The remaining
    fields are checked when a frame is read, :meth:`driftmap.store.frame_store.FrameStore.frame`, and by recovery.)"""
    if not isinstance(info, dict):
        return f"frame metadata is a JSON {type(info).__name__}, not an object"
    fid = info.get("frame_id")
    if not _is_int(fid) or not -(2**63) <= fid <= INT64_MAX:
        return f"frame_id {fid!r} is not a 64-bit integer"
    stamp = info.get("stamp_ns")
    if not _is_int(stamp) or not 0 <= stamp <= INT64_MAX:
        return f"frame {fid}: stamp_ns {stamp!r} is not a non-negative 64-bit integer"
    for key in ("sensor_name", "sensor_frame", "base_frame"):
        if not isinstance(info.get(key), str):
            return f"frame {fid}: {key} is not a string"
    if info.get("sensor_kind") not in _SENSOR_KINDS:
        return f"frame {fid}: unknown sensor_kind {info.get('sensor_kind')!r}"
    if not _numbers(info.get("T_base_sensor"), 16):
        return f"frame {fid}: T_base_sensor is not 16 finite numbers"
    pose = info.get("pose")
    if not isinstance(pose, dict) or not _numbers(pose.get("T_world_sensor"), 16):
        return f"frame {fid}: pose.T_world_sensor is not 16 finite numbers"
    if pose.get("source") not in _POSE_SOURCES or not _is_int(pose.get("revision")) or pose["revision"] < 0:
        return f"frame {fid}: pose.source / pose.revision malformed"
    if not isinstance(pose.get("world_frame", WORLD_FRAME), str):
        return f"frame {fid}: pose.world_frame is not a string"
    cov = pose.get("covariance_6x6")
    if cov is not None and not _numbers(cov, 36):
        return f"frame {fid}: pose.covariance_6x6 is not 36 finite numbers"
    points = info.get("points")
    if not isinstance(points, dict):
        return f"frame {fid}: no point layout"
    n, stride, fields = points.get("n_points"), points.get("point_stride"), points.get("fields")
    if not _is_int(n) or n < 0 or not _is_int(stride) or not 12 <= stride <= 1 << 16 or not isinstance(fields, list):
        return f"frame {fid}: point layout malformed (n_points {n!r}, point_stride {stride!r})"
    names: list[str] = []
    for f in fields:
        if (not isinstance(f, dict) or not isinstance(f.get("name"), str) or not _is_int(f.get("offset"))
                or f.get("type") not in _FIELD_SIZES or not 0 <= f["offset"] <= stride - _FIELD_SIZES[f["type"]]):
            return f"frame {fid}: point field {f!r} malformed"
        names.append(f["name"])
    if fields[:3] != [{"name": c, "offset": 4 * i, "type": int(_NUMERIC.FLOAT32)} for i, c in enumerate("xyz")]:
        return f"frame {fid}: the first point fields are not x y z float32"
    if len(set(names)) != len(names):
        return f"frame {fid}: point field names repeat"
    for attr, (comp, numeric, _) in _ATTRIBUTE_FIELDS.items():
        present = [c in names for c in comp]
        if any(present) and not all(present):
            return f"frame {fid}: attribute {attr} is missing some of its fields {comp}"
        if all(present):
            by_name = {f["name"]: f for f in fields}
            first = by_name[comp[0]]["offset"]
            size = _FIELD_SIZES[numeric]
            if any(by_name[c]["type"] != int(numeric) or by_name[c]["offset"] != first + k * size for k, c in enumerate(comp)):
                return f"frame {fid}: attribute {attr} has an unexpected layout"
    if not _is_int(points.get("crc32")):
        return f"frame {fid}: points.crc32 is not an integer"
    return None


def _check_event(event: object) -> str | None:
    if not isinstance(event, dict):
        return "segment event is not a JSON object"
    kind = event.get("event")
    if kind == "segment_start" and not isinstance(event.get("store_uuid"), str):
        return "segment_start event without a store_uuid string"
    if kind == EVENT_DATA_LOST:
        for key in ("frame_ids", "revision_ids"):
            value = event.get(key)
            if not isinstance(value, list) or not all(_is_int(i) for i in value):
                return f"{EVENT_DATA_LOST} event: {key} is not a list of integers"
        recovered = event.get("recovered_ns", 0)
        if not _is_int(recovered) or not 0 <= recovered <= INT64_MAX:
            return f"{EVENT_DATA_LOST} event: recovered_ns {recovered!r} is not a non-negative 64-bit integer"
    return None


def _check_revision(data: object) -> str | None:
    from driftmap.store.ledger import Revision

    try:
        rev = Revision.from_json(data)  # type: ignore[arg-type]
    except (StoreError, GeometryError) as exc:
        return f"revision record: {exc}"
    if not 0 <= rev.created_ns <= INT64_MAX:
        return f"revision {rev.revision_id}: created_ns {rev.created_ns} is not a non-negative 64-bit integer"
    return None


def _summary_problem(buf: memoryview, size: int, data_end: int, chunk_offsets: list[int], verify: bool) -> tuple[str, int] | None:
    """What is wrong with the summary and footer after the data section (they list every chunk), or None.

    The scanner reads the data section only; the summary is checked so that damage there is found (a generic MCAP
    reader such as Foxglove relies on it) and so that a chunk whose opcode byte was damaged (and would otherwise
    look like a record to skip) cannot vanish silently: the chunk offsets found must be the ones the summary lists.
    """
    footer = size - len(MCAP_MAGIC) - (1 + 8 + 20)
    if footer < data_end or bytes(buf[size - len(MCAP_MAGIC):]) != MCAP_MAGIC:
        return "no footer and closing magic after the end of data", data_end
    if buf[footer] != Opcode.FOOTER or struct.unpack_from("<Q", buf, footer + 1)[0] != 20:
        return "damaged footer", footer
    summary_start, _offsets_start, summary_crc = struct.unpack_from("<QQI", buf, footer + 9)
    if summary_start == 0:
        return "the segment has no summary", footer
    if summary_start != data_end:
        return f"the summary does not start at the end of data (footer says offset {summary_start})", footer
    if verify and summary_crc != 0 and zlib.crc32(buf[summary_start : footer + 9 + 16]) != summary_crc:
        return "summary CRC mismatch (damaged summary)", summary_start
    listed: list[int] = []
    pos = summary_start
    while pos < footer:
        if pos + 9 > footer:
            return "truncated summary record", pos
        opcode = buf[pos]
        (length,) = struct.unpack_from("<Q", buf, pos + 1)
        if pos + 9 + length > footer:
            return f"summary record (opcode 0x{opcode:02x}) overruns the footer", pos
        if opcode == Opcode.CHUNK_INDEX:
            if length < 24:
                return "damaged chunk index", pos
            listed.append(struct.unpack_from("<Q", buf, pos + 9 + 16)[0])
        pos += 9 + length
    if sorted(listed) != chunk_offsets:
        missing = sorted(set(listed) - set(chunk_offsets))
        extra = sorted(set(chunk_offsets) - set(listed))
        at = min(missing + extra) if missing or extra else summary_start
        return (f"the summary lists {len(listed)} chunks, the data section holds {len(chunk_offsets)} "
                f"(first difference at offset {at})"), at
    return None


def scan_segment(path: Path, *, verify: bool = True, stop_on_error: bool = True) -> SegmentScan:
    """Walk a segment's records without decoding point payloads.

    Complete chunks yield frames (metadata + payload offset) and revisions. A truncated tail stops the
    scan and is reported (``problem``, ``problem_offset``); with ``verify`` every chunk's CRC is checked,
    and a mismatch is reported the same way. With ``stop_on_error=False`` a chunk whose framing is intact
    but whose content is damaged is skipped and the scan goes on (used by recovery).

    Nothing read from the file is trusted: every length is checked against the bytes present before it is used
    (no allocation is sized by a length field), the data section may hold only the records the store writes
    (header, chunks, message indexes, end of data), every chunk's records must fill it exactly, and the metadata
    and revision records must be well formed (:func:`check_frame_info`). A closed segment's summary must list
    exactly the chunks found. Any violation is a ``problem`` (or, inside a chunk, a damaged chunk).
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
        size = scan.size = min(size, len(buf))
        chunk_offsets: list[int] = []
        # the message index records a chunk's messages must have next: channel id -> ((log time, offset), ...);
        # None: not checked (after a damaged chunk)
        expected_index: dict[int, tuple[tuple[int, int], ...]] | None = {}
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
                if opcode in (Opcode.DATA_END, Opcode.CHUNK) and expected_index:
                    scan.problem, scan.problem_offset = "the message index of the chunk before is missing", pos
                    break
                if opcode == Opcode.DATA_END:
                    if length != 4:
                        scan.problem, scan.problem_offset = "damaged end-of-data record", pos
                        break
                    scan.complete = True
                    scan.valid_bytes = end
                    summary = _summary_problem(buf, size, end, chunk_offsets, verify)
                    if summary is not None:
                        scan.problem, scan.problem_offset = summary
                    break
                if opcode == Opcode.CHUNK:
                    chunk_offsets.append(pos)
                    messages: dict[int, list[tuple[int, int]]] = {}
                    err = _scan_chunk(buf, body, end, path, channels, scan, verify, messages)
                    expected_index = {c: tuple(m) for c, m in messages.items()}
                    if err is not None:
                        if stop_on_error:
                            scan.problem, scan.problem_offset = err, pos
                            break
                        logger.warning("%s: skipping damaged chunk at offset %d: %s", path, pos, err)
                        scan.damaged_chunks.append((pos, err))
                        scan.damaged_bytes += end - pos
                        expected_index = None
                elif opcode == Opcode.MESSAGE_INDEX:
                    if length < 6 or struct.unpack_from("<I", buf, body + 2)[0] != length - 6 or (length - 6) % 16:
                        scan.problem, scan.problem_offset = "damaged message index record", pos
                        break
                    if expected_index is not None:
                        (channel_id,) = struct.unpack_from("<H", buf, body)
                        listed = tuple(struct.iter_unpack("<QQ", buf[body + 6 : end]))
                        if expected_index.pop(channel_id, None) != listed:
                            scan.problem, scan.problem_offset = "message index record disagrees with its chunk", pos
                            break
                elif not (opcode == Opcode.HEADER and pos == 8):
                    # the store writes nothing else into the data section: anything else is damage (a chunk
                    # whose opcode byte changed must not be skipped as if it were some other record)
                    scan.problem, scan.problem_offset = f"unexpected record opcode 0x{opcode:02x} in the data section", pos
                    break
                pos = end
                scan.valid_bytes = pos
        finally:
            buf.release()
    finally:
        mm.close()
    return scan


def read_store_uuid(path: Path) -> str | None:
    """The store a segment names in its first chunk (``segment_start``), or None when that cannot be read."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError:
        return None
    buf = memoryview(head)
    if bytes(buf[:8]) != MCAP_MAGIC:
        return None
    pos, channels = 8, {}
    scan = SegmentScan(path, len(head))
    while pos + 9 <= len(buf):
        opcode = buf[pos]
        (length,) = struct.unpack_from("<Q", buf, pos + 1)
        if pos + 9 + length > len(buf):
            return None
        if opcode == Opcode.CHUNK:
            err = _scan_chunk(buf, pos + 9, pos + 9 + length, path, channels, scan, True, {})
            return None if err is not None else scan.store_uuid
        pos += 9 + length
    return None


def _scan_chunk(buf: memoryview, body: int, end: int, path: Path, channels: dict[int, str], scan: SegmentScan,
                verify: bool, messages: dict[int, list[tuple[int, int]]]) -> str | None:
    """Read one chunk's inner records; returns an error string if the chunk is damaged. ``messages`` receives
    channel id -> [(log time, offset in the chunk's records)] of its messages (what its message index must say)."""
    try:
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
            if uncompressed_size > _MAX_UNCOMPRESSED_CHUNK:
                return f"chunk claims {uncompressed_size} uncompressed bytes"
            import lz4.frame
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
        frames: list[StoredFrameRef] = []
        revisions: list[dict[str, Any]] = []
        pending: dict[str, Any] | None = None
        start_uuid: str | None = None
        lost: list[dict[str, Any]] = []
        new_channels: dict[int, str] = {}
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
                new_channels[channel_id] = topic
            elif opcode == Opcode.MESSAGE:
                if length < 22:
                    return "message record shorter than its header"
                channel_id, _sequence, log_time = struct.unpack_from("<HIQ", records, body_pos)
                messages.setdefault(channel_id, []).append((log_time, pos))
                data_start = body_pos + 22
                data_end = body_pos + length
                topic = new_channels.get(channel_id, channels.get(channel_id))
                if topic == TOPIC_FRAMES:
                    if pending is not None:
                        return f"frame {pending['frame_id']}: metadata without points"
                    pending = json.loads(bytes(records[data_start:data_end]))
                    problem = check_frame_info(pending)
                    if problem is not None:
                        return problem
                elif topic is not None and topic.endswith("/points"):
                    if pending is None:
                        return "points without frame metadata"
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
                    revision = json.loads(bytes(records[data_start:data_end]))
                    problem = _check_revision(revision)
                    if problem is not None:
                        return problem
                    revisions.append(revision)
                elif topic == TOPIC_SEGMENT:
                    event = json.loads(bytes(records[data_start:data_end]))
                    problem = _check_event(event)
                    if problem is not None:
                        return problem
                    if event.get("event") == "segment_start":
                        start_uuid = str(event["store_uuid"])
                    elif event.get("event") == EVENT_DATA_LOST:
                        lost.append(event)
            elif opcode != Opcode.SCHEMA:
                return f"unexpected record opcode 0x{opcode:02x} in a chunk"
            pos = body_pos + length
        if pending is not None:
            return f"frame {pending['frame_id']}: metadata without points"
        times = [t for listed in messages.values() for t, _ in listed]
        if not times:
            return "chunk without messages"
        if (min(times), max(times)) != (start_time, end_time):
            return "chunk start / end times disagree with its messages"
    except (struct.error, ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError, RecursionError,
            ArithmeticError, MemoryError) as exc:
        return f"unreadable chunk content ({type(exc).__name__}: {exc})"
    channels.update(new_channels)  # a damaged chunk registers nothing
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

