"""How a store reports damage: :class:`StoreCorruptError` (a file is truncated or damaged), :class:`DataLoss`
(what damage took from the frames and revisions, as ``recover`` declared it) and :class:`RecoveryEvent` (what
opening or recovering a store dropped or repaired)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from driftmap.errors import StoreCorruptError as StoreCorruptError  # importable here as before
from driftmap.store.revision import Revision
from driftmap.store.segment_format import EVENT_DATA_LOST
from driftmap.store.segment_scan import SegmentScan
from driftmap.store.values import preview


@dataclass(frozen=True)
class DataLoss:
    """What damage took from a store's frames and revisions (declared by ``recover``), and what it did to the
    revisions that survived.

    ``frame_ids``: the lost frames (named by a stored revision, held by no segment; a lost frame that nothing
    names cannot be identified once its bytes are gone). ``revision_ids``: the revisions whose record is gone; a
    stand-in without poses of its own (parent: the revision before it) holds each one's id. ``trimmed``: revision
    -> the lost frames whose poses it no longer holds (it keeps all its other poses). ``orphaned``: revision ->
    its lost parent (the frames it does not set now take the stand-in's poses, those of the revision before).
    """

    frame_ids: tuple[int, ...] = ()
    revision_ids: tuple[int, ...] = ()
    trimmed: Mapping[int, tuple[int, ...]] = field(default_factory=dict, hash=False)
    orphaned: Mapping[int, int] = field(default_factory=dict, hash=False)

    def __bool__(self) -> bool:
        return bool(self.frame_ids or self.revision_ids)

    def only(self, frame_ids: set[int], revision_ids: set[int]) -> DataLoss:
        """The part of this loss that concerns ``frame_ids`` and ``revision_ids``."""
        trimmed = {r: mine for r, lost in self.trimmed.items() if (mine := tuple(f for f in lost if f in frame_ids))}
        return DataLoss(tuple(f for f in self.frame_ids if f in frame_ids),
                        tuple(r for r in self.revision_ids if r in revision_ids), trimmed,
                        {r: p for r, p in self.orphaned.items() if p in revision_ids})

    def __str__(self) -> str:
        parts = []
        if self.frame_ids:
            parts.append(f"frames {preview(self.frame_ids)} are lost")
        parts += [f"revision {r} lost the poses of {preview(lost)}" for r, lost in sorted(self.trimmed.items())]
        if self.revision_ids:
            parts.append(f"the records of revisions {preview(self.revision_ids)} are lost (a stand-in with the poses of "
                         f"the revision before holds each one's place)")
        for r, p in sorted(self.orphaned.items()):
            base = p - 1
            while base in self.revision_ids:
                base -= 1
            parts.append(f"revision {r}: its parent {p} is lost, the frames it does not set take revision {base}'s poses")
        return "; ".join(parts) or "nothing lost"


@dataclass(frozen=True)
class RecoveryEvent:
    """What opening or recovering a store had to drop or repair.

    For a segment: the frames and revision records it kept and the bytes that were not carried over (an
    unfinished tail, damaged chunks). For ``store.json`` and for the ``data_lost`` record: the frames and
    revisions (revision 0 included, as ``driftmap revisions`` lists them) of the recovered store. ``loss``: the
    frames and revisions this recovery found lost (see :class:`DataLoss`).
    """

    segment: str
    action: str
    frames_kept: int
    revisions_kept: int
    dropped_bytes: int
    detail: str
    loss: DataLoss | None = None

    def __str__(self) -> str:
        text = f"{self.segment}: {self.action}: kept {self.frames_kept} frames and {self.revisions_kept} revisions"
        if self.dropped_bytes:
            text += f", dropped {self.dropped_bytes} bytes"
        if self.loss:
            text += f"; {self.loss}"
        return f"{text} ({self.detail})"


def without_frames(rev: Revision, lost: list[int]) -> Revision:
    """``rev`` without the poses of the lost frames (every other field and pose unchanged)."""
    gone = set(lost)
    note = f"{rev.note} " if rev.note else ""
    return Revision(rev.revision_id, rev.parent_id, rev.source, rev.created_ns,
                    f"{note}[recovery: poses of {len(gone)} lost frame(s) removed]",
                    {k: v for k, v in rev.set_directly.items() if k not in gone},
                    {k: v for k, v in rev.propagated.items() if k not in gone}, rev.restores,
                    {k: v for k, v in rev.covariances.items() if k not in gone},
                    None if rev.frames is None else rev.frames[~np.isin(rev.frames, list(gone))])


def held_ids(scan: SegmentScan) -> tuple[set[int], set[int]]:
    """The frame and revision ids a scanned segment accounts for: those it stores, and those its ``data_lost``
    events declare lost (a loss record's segment "holds" the loss: if it is damaged, the loss is declared again,
    hostile trial 19 B1)."""
    frames, revisions = stored_ids(scan)
    lost_frames, lost_revisions = declared_ids(scan)
    return frames | lost_frames, revisions | lost_revisions


def stored_ids(scan: SegmentScan) -> tuple[set[int], set[int]]:
    """The frame and revision ids a scanned segment stores."""
    return ({r.frame_id for r in scan.frames},
            {rid for r in scan.revisions if isinstance(rid := r.get("revision_id"), int) and not isinstance(rid, bool)})


def declared_ids(scan: SegmentScan) -> tuple[set[int], set[int]]:
    """The frame and revision ids a scanned segment's ``data_lost`` events declare lost."""
    frames: set[int] = set()
    revisions: set[int] = set()
    for event in scan.data_lost:
        lost_frames, lost_revisions = lost_ids(event, scan.path)
        frames |= lost_frames
        revisions |= lost_revisions
    return frames, revisions


def unaccounted(recorded: list[tuple[set[int], set[int]] | None],
                scans: list[SegmentScan | None]) -> list[tuple[set[int], set[int]]]:
    """Per segment (in store order; ``recorded``: the ids its manifest entry records, ``scans``: what it holds now,
    None when missing), the recorded frame and revision ids that no segment stores and no ``data_lost`` event
    written with or after it declares lost: a declaration covers only the copies stored before it, so a frame lost, stored
    again and lost again is a new loss (hostile trial 19 B5)."""
    stored = [stored_ids(s) if s is not None else (set(), set()) for s in scans]
    declared = [declared_ids(s) if s is not None else (set(), set()) for s in scans]
    all_frames = set().union(*(f for f, _ in stored))
    all_revisions = set().union(*(r for _, r in stored))
    out = []
    later: tuple[set[int], set[int]] = (set(), set())  # declared in the segments after this one
    for k in range(len(scans) - 1, -1, -1):
        later = (later[0] | declared[k][0], later[1] | declared[k][1])  # a loss record accounts for its own ids
        rec = recorded[k]
        out.append((set(), set()) if rec is None else (rec[0] - all_frames - later[0], rec[1] - all_revisions - later[1]))
    return out[::-1]


def lost_ids(event: dict[str, Any], file: Path) -> tuple[set[int], set[int]]:
    """The frame and revision ids a ``data_lost`` event declares lost."""
    ids = []
    for key in ("frame_ids", "revision_ids"):
        value = event.get(key)
        if not isinstance(value, list) or any(isinstance(i, bool) or not isinstance(i, int) for i in value):
            raise StoreCorruptError(f"{file}: malformed {EVENT_DATA_LOST} record ({key} must be a list of integers)",
                                    path=file, offset=None)
        ids.append(set(value))
    return ids[0], ids[1]
