"""A merged store whose merge revision was lost to damage, or whose head restored revision 0: which sessions a
revision shows at their own, unmerged poses (hostile trials 19 W6, 21 W6 and 26 W1).

A merged store's revision 0 holds each session in its own world frame; the merge revision (1, and each append's)
places them in session 0's. When damage takes a merge revision, the stand-in that keeps its place holds the poses of
the revision before it, so every revision on top of it shows session ``k`` at its own origin: its map laid over
session 0's without alignment (2.1 m apart in trial 19), which ``diagnose`` reads as misaligned seams and
``decide`` as obstacles where there are none. A later revision that restores revision 0's poses (``rollback --to
0``) shows the same and is reported alike (with the merge revision that restores the merge). Revision 0 itself shows
the sessions unmerged by design and is not reported. The store layer answers the question so that every reader
(export, diagnose, decide, merge --append) asks the same one."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from driftmap.store.layout import MERGE_SUMMARY_FILE, SESSION_ID_STRIDE
from driftmap.store.merge_records import recorded_merge_revisions_in

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

__all__ = ["UnmergedSessions", "missing_merge_records", "unmerged_sessions"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class UnmergedSessions:
    """``sessions`` (never 0) that ``revision`` shows at their revision-0 poses because the merge revisions
    ``lost_merges`` were lost to damage."""

    revision: int
    lost_merges: tuple[int, ...]
    sessions: tuple[int, ...]
    merge_revisions: tuple[int, ...] = ()
    """the merge revisions the store still holds (with no lost merge: the revision restored revision 0's poses)"""

    def frame_mask(self, frame_ids: np.ndarray) -> np.ndarray:
        """Which of ``frame_ids`` belong to the unmerged sessions."""
        return np.isin(np.asarray(frame_ids, dtype=np.int64) // SESSION_ID_STRIDE, self.sessions)

    def __str__(self) -> str:
        which = ", ".join(map(str, self.sessions))
        if not self.lost_merges:  # a rollback to revision 0 (or a correction that restored its poses)
            back = (f": `driftmap rollback STORE --to {max(self.merge_revisions)}` restores the merge"
                    if self.merge_revisions else "")
            return (f"revision {self.revision} holds revision 0's poses for session {which} (each session in its own "
                    f"world frame), not aligned with session 0 as the merge placed "
                    f"{'it' if len(self.sessions) == 1 else 'them'}, so the map lays the sessions over each other "
                    f"misaligned{back}")
        return (f"revision {', '.join(map(str, self.lost_merges))}, the merge that placed the sessions in one world "
                f"frame, was lost to damage: revision {self.revision} shows session {which} at "
                f"{'its' if len(self.sessions) == 1 else 'their'} own poses (revision 0, each session in its own world "
                f"frame), not aligned with session 0, so the map lays them over each other misaligned. Export one "
                f"session at a time (export --trajectory --session K), or merge the session stores again into a new "
                f"store ({MERGE_SUMMARY_FILE} names them)")


def _merge_revisions(store: FrameStore) -> set[int]:
    """Revision 1 (the merge's own) and each recorded append's revision."""
    try:
        return recorded_merge_revisions_in(json.loads((store.path / MERGE_SUMMARY_FILE).read_text()))
    except (OSError, ValueError, TypeError, KeyError):
        logger.warning("%s: %s is unreadable; taking revision 1 as the only merge revision", store.path,
                       MERGE_SUMMARY_FILE)
        return {1}  # revision 1 is the merge's own, whatever the summary says


def unmerged_sessions(store: FrameStore, revision: int | None = None) -> UnmergedSessions | None:
    """The sessions other than 0 whose every frame ``revision`` (default: the head) places sits at its revision-0
    pose, on a merged store: because damage took a merge revision, or because the revision restored revision 0's
    poses (``rollback --to 0``; hostile trial 26 W1); None when none does, or for revision 0 (unmerged by
    design)."""
    rev = store.head if revision is None else int(revision)
    if rev == 0 or not (store.path / MERGE_SUMMARY_FILE).is_file():
        return None
    lost = set(store.loss.revision_ids)
    merges = _merge_revisions(store)
    lost_merges = sorted(merges & lost)
    held = {r.revision_id for r in store.revisions}
    ids = np.asarray(store.frame_ids, dtype=np.int64)
    placed = np.isin(ids, store.members(rev))
    at_own = placed & np.all(store.poses(rev) == store.poses(0), axis=(1, 2))
    session = ids // SESSION_ID_STRIDE
    unmerged = tuple(int(k) for k in np.unique(session[placed])
                     if k != 0 and at_own[session == k].sum() == placed[session == k].sum())
    if unmerged and not lost_merges:  # a restored revision 0: only the sessions a merge revision had placed (the
        # frames of an interrupted append sit at their own poses until it is finished: not a rollback's doing)
        aligned: set[int] = set()
        for m in merges & held:
            moved = np.isin(ids, store.members(m)) & ~np.all(store.poses(m) == store.poses(0), axis=(1, 2))
            aligned |= {int(k) for k in np.unique(session[moved])}
        unmerged = tuple(k for k in unmerged if k in aligned)
    if not unmerged:
        return None
    return UnmergedSessions(rev, tuple(lost_merges), unmerged, tuple(sorted(r for r in merges if r in held and r != rev)))


def missing_merge_records(store: FrameStore) -> str | None:
    """What ``merge_summary.json`` records that the store neither holds nor declares lost, in words; None when
    nothing is missing (or the store is no merge's). Hostile trial 22 W4: a merged store whose last segment and its
    ``store.json`` entry were both gone (a ``store.json`` older than the last append) read as intact, session 2 and
    revision 2 gone without a word, while the summary records both. Recorded: every connected session's frame
    count, the merge's revision 1 and each append's revision."""
    path = store.path / MERGE_SUMMARY_FILE
    if not path.is_file():
        return None
    try:
        summary = json.loads(path.read_text())
        sessions = [(int(s["session"]), int(s["n_frames"]), str(s.get("store", "?")))
                    for s in summary.get("sessions", []) if isinstance(s, dict) and s.get("connected")]
        revisions = recorded_merge_revisions_in(summary)
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return None  # an unreadable summary is reported where it is read (_merge_revisions)
    ids = np.asarray(store.frame_ids, dtype=np.int64)
    held = dict(zip(*np.unique(ids // SESSION_ID_STRIDE, return_counts=True), strict=True))
    lost_ids = np.asarray(store.loss.frame_ids, dtype=np.int64)
    lost = dict(zip(*np.unique(lost_ids // SESSION_ID_STRIDE, return_counts=True), strict=True))
    parts = []
    for k, n, source in sessions:
        have = int(held.get(k, 0)) + int(lost.get(k, 0))
        if have < n:
            parts.append(f"session {k} ({n} frames from {source}): "
                         + ("none of them" if have == 0 else f"{n - have} of them"))
    present = {r.revision_id for r in store.revisions} | set(store.loss.revision_ids)
    gone = sorted(revisions - present)
    if gone:
        parts.append(f"revision {', '.join(map(str, gone))} (the merge's or an append's)")
    if not parts:
        return None
    return (f"{MERGE_SUMMARY_FILE} records {'; '.join(parts)}, which the store neither holds nor declares lost: "
            f"a segment and its store.json entry are gone (a store.json older than the last append?). Restore the "
            f"store from a backup, or merge the session stores again into a new store")
