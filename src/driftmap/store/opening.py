"""Opening a store: scanning the segments its manifest lists (a closed segment must be intact; the last, open one
may end in a crashed writer's unfinished tail) and replaying their frames and revisions into the ledger, in store
order, with what ``recover`` declared lost (see :mod:`driftmap.store.frame_store`, "Losses")."""

from __future__ import annotations

import bisect

import logging
from pathlib import Path
from typing import Any

import numpy as np

from driftmap.errors import GeometryError, StoreCorruptError, StoreError
from driftmap.frame import PoseSource
from driftmap.store.chunk_scan import StoredFrameRef
from driftmap.store.damage import DataLoss, RecoveryEvent, declared_ids, lost_ids, unaccounted, without_frames
from driftmap.store.guards import READ_HINT, store_io_error
from driftmap.store.layout import MANIFEST
from driftmap.store.ledger import PoseLedger
from driftmap.store.manifest import SegmentEntry, unlisted_segments
from driftmap.store.revision import Revision
from driftmap.store.segment_format import EVENT_DATA_LOST
from driftmap.store.segment_scan import SegmentScan, scan_segment
from driftmap.store.values import preview

logger = logging.getLogger(__name__)


def load_segments(folder: Path, store_uuid: str, segments: list[SegmentEntry], ledger: PoseLedger,
                  refs: dict[int, StoredFrameRef], *, verify: bool, live_writer: bool) -> tuple[DataLoss, list[RecoveryEvent]]:
    """Scan the listed ``segments`` (each keeps its scan) and add their frames and revisions to the (empty)
    ``ledger`` and ``refs``. ``verify``: check every chunk's CRC; ``live_writer``: another process holds the writer
    lock (its open segment may be unfinished, or not created yet). Returns the recorded losses and what had to be
    dropped (a crashed writer's unfinished tail)."""
    fix = f"; run `driftmap recover {folder}`"
    try:
        unlisted = unlisted_segments(folder, segments)
    except OSError as exc:
        raise store_io_error(exc, folder, "listing the segments", folder, READ_HINT) from exc
    if unlisted:
        raise StoreCorruptError(f"{folder / MANIFEST}: does not list {preview(unlisted)}, which the store folder "
                                f"holds (a damaged manifest, or an older copy of it?){fix}",
                                path=folder / MANIFEST, offset=None)
    scans: list[SegmentScan] = []
    events: list[RecoveryEvent] = []
    for seg in segments:
        last = seg is segments[-1]
        file = folder / seg.name
        if not file.exists():
            if last and seg.state == "open" and live_writer:
                continue  # a live writer is starting this segment (listed first, then created)
            raise StoreCorruptError(f"{file}: segment listed in the manifest is missing{fix}", path=file, offset=None)
        try:
            scan = scan_segment(file, verify=verify)
        except OSError as exc:
            raise store_io_error(exc, file, "reading the segment", folder, READ_HINT) from exc
        event = _check_scan(folder, store_uuid, seg, scan, last=last, live_writer=live_writer)
        if event is not None:
            events.append(event)
        seg.scan = scan
        scans.append(scan)
    _check_records(folder, [s for s in segments if s.scan is not None])
    loss = replay(folder, ledger, refs, scans, strict=True)[0]
    if loss:
        logger.info("%s: recorded losses: %s", folder, loss)
    return loss, events


def _check_records(folder: Path, segments: list[SegmentEntry]) -> None:
    """Refuse a store whose closed segments no longer account for frames or revisions their manifest entries record
    (stored, or declared lost by a ``data_lost`` event anywhere): a recovery stopped before it declared them, or the
    segment of a loss record damaged (hostile trial 19 B1). ``driftmap recover`` declares them."""
    recorded = [seg.recorded_ids() if seg.state == "closed" else None for seg in segments]
    for seg, (frames, revisions) in zip(segments, unaccounted(recorded, [seg.scan for seg in segments]), strict=True):
        if frames or revisions:
            what = " and ".join(f"{kind} {preview(sorted(ids))}" for kind, ids in (("frames", frames),
                                                                                  ("revisions", revisions)) if ids)
            raise StoreCorruptError(f"{folder / seg.name}: the manifest records {what} in it, which no segment holds "
                                    f"and no recovery declared lost; run `driftmap recover {folder}`",
                                    path=folder / seg.name, offset=None)


def _check_scan(folder: Path, store_uuid: str, seg: SegmentEntry, scan: SegmentScan, *, last: bool,
                live_writer: bool) -> RecoveryEvent | None:
    """Refuse a segment that is damaged or belongs to another store; a crashed writer's unfinished tail at the end
    of the last, open segment is dropped (returned as an event) unless a writer is still alive."""
    file = folder / seg.name
    if scan.store_uuid is not None and scan.store_uuid != store_uuid:
        raise StoreCorruptError(f"{file}: belongs to store {scan.store_uuid}, but {MANIFEST} is that of store "
                                f"{store_uuid}; run `driftmap recover {folder}`", path=file, offset=None)
    if seg.state == "closed":
        if seg.bytes is not None and scan.size != seg.bytes:
            raise StoreCorruptError(
                f"{file}: closed segment is {scan.size} bytes, the manifest says {seg.bytes} "
                f"(truncated or appended to at offset {min(scan.size, seg.bytes)}); run `driftmap recover {folder}`",
                path=file, offset=min(scan.size, seg.bytes))
        if scan.problem or not scan.complete:
            raise StoreCorruptError(
                f"{file}: damaged at offset {scan.problem_offset}: {scan.problem or 'no end of data'}; "
                f"run `driftmap recover {folder}`", path=file, offset=scan.problem_offset)
    elif scan.problem and not last:
        raise StoreCorruptError(f"{file}: damaged at offset {scan.problem_offset}: {scan.problem}; run "
                                f"`driftmap recover {folder}`", path=file, offset=scan.problem_offset)
    elif scan.problem and not live_writer:
        dropped = scan.size - scan.valid_bytes
        logger.warning("%s: the writer stopped mid-append; %d trailing bytes at offset %d are an unfinished "
                       "frame and are dropped (%s)", file, dropped, scan.valid_bytes, scan.problem)
        return RecoveryEvent(seg.name, "crashed writer: unfinished tail dropped", len(scan.frames), len(scan.revisions),
                             dropped, scan.problem)
    return None


def replay(folder: Path, ledger: PoseLedger, refs: dict[int, StoredFrameRef], scans: list[SegmentScan], *,
           strict: bool) -> tuple[DataLoss, set[int], set[int]]:
    """Add the scanned segments' frames and revisions to an empty ``ledger`` and ``refs``, in store order (a
    revision refers to frames and revisions stored before it).

    A revision that names frames no segment holds is read without their poses, and a gap before a revision's
    id is filled with stand-ins, as far as the store's ``data_lost`` events declare those frames and revisions
    lost. Anything undeclared raises :class:`StoreCorruptError` (``strict``) or is treated the same way and
    returned (``recover`` declares it). Returns the loss, the undeclared frame ids and revision ids.
    """
    run = _Replay(folder, ledger, refs, scans, strict)
    for scan in scans:
        run.fill_tail(scan)
        added = 0  # frames and revisions in store order: a revision's frames are those stored before it
        offsets = [ref.payload_offset for ref in scan.frames]
        for rev_json, after in zip(scan.revisions, scan.revision_after_offset, strict=True):
            before = max(added, bisect.bisect_right(offsets, after))
            run.add_frames(scan, added, before)
            added = before
            run.add_revision(scan, rev_json)
        run.add_frames(scan, added, len(scan.frames))
    lost_frames = sorted(f for f in run.named_lost | run.declared_frames if f not in ledger)
    return DataLoss(tuple(lost_frames), tuple(run.stand_ins), run.trimmed, run.orphaned), run.new_frames, run.new_revisions


class _Replay:
    """The state of one :func:`replay`: what the ``data_lost`` events declare, and what was found lost so far."""

    def __init__(self, folder: Path, ledger: PoseLedger, refs: dict[int, StoredFrameRef], scans: list[SegmentScan],
                 strict: bool) -> None:
        self.folder, self.ledger, self.refs, self.strict = folder, ledger, refs, strict
        self.fix = f"; run `driftmap recover {folder}`"
        self.declared_frames: set[int] = set()
        self.declared_revisions: set[int] = set()
        for scan in scans:
            frames, revisions = declared_ids(scan)
            self.declared_frames |= frames
            self.declared_revisions |= revisions
        self.new_frames: set[int] = set()
        self.new_revisions: set[int] = set()
        self.named_lost: set[int] = set()
        self.stand_ins: list[int] = []
        self.trimmed: dict[int, tuple[int, ...]] = {}
        self.orphaned: dict[int, int] = {}

    def add_frames(self, scan: SegmentScan, start: int, stop: int) -> None:
        for ref in scan.frames[start:stop]:
            if ref.frame_id in self.refs:
                raise StoreCorruptError(f"{scan.path}: frame {ref.frame_id} stored twice", path=scan.path,
                                        offset=ref.payload_offset)
            try:
                self.ledger.add_frame(ref.frame_id, int(ref.info["stamp_ns"]),
                                      np.asarray(ref.info["pose"]["T_world_sensor"], dtype=np.float64).reshape(4, 4),
                                      ref.info["pose"].get("source"))
            except (StoreError, GeometryError, ValueError, TypeError, KeyError) as exc:
                raise StoreCorruptError(f"{scan.path}: frame {ref.frame_id}: damaged metadata ({exc}){self.fix}",
                                        path=scan.path, offset=ref.payload_offset) from exc
            self.refs[ref.frame_id] = ref

    def add_revision(self, scan: SegmentScan, rev_json: dict[str, Any]) -> None:
        try:
            rev = Revision.from_json(rev_json)
        except StoreError as exc:
            raise StoreCorruptError(f"{scan.path}: {exc}", path=scan.path, offset=None) from exc
        rid, head = rev.revision_id, self.ledger.head
        if rid <= head:
            raise StoreCorruptError(f"{scan.path}: revision {rid} is stored again after revision {head}",
                                    path=scan.path, offset=None)
        self.fill_gap(scan, rev, head)
        named = rev.changed_frame_ids if rev.frames is None else rev.frames  # its frames hold the changed ones
        absent = named[~np.isin(named, self.ledger.frame_ids)].tolist()
        if absent:
            undeclared = [f for f in absent if f not in self.declared_frames]
            if undeclared and self.strict:
                raise StoreCorruptError(
                    f"{scan.path}: revision {rid} holds poses of frames {preview(undeclared)}, which no segment "
                    f"of the store holds (lost with a damaged or missing segment?){self.fix}", path=scan.path, offset=None)
            self.new_frames.update(undeclared)
            self.named_lost.update(absent)
            if (posed := [f for f in absent if f in rev.set_directly or f in rev.propagated]):
                self.trimmed[rid] = tuple(posed)  # poses lost (a lost frame it only counted among its frames: no pose)
            rev = without_frames(rev, absent)
        if rev.parent_id in self.stand_ins:
            self.orphaned[rid] = int(rev.parent_id)
        try:
            self.ledger.commit(rev)
        except StoreError as exc:
            raise StoreCorruptError(f"{scan.path}: {exc}{self.fix}", path=scan.path, offset=None) from exc

    def fill_gap(self, scan: SegmentScan, rev: Revision, head: int) -> None:
        """Put stand-ins in the place of the revisions between ``head`` and ``rev`` (their records are lost)."""
        self._stand_ins(scan, range(head + 1, rev.revision_id), rev.created_ns,
                        f"revision {rev.revision_id} follows revision {head}")

    def fill_tail(self, scan: SegmentScan) -> None:
        """Put stand-ins in the place of the revisions that ``scan``'s ``data_lost`` events declare lost after the
        last revision read (records cut off the end of a segment, which no later revision shows were there:
        hostile trial 18 B8), in store order: where recovery declared them."""
        for event in scan.data_lost:
            revisions = lost_ids(event, scan.path)[1]
            last = max(revisions, default=-1)
            if last > self.ledger.head:
                made = event.get("recovered_ns")
                made = made if isinstance(made, int) and not isinstance(made, bool) and made >= 0 else 0
                self._stand_ins(scan, range(self.ledger.head + 1, last + 1), made,
                                f"its {EVENT_DATA_LOST} record declares revision {last} lost after revision "
                                f"{self.ledger.head}")

    def _stand_ins(self, scan: SegmentScan, gap: range, created_ns: int, where: str) -> None:
        """Stand-ins for the revisions ``gap`` (their records are lost), each placing the frames its predecessor
        places (hostile trial 18 W7: not every frame stored before it, which showed frames its predecessor leaves
        out at poses no revision gave them)."""
        undeclared = [r for r in gap if r not in self.declared_revisions]
        if undeclared and self.strict:
            raise StoreCorruptError(
                f"{scan.path}: {where}: no segment holds revisions {preview(undeclared)} (lost with a damaged or "
                f"missing segment?){self.fix}", path=scan.path, offset=None)
        self.new_revisions.update(undeclared)
        for r in gap:
            # created_ns: that of the revision after the gap, or of the recovery (the lost one was made no later)
            self.ledger.commit(Revision(r, r - 1, PoseSource.NONE, created_ns,
                                        f"[recovery: stand-in for lost revision {r}, with the poses of revision {r - 1}]",
                                        frames=self.ledger.members(r - 1, later=False)))
            self.stand_ins.append(r)
