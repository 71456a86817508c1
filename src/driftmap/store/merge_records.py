"""What a merged store's summary (``merge_summary.json``) records of the store's own revisions, read at the store
layer: the merge's revision 1 and each append's. ``recover`` declares lost the append revisions lost with their
segment (hostile trial 22 W4: :func:`lost_append_revisions`), and ``store/unmerged.py`` names the sessions a lost
merge revision leaves unmerged."""

from __future__ import annotations

import json
from pathlib import Path

from driftmap.store.layout import MERGE_SUMMARY_FILE, SESSION_ID_STRIDE

__all__ = ["lost_append_revisions", "recorded_merge_revisions_in"]


def recorded_merge_revisions_in(summary: object) -> set[int]:
    """Revision 1 and the append revisions a parsed merge summary records."""
    appends = summary.get("appends", []) if isinstance(summary, dict) else []
    return {1} | {int(a["revision_id"]) for a in appends if isinstance(a, dict) and a.get("revision_id")}


def lost_append_revisions(path: Path, held_frames: set[int], held_revisions: set[int]) -> set[int]:
    """The append revisions the merge summary in ``path`` records that the store lost with their segment, judged
    against what the store holds (``held_*``: stored or declared lost) so that a damaged or foreign summary never
    makes up a loss (hostile trial 23 B1: an edited ``revision_id`` made ``recover`` declare phantom revisions, a
    negative one left the store unreadable, 2,000,000 ran out of memory). An append's revision counts as lost only
    when all of this holds: the store is a merge's (it holds frames of a session other than 0 that the summary
    records); the id is an integer past both the append's ``previous_head`` and every revision the store holds, and
    within the number of recorded appends of the last held one; and the frames of a session the append connected
    are all gone as well (an append writes its frames and its revision into one segment)."""
    try:
        summary = json.loads((path / MERGE_SUMMARY_FILE).read_text())
    except (OSError, ValueError, RecursionError):
        return set()
    if not isinstance(summary, dict) or not isinstance(summary.get("appends"), list):
        return set()
    held_sessions = {f // SESSION_ID_STRIDE for f in held_frames}
    recorded = {s.get("session") for s in summary.get("sessions", []) if isinstance(s, dict)}
    if not (held_sessions - {0}) & recorded:
        return set()  # not this merged store's summary
    appends = [a for a in summary["appends"] if isinstance(a, dict)]
    last = max(held_revisions, default=0)
    lost = set()
    for append in appends:
        rid, before = append.get("revision_id"), append.get("previous_head")
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in (rid, before)):
            continue
        if not (0 <= before < rid and last < rid <= last + len(appends)):
            continue
        sessions = [s.get("session") for s in append.get("sessions", []) if isinstance(s, dict)
                    and s.get("connected") and isinstance(s.get("n_frames"), int) and s["n_frames"] > 0]
        if any(isinstance(k, int) and k > 0 and k not in held_sessions for k in sessions):
            lost.add(rid)
    return lost
