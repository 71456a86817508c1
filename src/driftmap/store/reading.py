"""Reading frames back: the segments mapped into memory (read-only, remapped when a segment has grown) and a
frame rebuilt from its metadata and point payload."""

from __future__ import annotations

import contextlib
import mmap
from pathlib import Path

import numpy as np

from driftmap.errors import DriftmapError, StoreCorruptError, StoreError
from driftmap.frame import Frame
from driftmap.store.chunk_scan import StoredFrameRef
from driftmap.store.frame_codec import frame_from_info, unpack_attributes
from driftmap.store.guards import READ_HINT, store_io_error
from driftmap.store.manifest import SegmentEntry
from driftmap.store.segment_scan import iter_payload_bytes


def decode_frame(ref: StoredFrameRef, mm: mmap.mmap | None) -> Frame | str:
    """The frame ``ref`` points at, or why it cannot be read back. Returns instead of raising, so that no exception
    (traceback) keeps a view of the mapped segment alive."""
    n, stride = ref.n_points, ref.point_stride
    payload = np.frombuffer(iter_payload_bytes(ref, mm), dtype=np.uint8)
    if len(payload) != n * stride:
        return f"{len(payload)} payload bytes, {n * stride} expected"
    try:
        if stride == 12:
            points = payload.view("<f4").reshape(n, 3)
        else:
            points = np.ascontiguousarray(payload.reshape(n, stride)[:, :12]).view("<f4").reshape(n, 3)
        attributes = unpack_attributes(payload, n, stride, ref.info["points"]["fields"])
        return frame_from_info(ref.info, points, attributes)
    except (DriftmapError, KeyError, TypeError, ValueError, ArithmeticError, AttributeError) as exc:
        return f"stored metadata cannot be read back ({type(exc).__name__}: {exc})"


def frame_from_ref(folder: Path, ref: StoredFrameRef, mm: mmap.mmap | None) -> Frame:
    """The frame ``ref`` points at (in the store in ``folder``); metadata or a payload that cannot be read back is a
    :class:`StoreCorruptError` naming the segment and the frame (``driftmap recover`` drops such frames)."""
    frame = decode_frame(ref, mm)
    if isinstance(frame, str):  # raised here, where no view of the mapped segment is alive (it could not be closed)
        raise StoreCorruptError(f"{ref.segment}: frame {ref.frame_id}: {frame}; run `driftmap recover {folder}`",
                                path=ref.segment, offset=ref.payload_offset)
    return frame


def segment_map(folder: Path, segments: list[SegmentEntry], segment: Path, min_size: int = 0) -> mmap.mmap:
    """A read-only map of ``segment`` (one of ``segments``, in ``folder``), kept with its entry; remapped when the
    segment has grown past ``min_size``.

    Arrays handed out earlier keep their (older, smaller) mapping alive; nothing is copied.
    """
    for seg in segments:
        if folder / seg.name == segment:
            if seg.mm is None or len(seg.mm) < min_size:
                try:
                    with open(segment, "rb") as fh:
                        seg.mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
                except (OSError, ValueError) as exc:  # ValueError: an empty file cannot be mapped
                    if isinstance(exc, OSError):
                        raise store_io_error(exc, segment, "mapping the segment", folder, READ_HINT) from exc
                    raise StoreCorruptError(f"{segment}: empty; run `driftmap recover {folder}`", path=segment,
                                            offset=0) from exc
                if len(seg.mm) < min_size:
                    raise StoreCorruptError(f"{segment}: {len(seg.mm)} bytes, but a frame's points end at offset "
                                            f"{min_size} (truncated after the store was opened?); run `driftmap "
                                            f"recover {folder}`", path=segment, offset=len(seg.mm))
            return seg.mm
    raise StoreError(f"{segment}: not a segment of {folder}")


def release_maps(segments: list[SegmentEntry]) -> None:
    """Close the segments' maps (one still viewed by an array handed out is left to the array)."""
    for seg in segments:
        if seg.mm is not None:
            with contextlib.suppress(BufferError):
                seg.mm.close()
            seg.mm = None
