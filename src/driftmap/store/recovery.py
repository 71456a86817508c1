"""Recovery: salvaging every intact frame and revision of a damaged store (``FrameStore.recover``, ``driftmap
recover``), and rewriting the segment a crashed writer left open when the next writer opens the store.

Every step is a complete file written beside the old one and renamed into place, with the manifest written after
it, so an interrupted recovery is finished by running it again. See :mod:`driftmap.store.frame_store` ("Losses")
for what recovery declares about the frames and revisions that damage took.
"""

from __future__ import annotations

import contextlib
import json
import logging
import mmap
import os
import shutil
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from driftmap.errors import DriftmapError, StoreError
from driftmap.store.chunk_scan import StoredFrameRef
from driftmap.store.damage import RecoveryEvent, StoreCorruptError, held_ids, unaccounted
from driftmap.store.frame_codec import frame_from_info, unpack_attributes
from driftmap.store.guards import RECOVER_HINT, store_io_error
from driftmap.store.layout import (
    BEFORE_DAMAGE_SUFFIX,
    DAMAGED_SUFFIX,
    MANIFEST,
    MERGE_SUMMARY_FILE,
    RECOVERING_SUFFIX,
    TMP_SUFFIX,
    dropped_tail_name,
    segment_name,
)
from driftmap.store.ledger import PoseLedger
from driftmap.store.lock import acquire_writer_lock, release_writer_lock, writer_alive
from driftmap.store.manifest import (
    SegmentEntry,
    atomic_write_json,
    carry_records,
    entries_of,
    fsync_dir,
    loose_record_ok,
    lost_segments,
    manifest_from_segments,
    read_manifest,
    size_or_none,
    unlisted_segments,
    write_manifest,
)
from driftmap.store.merge_records import lost_append_revisions
from driftmap.store.opening import load_segments, replay
from driftmap.store.reading import decode_frame
from driftmap.store.renamed_segments import restore_segment_names
from driftmap.store.segment import SegmentWriter
from driftmap.store.segment_format import EVENT_DATA_LOST
from driftmap.store.segment_scan import SegmentScan, iter_payload_bytes, read_store_uuid, scan_segment
from driftmap.store.values import preview
from driftmap.store.writing import next_segment_index, start_segment

logger = logging.getLogger(__name__)


def recover_store(path: Path) -> list[RecoveryEvent]:
    """:meth:`FrameStore.recover <driftmap.store.frame_store.FrameStore.recover>` (an ``OSError`` of a step names
    the file it was working on)."""
    manifest, rebuilt_because = _manifest_to_recover(path)
    n_rebuilt_from = len(manifest["segments"])  # (the recovery adds any segment it writes to the list)
    run = _Recovery(path, manifest)
    lock = acquire_writer_lock(path)
    try:
        if rebuilt_because is not None:
            run.replace_manifest()
        run.events += restore_segment_names(path, run.segments)  # (trial 29 W1) before any is judged damaged
        for index, seg in enumerate(run.segments):
            run.check_segment(index, seg)
        run.forget_missing_segments()
        run.declare_loss()
    except OSError as exc:
        raise store_io_error(exc, exc.filename or run.current, "recovering the store", path, RECOVER_HINT) from exc
    finally:
        release_writer_lock(lock)
    n_frames, n_revisions = _reopened(path)
    if rebuilt_because is not None:
        run.events.insert(0, RecoveryEvent(MANIFEST, f"rebuilt from {n_rebuilt_from} segments{run.kept_manifest}",
                                           n_frames, n_revisions, 0, rebuilt_because))
    for event in run.events:
        logger.info("recover %s: %s", path, event)  # returned to the caller, who reports them
    return run.events


def _manifest_to_recover(path: Path) -> tuple[dict[str, Any], str | None]:
    """The manifest recovery works from, and why it was rebuilt from the segments (None: it was not): it is
    unreadable, does not list every segment file, or names another store than its segments."""
    try:
        manifest = read_manifest(path, hint=False)
    except StoreCorruptError as exc:
        because = str(exc)
        return _rebuilt(path, manifest_from_segments(path, because)), because
    copies = _damaged_copies(path / MANIFEST)
    if manifest.get("rebuilt_because") and copies:
        # rebuilt by a recovery that may have stopped before it declared the loss: the damaged manifest's records of
        # segments the rebuilt one holds none for (a cut segment's, not written while it was open: trial 23 B2)
        carried = carry_records(copies[-1], manifest, only_missing=True)
        if carried:
            logger.info("%s: the records of what %s held are taken from %s", path, preview(carried), copies[-1].name)
    segments = entries_of(manifest)
    unlisted = unlisted_segments(path, segments)
    strangers = [s.name for s in segments if (path / s.name).exists()
                 and read_store_uuid(path / s.name) not in (None, manifest["store_uuid"])]
    if not (unlisted or strangers):
        return manifest, None
    because = (f"{path / MANIFEST}: " + (f"does not list {preview(unlisted)}" if unlisted else
               f"names store {manifest['store_uuid']}, its segments {preview(strangers)} another"))
    return _rebuilt(path, manifest_from_segments(path, because, lost_segments(manifest))), because


def _rebuilt(path: Path, manifest: dict[str, Any]) -> dict[str, Any]:
    """A manifest rebuilt from the segments, with what the one it replaces recorded of each segment's contents."""
    carried = carry_records(path / MANIFEST, manifest)
    if carried:
        logger.info("%s: the records of what %s held are taken from the manifest it replaces", path, preview(carried))
    return manifest


def _reopened(path: Path) -> tuple[int, int]:
    """The frames and revisions of the recovered store, read as opening it reads them (a StoreCorruptError if it
    still does not open)."""
    try:
        manifest = read_manifest(path)
        ledger = PoseLedger()
        load_segments(path, manifest["store_uuid"], entries_of(manifest), ledger, {}, verify=False,
                      live_writer=writer_alive(path))
    except StoreError as exc:
        raise StoreCorruptError(f"{path}: recovery could not make the store readable: {exc}",
                                path=path, offset=getattr(exc, "offset", None)) from exc
    return ledger.n_frames, len(ledger.revisions)


class _Recovery:
    """One run of :func:`recover_store`: the manifest and segments it rewrites, what it found and did, and the file
    it is working on (named by an ``OSError``)."""

    def __init__(self, path: Path, manifest: dict[str, Any]) -> None:
        self.path, self.manifest = path, manifest
        self.segments = entries_of(manifest)
        self.events: list[RecoveryEvent] = []
        self.damage: list[str] = []
        self.scans: list[SegmentScan] = []
        self.known_frames: set[int] = set()
        self.cut_frames: set[int] = set()  # recorded in a segment's manifest entry, gone from the segment
        self.cut_revisions: set[int] = set()
        # segment -> what its record names that it no longer holds: the cause a loss record gives when the segment
        # itself reads healthy (a recovery stopped after rewriting it; trial 19 W4)
        self.cut_causes: dict[str, str] = {}
        self.damaged_segments: set[str] = set()  # found damaged by this recovery (their cause is in ``damage``)
        self.held: list[tuple[SegmentEntry, SegmentScan | None]] = []  # each checked segment, as it is now
        self.current = path / MANIFEST
        self.kept_manifest = ""

    def write_manifest(self) -> None:
        write_manifest(self.path, self.manifest, self.segments)

    def replace_manifest(self) -> None:
        """Write the rebuilt manifest; the damaged one is kept as ``store.json.damaged``."""
        file = self.path / MANIFEST
        if file.exists():
            damaged_manifest = free_name(self.path / (MANIFEST + DAMAGED_SUFFIX))
            os.replace(file, damaged_manifest)
            self.kept_manifest = f" (damaged original kept as {damaged_manifest.name})"
        self.write_manifest()

    def check_segment(self, index: int, seg: SegmentEntry) -> None:
        """Rewrite segment ``index`` if it is damaged, was left open, or holds frames an earlier one holds."""
        file = self.current = self.path / seg.name
        if not file.exists():
            self.events.append(RecoveryEvent(seg.name, "missing segment removed from the manifest", 0, 0, 0,
                                             "file not found: its frames and revisions are lost"))
            self.damage.append(f"{seg.name} missing")
            self.damaged_segments.add(seg.name)
            seg.state = "missing"
            if seg.rewritten_from is None:
                seg.rewritten_from = seg.bytes
            self.held.append((seg, None))
            return
        scan = scan_segment(file, verify=True, stop_on_error=False)
        twice = [r.frame_id for r in scan.frames if r.frame_id in self.known_frames]
        unreadable = unreadable_frames(scan)
        healthy = (seg.state == "closed" and scan.complete and not scan.problem and not scan.damaged_chunks
                   and scan.size == seg.bytes and not twice and not unreadable)
        if not healthy:
            if seg.rewritten_from is None:  # (an unfinished recovery's, kept: the size before the damage it found)
                seg.rewritten_from = seg.bytes if seg.bytes is not None else scan.size
            _note_before_damage(file, seg)
            copies = _damaged_copies(file)
            if (copies and seg.state == "closed" and scan.complete and not scan.problem and not scan.damaged_chunks
                    and not twice and not unreadable):
                self.finish_rewrite(seg, scan, copies[-1])
            else:
                scan = self.rewrite_segment(index, seg, scan, twice, unreadable)
        # compared with the records once every segment is checked, and the records updated only once the loss is
        # declared: a recovery stopped in between (disk full) leaves the old records, so the next one still finds
        # what was cut off
        self.held.append((seg, scan))
        self.known_frames.update(r.frame_id for r in scan.frames)
        self.scans.append(scan)

    def note_cuts(self) -> None:
        """Note the frames and revisions the manifest records in a segment that no segment holds or declared lost
        any more. A record that does not fit the store is not used (warned about): more frames than the store's
        median frame size fits in the segment's recorded size, or revision ids past the store's last revision by
        more than the records name (hostile trial 19 B3, B4)."""
        scans = [scan for _, scan in self.held]
        every = [held_ids(scan) for scan in scans if scan is not None]
        last = max(set().union(*(r for _, r in every)), default=0)
        beyond = {r for seg, _ in self.held if seg.revisions is not None for r in seg.revisions if r > last}
        sizes = [ref.n_points * ref.point_stride for scan in self.scans for ref in scan.frames]
        frame_bytes = float(np.median(sizes)) if sizes else 0.0
        recorded: list[tuple[set[int], set[int]] | None] = []
        for seg, scan in self.held:
            before = _before_damage(self.path / seg.name)
            if (seg.frames is None or seg.revisions is None) and before.get("frames") is not None:
                seg.frames, seg.revisions = before["frames"], before["revisions"]  # the manifest's record is gone
            if seg.frames is None or seg.revisions is None:
                recorded.append(None)
                continue
            kept = _damaged_copies(self.path / seg.name)
            if seg.rewritten_from is None and scan is not None and not kept:
                # an intact segment (never found damaged): what it holds is what it held, and a record naming more is
                # itself damaged (a bit flip in store.json: trial 20 B2); record_held writes the true one. A segment
                # an earlier recovery rewrote (its damaged copy kept beside it) is not: a recovery stopped before its
                # declaration by older code, or whose rewritten_from_bytes was lost, left it so (trial 21 B2)
                if seg.recorded_ids() != held_ids(scan):
                    logger.warning("%s: its manifest entry's record of what it holds does not match the intact "
                                   "segment (the manifest was damaged or edited); it is corrected, nothing is lost",
                                   self.path / seg.name)
                recorded.append(None)
                continue
            n_recorded = sum(b - a + 1 for a, b in seg.frames)
            implausible = [r for r in seg.revisions if r > last + len(beyond)]
            # what the segment was before the damage, not what survived (trial 20 B1)
            # (the note a recovery left beside the copy: a lost ``rewritten_from_bytes`` left only the copy's size,
            # a lower bound that made a cut of over 3/4 read as implausible: hostile trial 22 B2)
            size = max([seg.rewritten_from or 0, before.get("bytes") or 0, *(_size(copy) for copy in kept)])
            if implausible or (not seg.declares_loss and n_recorded * frame_bytes > 4 * size):
                logger.warning("%s: its manifest entry's record of what it holds does not fit the store (%s); it is "
                               "not used", self.path / seg.name,
                               f"revisions {preview(implausible)} past the last one, {last}" if implausible else
                               f"{n_recorded} frames of about {frame_bytes:.0f} bytes in {size} bytes")
                recorded.append(None)
                continue
            recorded.append(seg.recorded_ids())
        for (seg, _), (cut_frames, cut_revisions) in zip(self.held, unaccounted(recorded, scans), strict=True):
            if cut_frames or cut_revisions:
                logger.warning("%s: its manifest entry records frames %s and revisions %s that no segment holds now",
                               self.path / seg.name, preview(sorted(cut_frames)) or "-",
                               preview(sorted(cut_revisions)) or "-")
                self.cut_causes[seg.name] = _cut_cause(self.path / seg.name, cut_frames, cut_revisions)
            self.cut_frames |= cut_frames
            self.cut_revisions |= cut_revisions

    def note_merge_records(self) -> None:
        """Note the append revisions ``merge_summary.json`` records that were lost with their segment (hostile trial
        22 W4: a segment gone with its manifest entry, a ``store.json`` older than the last append, left nothing else
        that names them, and a later revision took the lost id), as far as the store's own contents bear the summary
        out (:func:`lost_append_revisions`). Their frames' ids the summary does not record: ``missing_merge_records``
        names the sessions short of frames."""
        every = [held_ids(scan) for _, scan in self.held if scan is not None]
        frames = set().union(*(f for f, _ in every)) | self.cut_frames
        held = set().union(*(r for _, r in every)) | self.cut_revisions
        gone = lost_append_revisions(self.path, frames, held)
        if gone:
            logger.warning("%s: %s records revisions %s that no segment holds", self.path, MERGE_SUMMARY_FILE,
                           preview(sorted(gone)))
            self.cut_revisions |= gone
            self.cut_causes[MERGE_SUMMARY_FILE] = (
                f"{MERGE_SUMMARY_FILE} records revision {', '.join(map(str, sorted(gone)))} (an append's) with its "
                f"session's frames, which no segment holds: a segment gone with its {MANIFEST} entry")

    def rewrite_segment(self, index: int, seg: SegmentEntry, scan: SegmentScan, twice: list[int],
                        unreadable: list[tuple[int, str]]) -> SegmentScan:
        """Rewrite a segment from its intact chunks (the damaged file is kept beside it); returns its new scan."""
        file = self.path / seg.name
        was_open = seg.state != "closed"
        dropped = {f for f, _ in unreadable}  # never copied: a fresh CRC would make them look intact
        scan.frames = [r for r in scan.frames if r.frame_id not in self.known_frames and r.frame_id not in dropped]
        tmp = self.current = file.with_name(file.name + RECOVERING_SUFFIX)
        tmp.unlink(missing_ok=True)
        writer = SegmentWriter(tmp, index, self.manifest["store_uuid"], fsync=True)
        try:
            skipped = unreadable + copy_scan_into(scan, writer)
            for event in scan.data_lost:
                writer.append_event(event, int(event.get("recovered_ns", 0)))
            size = writer.close()
        except BaseException:
            writer.abandon()
            raise
        if skipped:
            lost = {f for f, _ in skipped}
            scan.frames = [r for r in scan.frames if r.frame_id not in lost]
        self.current = file
        damaged = free_name(file.with_name(file.name + DAMAGED_SUFFIX))
        keep_copy(file, damaged)
        os.replace(tmp, file)  # atomic: the segment is never missing, whenever recovery stops
        fsync_dir(self.path)
        seg.state, seg.bytes = "closed", size
        self.write_manifest()
        detail = _damage_detail(scan, twice, skipped, was_open)
        self.damage.append(f"{seg.name}: {detail}")
        self.damaged_segments.add(seg.name)
        tail = 0 if scan.complete else scan.size - scan.valid_bytes
        self.events.append(RecoveryEvent(seg.name, f"rewritten (damaged original kept as {damaged.name})",
                                         len(scan.frames), len(scan.revisions), tail + scan.damaged_bytes, detail))
        return scan_segment(file, verify=False)  # the frames now live in the rewritten file

    def finish_rewrite(self, seg: SegmentEntry, scan: SegmentScan, copy: Path) -> None:
        """A segment that reads clean but not at its manifest size, beside a damaged copy: a recovery stopped
        between replacing it by its rewrite and writing the manifest. The rewrite stands (rewriting it again would
        name "size differs from the manifest" as the cause, hostile trial 21 W8); the cause is the damaged copy's."""
        copy_scan = scan_segment(copy, verify=True, stop_on_error=False)
        detail = _damage_detail(copy_scan, [], [], False)
        if detail == "size differs from the manifest":
            detail = f"damaged (kept as {copy.name})"
        seg.bytes = scan.size
        self.write_manifest()
        self.damage.append(f"{seg.name}: {detail}")
        self.damaged_segments.add(seg.name)
        self.events.append(RecoveryEvent(seg.name, f"rewritten by an earlier recovery that stopped before recording "
                                                   f"it (damaged original kept as {copy.name})",
                                         len(scan.frames), len(scan.revisions), 0, detail))

    def forget_missing_segments(self) -> None:
        """Take the missing segments off the manifest (recorded as ``lost_segments``)."""
        missing = [s.name for s in self.segments if s.state == "missing"]
        if missing:
            self.segments[:] = [s for s in self.segments if s.state != "missing"]
            self.manifest["lost_segments"] = lost_segments(self.manifest) + missing
            self.write_manifest()

    def declare_loss(self) -> None:
        """What the damage took from the revisions that survived: declared in a ``data_lost`` event of its own, in a
        new segment."""
        self.note_cuts()
        self.note_merge_records()
        new_frames, new_revisions = replay(self.path, PoseLedger(), {}, self.scans, strict=False)[1:]
        new_frames |= self.cut_frames  # (not declared by a loss record written after the copy that was lost)
        new_revisions |= self.cut_revisions
        if new_frames or new_revisions:
            self.write_loss(new_frames, new_revisions)
        self.record_held()

    def record_held(self) -> None:
        """Record in the manifest what each checked segment holds now (after the loss it shows is declared)."""
        changed = False
        for seg, scan in self.held:
            frames, revisions = held_ids(scan) if scan is not None else (set(), set())
            declares = scan is not None and bool(scan.data_lost)
            if (seg.recorded_ids() != (frames, revisions) or seg.declares_loss != declares
                    or seg.rewritten_from is not None):
                seg.record_contents(frames, revisions)
                seg.declares_loss = declares
                seg.rewritten_from = None  # what the damage took is declared now
                changed = True
        if changed:
            self.write_manifest()

    def write_loss(self, new_frames: set[int], new_revisions: set[int]) -> None:
        """Declare the frames and revisions lost in a ``data_lost`` event, in a new segment of its own."""
        causes = self.damage + [cause for name, cause in self.cut_causes.items() if name not in self.damaged_segments]
        because = "; ".join(causes) or "stored revisions name frames or follow revisions that no segment holds"
        now = time.time_ns()
        self.current = self.path / segment_name(next_segment_index(self.path, self.manifest, self.segments))
        writer = start_segment(self.path, self.manifest, self.segments, fsync=True, what="appending")
        try:
            writer.append_event({"event": EVENT_DATA_LOST, "recovered_ns": now, "frame_ids": sorted(new_frames),
                                 "revision_ids": sorted(new_revisions), "because": because}, now)
        except BaseException:
            writer.abandon()
            raise
        self.segments[-1].state, self.segments[-1].bytes = "closed", writer.close()
        self.segments[-1].record_contents(new_frames, new_revisions)  # it accounts for the loss it declares
        self.segments[-1].declares_loss = True
        self.write_manifest()
        ledger = PoseLedger()  # the store as it reads now: stand-ins for the revisions declared lost
        loss = replay(self.path, ledger, {}, [*self.scans, scan_segment(self.current, verify=False)], strict=False)[0]
        self.events.append(RecoveryEvent(self.segments[-1].name, f"recorded the loss in a {EVENT_DATA_LOST} event",
                                         ledger.n_frames, len(ledger.revisions), 0, because,
                                         loss.only(new_frames, new_revisions)))


def _damaged_copies(file: Path) -> list[Path]:
    """The damaged copies recoveries kept of ``file`` (``NAME.damaged``, ``NAME.damaged.1`` ...), oldest first."""
    copies = [p for p in file.parent.glob(file.name + DAMAGED_SUFFIX + "*") if p.is_file()]
    return sorted(copies, key=lambda p: p.stat().st_mtime)


def _before_damage_file(file: Path) -> Path:
    return file.with_name(file.name + BEFORE_DAMAGE_SUFFIX)


def _note_before_damage(file: Path, seg: SegmentEntry) -> None:
    """Beside segment ``file``, found damaged: a note of its size before the damage and of the manifest's record of
    what it held (``NAME.before-damage.json``), written before the segment is rewritten and kept for good, as its
    damaged copy is. It is the evidence a recovery stopped before its declaration leaves when the manifest's
    ``rewritten_from_bytes`` (or its record) is lost as well (hostile trial 22 B2). A note already there stays
    unless this one's size is larger (a closed segment never grows; a rewrite shrinks it)."""
    note = _before_damage(file)
    size = seg.rewritten_from if seg.rewritten_from is not None else 0
    if note and (note.get("bytes") or 0) >= size:
        return
    record = ({"frames": seg.frames, "revisions": seg.revisions}
              if seg.frames is not None and seg.revisions is not None else {})
    atomic_write_json(_before_damage_file(file), {"segment": file.name, "bytes": size, **record,
                                                   "found_ns": time.time_ns()})


def _before_damage(file: Path) -> dict[str, Any]:
    """The note :func:`_note_before_damage` left beside ``file``, as far as it is well formed (``bytes``, and
    ``frames`` / ``revisions`` only as a well-formed record that fits that size); empty when there is none."""
    try:
        note = json.loads(_before_damage_file(file).read_bytes())
    except (OSError, ValueError, RecursionError):
        return {}
    if not isinstance(note, dict) or note.get("segment") != file.name:
        return {}
    size = size_or_none(note.get("bytes"))
    if size is None:
        return {}
    out: dict[str, Any] = {"bytes": size}
    if loose_record_ok(note):
        out["frames"], out["revisions"] = note["frames"], note["revisions"]
    return out


def _size(file: Path) -> int:
    try:
        return file.stat().st_size
    except OSError:
        return 0


def _cut_cause(file: Path, cut_frames: set[int], cut_revisions: set[int]) -> str:
    """Why frames and revisions are lost when ``file`` reads healthy but its manifest record names them."""
    named = [f"frames {preview(sorted(cut_frames))}" if cut_frames else "",
             f"revisions {preview(sorted(cut_revisions))}" if cut_revisions else ""]
    copies = _damaged_copies(file)
    kept = f"; the damaged file an earlier recovery rewrote is kept as {copies[-1].name}" if copies else ""
    return (f"{file.name}: its manifest entry records {' and '.join(n for n in named if n)}, which it no longer holds "
            f"(cut off its end or damaged{kept})")


def _damage_detail(scan: SegmentScan, twice: list[int], skipped: list[tuple[int, str]], was_open: bool) -> str:
    """What was wrong with a rewritten segment, for its recovery event."""
    problems = [f"{why} at offset {off}" for off, why in scan.damaged_chunks]
    if scan.problem:
        problems.append(f"{scan.problem} at offset {scan.problem_offset}")
    if twice:
        problems.append(f"frames {preview(twice)} are stored in an earlier segment too (the later copies were dropped)")
    problems += [f"frame {f}: {why}" for f, why in skipped]
    return "; ".join(problems) or ("segment was not closed" if was_open else "size differs from the manifest")


def recover_open_segments(path: Path, manifest: dict[str, Any], segments: list[SegmentEntry],
                          refs: dict[int, StoredFrameRef]) -> list[RecoveryEvent]:
    """Rewrite the segments a crashed writer left open (each scanned by opening) into clean, closed segments,
    updating ``refs`` to the rewritten files. Frames that cannot be read back are not what a crash leaves behind:
    they are never repaired behind the user's back (a StoreCorruptError asking for ``driftmap recover``)."""
    events = []
    for index, seg in enumerate(segments):
        if seg.state != "open":
            continue
        file = path / seg.name
        scan = seg.scan
        assert scan is not None
        bad = unreadable_frames(scan)
        if bad:
            raise StoreCorruptError(f"{file}: frames {preview(f for f, _ in bad)} cannot be read back ({bad[0][1]}); "
                                    f"run `driftmap recover {path}`", path=file, offset=None)
        tmp = file.with_name(file.name + RECOVERING_SUFFIX)
        tmp.unlink(missing_ok=True)
        writer = SegmentWriter(tmp, index, manifest["store_uuid"], fsync=True)
        try:
            copy_scan_into(scan, writer)
            size = writer.close()
        except BaseException:
            writer.abandon()
            tmp.unlink(missing_ok=True)
            raise
        if scan.valid_bytes < scan.size:
            with open(file, "rb") as src, open(path / dropped_tail_name(seg.name), "wb") as dst:
                src.seek(scan.valid_bytes)
                dst.write(src.read())
        os.replace(tmp, file)
        seg.state, seg.bytes = "closed", size
        seg.scan = scan_segment(file, verify=False)
        seg.record_contents(*held_ids(seg.scan))
        seg.declares_loss = bool(seg.scan.data_lost)
        refs.update({ref.frame_id: ref for ref in seg.scan.frames})
        write_manifest(path, manifest, segments)
        logger.info("%s: recovered %d frames and %d revisions into a closed segment", file, len(scan.frames), len(scan.revisions))
        events.append(RecoveryEvent(seg.name, "rewritten as a closed segment", len(scan.frames), len(scan.revisions),
                                    scan.size - scan.valid_bytes, scan.problem or "writer did not close the segment"))
    return events


def copy_scan_into(scan: SegmentScan, writer: SegmentWriter) -> list[tuple[int, str]]:
    """Copy the scanned frames (bit for bit) and revisions into ``writer``; returns (frame id, reason) of the
    frames whose stored metadata cannot be read back (they are not copied)."""
    skipped: list[tuple[int, str]] = []
    with open(scan.path, "rb") as fh:
        mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) if scan.size else None
        try:
            items: list[tuple[int, int, str, Any]] = [(r.payload_offset, 0, "frame", r) for r in scan.frames]
            for k, (rev, after) in enumerate(zip(scan.revisions, scan.revision_after_offset, strict=True)):
                items.append((after, 1 + k, "revision", rev))
            # the store order kept: frames in file order, each revision after the frames stored before it
            for _, _, kind, item in sorted(items, key=lambda x: (x[0], x[1])):
                if kind == "frame":
                    frame = decode_frame(item, mm)
                    if isinstance(frame, str):
                        logger.warning("%s: frame %d: %s: not copied", scan.path, item.frame_id, frame)
                        skipped.append((item.frame_id, frame))
                        continue
                    writer.append_frame(frame, check=False)  # as stored, bit for bit
                else:
                    writer.append_revision(item, int(item["created_ns"]))
        finally:
            if mm is not None:
                mm.close()
    return skipped


def unreadable_frames(scan: SegmentScan) -> list[tuple[int, str]]:
    """(frame id, reason) of the scanned frames that cannot be read back as stored: metadata that does not
    rebuild a :class:`Frame`, or a point payload whose CRC32 is not the one the metadata recorded. (Opening
    checks only what it needs and the chunk CRCs; this is the rest, run by ``recover``.)"""
    bad: list[tuple[int, str]] = []
    if not scan.frames:
        return bad
    with open(scan.path, "rb") as fh:
        mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    try:
        for ref in scan.frames:
            try:
                frame_from_info(ref.info, np.zeros((0, 3), np.float32),
                                unpack_attributes(np.zeros(0, np.uint8), 0, ref.point_stride, ref.info["points"]["fields"]))
            except (DriftmapError, KeyError, TypeError, ValueError, ArithmeticError, AttributeError) as exc:
                bad.append((ref.frame_id, f"unreadable metadata ({type(exc).__name__}: {exc})"))
                continue
            payload = iter_payload_bytes(ref, mm)
            problem = ("the point payload is cut short" if len(payload) != ref.n_points * ref.point_stride else
                       "the point payload's CRC32 is not the one its metadata recorded"
                       if zlib.crc32(payload) != ref.info["points"]["crc32"] else None)
            del payload
            if problem is not None:
                bad.append((ref.frame_id, problem))
    finally:
        with contextlib.suppress(BufferError):
            mm.close()
    return bad


def keep_copy(file: Path, copy: Path) -> None:
    """Keep ``file``'s bytes as ``copy`` (a hard link, else a copy) while ``file`` itself stays in place."""
    try:
        os.link(file, copy)
    except OSError:
        tmp = copy.with_name(copy.name + TMP_SUFFIX)
        shutil.copyfile(file, tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, copy)


def free_name(path: Path) -> Path:
    """``path``, or ``path.1``, ``path.2``, ... : the first that does not exist (never overwrite a kept file)."""
    candidate, n = path, 0
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.name}.{n}")
    return candidate
