"""One MCAP segment of a frame store: how frames and pose revisions are written (:class:`SegmentWriter`).

What a segment holds is described in :mod:`driftmap.store.segment_format`; how it is found again without reading
the point payloads is :mod:`driftmap.store.segment_scan`; a frame's metadata and point layout are
:mod:`driftmap.store.frame_codec`. Their names are re-exported here.

The writer flushes after every frame and revision: a chunk on disk is a committed frame; a writer killed
mid-append leaves at most one incomplete chunk at the end of the file.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set
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
from driftmap.store.frame_codec import (
    INT64_MAX,
    UINT64_MAX,
    WORLD_FRAME,
    check_frame_for_store,
    check_frame_info,
    check_log_time,
    cloud_frame_name,
    frame_from_info,
    frame_info,
    pack_points,
    point_layout,
    unpack_attributes,
)
from driftmap.store.segment_format import (
    CHUNK_HEADER_BYTES,
    EVENT_DATA_LOST,
    JSON_SCHEMA_FRAME_INFO,
    JSON_SCHEMA_REVISION,
    JSON_SCHEMA_SEGMENT,
    MCAP_MAGIC,
    MESSAGE_HEADER_BYTES,
    PAYLOAD_ALIGNMENT,
    SEGMENT_LIBRARY_PREFIX,
    TOPIC_FRAMES,
    TOPIC_REVISIONS,
    TOPIC_SEGMENT,
    TOPIC_TF,
    json_bytes,
    points_topic,
)
from driftmap.store.segment_scan import SegmentScan, StoredFrameRef, iter_payload_bytes, read_store_uuid, scan_segment

#: what this module offers: the writer, and (as before the segment code was split into the format, the frame codec,
#: the writer and the scanner) the names it used to define or import
__all__ = [
    "EVENT_DATA_LOST", "INT64_MAX", "MCAP_MAGIC", "PAYLOAD_ALIGNMENT", "TOPIC_FRAMES", "TOPIC_REVISIONS",
    "TOPIC_SEGMENT", "TOPIC_TF", "UINT64_MAX", "WORLD_FRAME", "Frame", "FrameQuality", "FrameRejectedError",
    "GeometryError", "PinholeIntrinsics", "PointAttributes", "PoseEstimate", "PoseSource", "Provenance", "SegmentScan",
    "SegmentWriter", "SensorKind", "StoreError", "StoredFrameRef", "TrackingHealth", "check_frame_for_store",
    "check_frame_info", "check_log_time", "cloud_frame_name", "frame_from_info", "frame_info", "iter_payload_bytes",
    "open_new_segment_file", "pack_points", "point_layout", "read_store_uuid", "scan_segment", "unpack_attributes",
]

logger = logging.getLogger(__name__)


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
    frame_ids: list[int] = field(init=False, default_factory=list)
    """The frames written to the segment (complete chunks), in order."""
    revision_ids: list[int] = field(init=False, default_factory=list)
    """The revisions written to the segment (complete chunks), in order."""

    def __post_init__(self) -> None:
        if self.path.exists():
            raise StoreError(f"{self.path}: segment already exists")
        self._fh = open_new_segment_file(self.path)
        with self._writing("starting the segment"):
            self._writer = Writer(self._fh, chunk_size=1 << 62, compression=CompressionType.NONE, use_chunking=True)
            self._writer.start(profile="", library=f"{SEGMENT_LIBRARY_PREFIX}{__version__}")
            json_schemas = {
                "driftmap.SegmentEvent": JSON_SCHEMA_SEGMENT,
                "driftmap.FrameInfo": JSON_SCHEMA_FRAME_INFO,
                "driftmap.PoseRevision": JSON_SCHEMA_REVISION,
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
        self._writer.add_message(self._channels[TOPIC_SEGMENT], log_time_ns, json_bytes(payload), log_time_ns)
        self._commit()

    def append_event(self, payload: dict[str, Any], log_time_ns: int) -> None:
        """Write one segment event (``payload["event"]`` names its kind) as a chunk of its own."""
        t = check_log_time(log_time_ns, f"{self.path}: segment event {payload.get('event')!r}", field_name="log_time_ns")
        data = json_bytes(payload)
        with self._writing(f"event {payload.get('event')!r}"):
            self._writer.add_message(self._channels[TOPIC_SEGMENT], t, data, t)
            self._commit()

    def _commit(self) -> None:
        self._writer.flush()  # finishes the chunk and flushes Python's buffer: the chunk is in the kernel
        if self.fsync:
            os.fsync(self._fh.fileno())
        self.good_size = self._fh.tell()

    def points_topic(self, sensor_name: str) -> str:
        return points_topic(sensor_name)

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
            info_core = json_bytes(info_dict)
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
            payload_offset = chunk_start + CHUNK_HEADER_BYTES + 2 * MESSAGE_HEADER_BYTES + len(info_core) + prefix
            info = info_core + b" " * (-payload_offset % PAYLOAD_ALIGNMENT)
            payload_offset = chunk_start + CHUNK_HEADER_BYTES + 2 * MESSAGE_HEADER_BYTES + len(info) + prefix
            self._writer.add_message(self._channels[TOPIC_FRAMES], t, info, t)
            self._writer.add_message(self._channels[topic], t, cloud_bytes, t)
            self._writer.add_message(self._channels[TOPIC_TF], t, tf_bytes, t)
            self._commit()
        self.frame_ids.append(int(frame.frame_id))
        return payload_offset, info_dict

    def append_revision(self, revision_json: dict[str, Any], log_time_ns: int) -> None:
        t = check_log_time(log_time_ns, f"{self.path}: revision {revision_json.get('revision_id')}",
                           field_name="created_ns")
        try:
            data = json_bytes(revision_json)
        except (TypeError, ValueError) as exc:
            raise FrameRejectedError(f"{self.path}: revision {revision_json.get('revision_id')}: not storable as JSON "
                                     f"({exc})", frame_id=None, field="revision") from exc
        with self._writing(f"revision {revision_json.get('revision_id')}"):
            self._writer.add_message(self._channels[TOPIC_REVISIONS], t, data, t)
            self._commit()
        if isinstance(rid := revision_json.get("revision_id"), int):
            self.revision_ids.append(rid)

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
