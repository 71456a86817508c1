"""The write session of a store opened for appending: the new segment it starts on first use (listed in the
manifest before it is created), frames and revisions written to it, and the segment closed at the end. A failed
write (disk full, an I/O error) is a :class:`~driftmap.errors.StoreIOError` naming the file; the segment is then
left ``open`` for the next writer or ``driftmap recover``."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import FrameRejectedError, GeometryError, StoreError, parse_enum
from driftmap.frame import Frame, PoseSource
from driftmap.store.frame_codec import check_frame_for_store
from driftmap.store.guards import RESUME_HINT, store_io_error
from driftmap.store.layout import MANIFEST, SEGMENT_FILES_GLOB, segment_index, segment_name
from driftmap.store.ledger import PoseLedger
from driftmap.store.manifest import SegmentEntry, lost_segments, write_manifest
from driftmap.store.revision import Revision
from driftmap.store.segment import SegmentWriter

logger = logging.getLogger(__name__)

REVISION_HINT = ("the frames and revisions stored before it are intact; free space (or fix the device), run "
                 "`driftmap recover {store}` and make the correction again")
"""how to continue after a revision could not be stored"""


def refuse_broken(folder: Path, writer: SegmentWriter | None, what: str) -> None:
    """Refuse to go on ``what`` with a writer broken by an earlier failed write."""
    if writer is not None and writer.broken is not None:
        raise StoreError(f"{writer.path}: cannot go on {what}: an earlier write to this segment failed "
                         f"({writer.broken}); close the store: {RESUME_HINT.format(store=folder)}")


def next_segment_index(folder: Path, manifest: dict[str, Any], segments: list[SegmentEntry]) -> int:
    """One past the highest segment index in use: listed, removed by recovery, or any ``segment-N.*`` file
    (kept damaged copies, an orphan of an interrupted recovery), so a new segment never takes a used name."""
    names = [s.name for s in segments] + lost_segments(manifest)
    names += [f.name for f in folder.glob(SEGMENT_FILES_GLOB)]
    return max((i for n in names if (i := segment_index(n)) is not None), default=-1) + 1


def start_segment(folder: Path, manifest: dict[str, Any], segments: list[SegmentEntry], *, fsync: bool,
                  what: str) -> SegmentWriter:
    """Start a new segment for ``what`` (e.g. ``"appending frame 7"``): listed (``open``) in the manifest first,
    then created, so that a crash in between leaves nothing unlisted."""
    try:
        index = next_segment_index(folder, manifest, segments)
    except OSError as exc:
        raise store_io_error(exc, folder, f"listing the segments ({what})", folder) from exc
    name = segment_name(index)
    segments.append(SegmentEntry(name, "open", None))
    try:
        write_manifest(folder, manifest, segments)
    except OSError as exc:
        segments.pop()  # the manifest on disk is the one before (written atomically)
        raise store_io_error(exc, folder / MANIFEST, f"starting segment {name} ({what})", folder) from exc
    try:
        return SegmentWriter(folder / name, index, manifest["store_uuid"], fsync=fsync)
    except OSError as exc:
        _forget_unstarted_segment(folder, manifest, segments, name)
        raise store_io_error(exc, folder / name, f"starting the segment ({what})", folder) from exc


def _forget_unstarted_segment(folder: Path, manifest: dict[str, Any], segments: list[SegmentEntry], name: str) -> None:
    """After a new segment could not be started: take it off the manifest again if its file was never made
    (a listed segment that does not exist would read as data lost); else it stays, ``open``, for recovery."""
    if (folder / name).exists():
        return
    segments[:] = [seg for seg in segments if seg.name != name]
    try:
        write_manifest(folder, manifest, segments)
    except OSError as exc:
        logger.warning("%s: could not take the unstarted segment %s off the manifest (%s); run `driftmap recover "
                       "%s`", folder / MANIFEST, name, exc, folder)


def check_new_frame(folder: Path, ledger: PoseLedger, frame: Frame) -> tuple[int, NDArray[np.float64], PoseSource]:
    """Everything about ``frame`` that appending it checks before writing (see ``FrameStore.append``); returns its
    id, its revision-0 pose and the pose's source."""
    check_frame_for_store(frame, str(folder))
    fid = int(frame.frame_id)
    if fid in ledger:
        raise StoreError(f"{folder}: frame {fid} is already stored; frame ids must be unique")
    try:  # what the ledger will check after the write, checked before it (Frame already makes poses rigid)
        T = geometry.as_rigid(frame.pose.T_world_sensor, f"{folder}: frame {fid}: pose.T_world_sensor")
        source = parse_enum(PoseSource, frame.pose.source, f"{folder}: frame {fid}: pose.source", StoreError)
    except (GeometryError, StoreError) as exc:
        raise FrameRejectedError(str(exc), frame_id=fid, field="pose") from exc
    return fid, T, source


def write_frame(folder: Path, writer: SegmentWriter, frame: Frame, fid: int) -> tuple[int, dict[str, Any]]:
    """Write a checked frame; returns the file offset of its point payload and its metadata."""
    try:
        return writer.append_frame(frame, check=False)
    except OSError as exc:
        raise store_io_error(exc, writer.path, f"appending frame {fid}", folder) from exc


def write_revision(folder: Path, writer: SegmentWriter, revision: Revision) -> None:
    """Write a planned revision (the ledger commits it once this succeeded)."""
    try:
        writer.append_revision(revision.to_json(), revision.created_ns)
    except OSError as exc:
        raise store_io_error(exc, writer.path, f"storing pose revision {revision.revision_id}", folder,
                             REVISION_HINT) from exc


def finish_segment(folder: Path, manifest: dict[str, Any], segments: list[SegmentEntry], writer: SegmentWriter) -> None:
    """Finish the session's segment (MCAP summary and footer) and record it ``closed``; after a failed write it is
    left ``open`` for the next writer or ``driftmap recover``, with a warning."""
    if writer.broken is not None:
        logger.warning("%s: left open after a failed write (%s); its frames are intact, and the next writer "
                       "(driftmap build ... --resume) or `driftmap recover %s` finishes it", writer.path,
                       writer.broken, folder)
        writer.abandon()
        return
    try:
        size = writer.close()
    except OSError as exc:
        raise store_io_error(exc, writer.path, "finishing the segment (summary and footer)", folder) from exc
    seg = next(s for s in segments if s.name == writer.path.name)
    seg.state, seg.bytes = "closed", size
    seg.record_contents(writer.frame_ids, writer.revision_ids)
    try:
        write_manifest(folder, manifest, segments)
    except OSError as exc:
        raise store_io_error(exc, folder / MANIFEST, f"recording {seg.name} as closed", folder) from exc
