"""What one MCAP segment of a frame store holds: its topics, events and record sizes (the writer is
:mod:`driftmap.store.segment`, the scanner :mod:`driftmap.store.segment_scan`, a frame's metadata and point layout
:mod:`driftmap.store.frame_codec`).

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
from typing import Any

MCAP_MAGIC = b"\x89MCAP0\r\n"
# a segment's MCAP header: profile "" and library "driftmap VERSION" (SegmentWriter; checked by scan_segment)
SEGMENT_LIBRARY_PREFIX = "driftmap "
PAYLOAD_ALIGNMENT = 16
TOPIC_SEGMENT = "/driftmap/segment"
TOPIC_FRAMES = "/driftmap/frames"
TOPIC_REVISIONS = "/driftmap/revisions"
TOPIC_TF = "/tf"
EVENT_DATA_LOST = "data_lost"
CHUNK_HEADER_BYTES = 1 + 8 + 8 + 8 + 8 + 4 + 4 + 8  # opcode, length, start, end, size, crc, "" compression, records length
MESSAGE_HEADER_BYTES = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel, sequence, log_time, publish_time
MAX_UNCOMPRESSED_CHUNK = 1 << 32
"""the largest uncompressed chunk a compressed chunk may claim (the store writes uncompressed chunks only)"""

JSON_SCHEMA_FRAME_INFO = {
    "title": "driftmap.FrameInfo",
    "description": "Metadata of one stored frame; its points are the next message in the same chunk.",
    "type": "object",
}
JSON_SCHEMA_REVISION = {"title": "driftmap.PoseRevision", "description": "A pose revision of the ledger.", "type": "object"}
JSON_SCHEMA_SEGMENT = {"title": "driftmap.SegmentEvent", "description": "Segment start and sensor registration.", "type": "object"}


def points_topic(sensor_name: str) -> str:
    """The topic of a sensor's point clouds."""
    return f"/driftmap/{sensor_name}/points"


def json_bytes(obj: Any) -> bytes:
    """``obj`` as compact JSON (NaN and infinity refused: a ``ValueError``)."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
