"""``driftmap merge MERGED NEW [NEW ...] --append``: new sessions appended in place to a merged store (issue 26).

The merged store (made by :func:`~driftmap.pipeline.merge.merge_stores`) gains the new sessions' frames and one new
pose revision; its older revisions stay (``rollback`` returns to the map before the append). The new stores are
opened read-only and never modified.

1. **Checks** (before anything is written): the first store is a merged store (``merge_summary.json`` and merged
   frames); every new store has frames, is no merged store, is not already a session of it (its store uuid), and has
   the merged store's sensor kind and intrinsics kind; no new store twice. The merged store is opened for appending
   (its writer lock is held for the whole append: no other writer meanwhile).
2. **Keyframes**: the existing sessions' on the merged store's revision 0 (each session's head poses as merged,
   the frames' points as stored: the keyframes the merge itself used), the new sessions' on their head revision,
   with the loop-closure settings and the keyframe range the merge recorded.
3. **Loops** between each new session and every existing one (and the new ones before it), found and verified as
   ``merge`` does (:func:`~driftmap.pipeline.merge_loops.find_pair_loops`). A new session connected to no existing
   one (directly or through another new one) is reported and nothing of it is appended; if none connects, nothing
   is written and the error says why.
4. **One pose graph** over every session: each session's odometry edges (the relative poses of its head as merged),
   the recorded loops between the existing sessions (their measurement and information as ``merge_summary.json``
   holds them; a store merged before they were recorded has its accepted loops verified again), the new loops;
   session 0's first keyframe fixed. The existing keyframes start at the store's head poses.
5. **Only what moves**: every frame's optimised pose (per session, the keyframes' correction propagated as ``merge``
   does); an existing frame that moves less than ``move_tolerance_m`` and turns less than ``move_tolerance_deg``
   keeps its head pose to the bit (the new revision does not name it, so the map view re-transforms only the moved
   frames). The new revision (source ``loop_closure``, note ``append of ...``) sets the moved frames and every new
   frame.
6. **Crash safety**: ``merge_summary.json`` records the append as in progress (``append_in_progress``) before the
   first frame is written; the frames and the revision go into one new segment of the store. A failure before the
   revision is stored takes that segment back (:meth:`~driftmap.store.frame_store.FrameStore.discard_session`) and
   restores the summary: the store is as it was. A process killed in that window leaves the new frames (no revision
   names them; the head is the map before the append) and the in-progress record: the next append refuses any other
   stores and, given the same ones again, skips the frames already stored and finishes it. The summary is written
   last (atomically), with the append in ``appends`` and the new sessions in ``sessions`` and ``pairs``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import ConfigError, MergeError, StoreError
from driftmap.frame import Frame, PoseSource
from driftmap.pipeline.build_config import BuildConfig, BuildResult, ProgressCallback
from driftmap.pipeline.loop_closure import EdgeGroup, keyframe_clouds, odometry_edges, optimize_calibrated
from driftmap.pipeline.merge import (
    MERGE_SUMMARY_FILE,
    SESSION_ID_STRIDE,
    SessionReport,
    copy_frames,
    frame_origin,
    keyframe_range,
    odometry_config,
    record_graph_verdicts,
    refuse_partial_head,
    session_keyframes,
    source_losses,
    store_sessions,
)
from driftmap.pipeline.merge_loops import MIN_CONSISTENT_LOOPS, PairLoops, drop_graph_rejected, find_pair_loops
from driftmap.pipeline.same_recording import frame_readings, refuse_same_recording
from driftmap.registration.loops import CandidateKind, Keyframe, LoopClosureConfig, select_keyframes, verify
from driftmap.registration.place import scan_context_distance, yaw_guess
from driftmap.store.frame_store import FrameStore
from driftmap.store.manifest import read_manifest
from driftmap.store.propagation import propagate_correction
from driftmap.store.unmerged import unmerged_sessions
from driftmap.store.values import preview

__all__ = ["APPEND_MOVE_TOLERANCE_DEG", "APPEND_MOVE_TOLERANCE_M", "PENDING_KEY", "AppendResult",
           "abandon_interrupted_append", "append_sessions", "interrupted_append"]

logger = logging.getLogger(__name__)

APPEND_MOVE_TOLERANCE_M = 1e-3
"""An existing frame whose optimised pose is within this distance (and :data:`APPEND_MOVE_TOLERANCE_DEG`) of its
head pose keeps the head pose exactly: the solver's own noise is not a correction."""
APPEND_MOVE_TOLERANCE_DEG = 0.05
PENDING_KEY = "append_in_progress"
"""``merge_summary.json``'s record of an append whose frames may be (partly) stored without its revision."""


@dataclass
class AppendResult:
    """One ``merge --append`` (also its record in ``merge_summary.json``'s ``appends``)."""

    store: str
    sessions: list[SessionReport]
    """the new sessions (numbered after every session the store ever reported), connected or not"""
    pairs: list[dict[str, Any]]
    """the new session pairs' loops (as :class:`~driftmap.pipeline.merge.MergeResult.pairs`)"""
    not_connected: list[int]
    previous_head: int
    revision_id: int | None = None
    n_frames: int = 0
    """frames in the store after the append"""
    n_frames_appended: int = 0
    existing_frames: int = 0
    existing_moved: int = 0
    """existing frames the new revision sets (moved more than the tolerance)"""
    existing_kept: int = 0
    """existing frames keeping their head pose to the bit"""
    max_existing_shift_m: float | None = None
    """the largest move of an existing frame (the moved ones)"""
    max_kept_shift_m: float | None = None
    """the largest move below the tolerance that was not applied"""
    move_tolerance_m: float = APPEND_MOVE_TOLERANCE_M
    move_tolerance_deg: float = APPEND_MOVE_TOLERANCE_DEG
    loops_reused: int = 0
    """recorded loops between the existing sessions taken as recorded"""
    loops_reverified: int = 0
    """recorded loops verified again (a store merged before loops' measurements were recorded)"""
    loops_new: int = 0
    graph_error_before: float | None = None
    graph_error_after: float | None = None
    loops_rejected_by_graph: int = 0
    information_scale: dict[str, float] = field(default_factory=dict)
    resumed: bool = False
    """an interrupted append of the same stores was finished"""
    seconds_per_stage: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def read_summary(store: Path) -> dict[str, Any]:
    try:
        data = json.loads((store / MERGE_SUMMARY_FILE).read_text())
    except FileNotFoundError:
        raise ConfigError(f"{store}: is not a merged store (no {MERGE_SUMMARY_FILE}); --append adds sessions to a "
                          f"store `driftmap merge A B --out STORE` made: merge the stores first") from None
    except (OSError, ValueError) as exc:
        raise StoreError(f"{store / MERGE_SUMMARY_FILE}: cannot be read ({exc}); the store's frames and revisions "
                         f"are untouched") from exc
    if not isinstance(data, dict) or not isinstance(data.get("sessions"), list):
        raise StoreError(f"{store / MERGE_SUMMARY_FILE}: not a merge summary (no 'sessions' list)")
    return data


def write_summary(store: Path, data: dict[str, Any] | str) -> None:
    """``merge_summary.json`` (a dict, or its text) written beside and renamed into place (a crash leaves the old
    one or the new one)."""
    tmp = store / f".{MERGE_SUMMARY_FILE}.tmp"
    tmp.write_text(data if isinstance(data, str) else json.dumps(data, indent=2, default=str) + "\n")
    os.replace(tmp, store / MERGE_SUMMARY_FILE)


class _SessionRows:
    """One session of the merged store as :func:`keyframe_clouds` reads a store: its rows, their revision-0 poses
    (the session's head as merged) and stamps."""

    def __init__(self, store: FrameStore, rows: NDArray[np.intp]) -> None:
        self._store = store
        self.frame_ids = store.frame_ids[rows]
        self._rev0 = store.poses(0)[rows]
        self.ledger = SimpleNamespace(stamps_ns=store.ledger.stamps_ns[rows])

    def poses(self, revision: int | None = None) -> NDArray[np.float64]:
        return self._rev0

    def frame(self, frame_id: int, revision: int | None = None) -> Frame:
        return self._store.frame(frame_id)


def append_sessions(merged: str | Path, new_stores: Sequence[str | Path], *, config: BuildConfig | None = None,
                    progress: ProgressCallback | None = None, move_tolerance_m: float = APPEND_MOVE_TOLERANCE_M,
                    move_tolerance_deg: float = APPEND_MOVE_TOLERANCE_DEG) -> AppendResult:
    """Append the sessions in ``new_stores`` to the merged store ``merged`` in place (module docstring).
    ``config``: the ``[build]`` settings of the pose graph (give the merge's); the loop-closure settings and the
    keyframe range are the ones the merge recorded (``build.num_threads`` applies).

    Raises :class:`ConfigError` for unusable input (``merged`` not a merged store, a new store already a session of
    it, twice, of another sensor, empty, itself merged) and :class:`MergeError` when no new session connects (nothing
    is written then)."""
    config = config or BuildConfig()
    tick = progress or (lambda stage, done, total: None)
    merged = Path(merged)
    paths = [Path(p) for p in new_stores]
    if not paths:
        raise ConfigError(f"--append {merged}: give at least one new store to append to it")
    _check_paths(merged, paths)
    summary = read_summary(merged)
    store = FrameStore.open(merged, "a")
    sources: list[FrameStore] = []
    try:
        for p in paths:
            sources.append(FrameStore.open(p, "r"))
        return _append(merged, store, summary, paths, sources, config, tick, move_tolerance_m, move_tolerance_deg)
    finally:
        for s in sources:
            s.close()
        store.close()  # no-op after a discard; nothing was written when the append stopped before writing


def _check_paths(merged: Path, paths: list[Path]) -> None:
    if not merged.is_dir():
        raise ConfigError(f"--append {merged}: no such store folder (the first store is the merged store to append "
                          f"to)")
    target = merged.resolve()
    for k, p in enumerate(paths):
        r = p.resolve()
        if r == target or r.is_relative_to(target) or target.is_relative_to(r):
            raise ConfigError(f"{p}: is (or holds, or lies inside) the merged store {merged} it would be appended "
                              f"to; give the stores of the new sessions")
        for j in range(k):
            if r == paths[j].resolve() or (p.exists() and paths[j].exists() and os.path.samefile(p, paths[j])):
                raise ConfigError(f"{paths[j]} and {p}: the same store twice; give each new session once")


def _check_new(merged: Path, store: FrameStore, summary: dict[str, Any], paths: list[Path],
               sources: list[FrameStore]) -> list[str]:
    """The new stores against the merged one (module docstring, 1); returns their uuids."""
    if not store_sessions(store):
        raise ConfigError(f"{merged}: has {MERGE_SUMMARY_FILE} but its frames are not merged frames; --append needs a "
                          f"store `driftmap merge` made")
    if (unmerged := unmerged_sessions(store)) is not None:  # hostile trial 21 W6: it appended onto that head
        raise ConfigError(f"{merged}: {unmerged}; an append would build on that head and leave the session"
                          f"{'s' if len(unmerged.sessions) > 1 else ''} unaligned. Merge the session stores again "
                          f"into a new store, then append to that")
    own = str(read_manifest(merged)["store_uuid"])
    existing = {str(s["store_uuid"]): s for s in summary["sessions"] if s.get("connected")}
    first = store.frame(int(store.frame_ids[0]))
    uuids: list[str] = []
    for p, s in zip(paths, sources, strict=True):
        if len(s) == 0:
            raise StoreError(f"{p}: the store has no frames; nothing to append")
        if (p / MERGE_SUMMARY_FILE).is_file() or store_sessions(s):
            raise ConfigError(f"{p}: is a merged store itself; append the stores of its sessions one by one")
        if int(s.frame_ids.max()) >= SESSION_ID_STRIDE or int(s.frame_ids.min()) < 0:
            raise ConfigError(f"{p}: frame ids {int(s.frame_ids.min())}..{int(s.frame_ids.max())} are outside "
                              f"0..{SESSION_ID_STRIDE - 1}, which a merged store keeps per session")
        refuse_partial_head(p, s, "merge --append")
        uuid = str(read_manifest(p)["store_uuid"])
        if uuid == own:
            raise ConfigError(f"{p}: is a copy of the merged store {merged} (store uuid {uuid})")
        if uuid in existing:
            row = existing[uuid]
            k = int(row["session"])
            ids = np.asarray(store.frame_ids, np.int64)
            mine = ids[ids // SESSION_ID_STRIDE == k]
            if not np.isin(mine, store.members()).any():  # undone by a rollback, or lost to damage
                why = (f"a rollback or the loss of revisions {preview(store.loss.revision_ids)} to damage "
                       f"(`driftmap recover`)" if store.loss.revision_ids else "a rollback")
                placing = [r.revision_id for r in store.revisions if r.revision_id not in store.loss.revision_ids
                           and r.revision_id != 0  # (each session in its own world frame: not the merged map)
                           and len(mine) and np.isin(mine, store.members(r.revision_id)).any()]
                # (hostile trial 21 W7: with every frame of the session lost, no rollback brings it back)
                kept = (f"its frames stay stored in the revisions that place them (`driftmap rollback {merged} --to "
                        f"{placing[-1]}` brings one back)" if placing else
                        f"no revision places its {len(mine)} stored frames any more" if len(mine) else
                        "every frame of it was lost to damage")
                raise ConfigError(f"{p}: was session {k} of {merged} (store uuid {uuid}), which {why} left out of "
                                  f"the head (revision {store.head}); {kept}, and a store is appended once: to append "
                                  f"the session anew, build its log into a new store and append that")
            raise ConfigError(f"{p}: is already session {row['session']} of {merged} (store uuid {uuid}, merged from "
                              f"{row['store']}); a session is appended once")
        if uuid in uuids:
            j = uuids.index(uuid)
            raise ConfigError(f"{paths[j]} and {p}: the same store twice (store uuid {uuid}: one is a copy of the "
                              f"other); give each new session once")
        uuids.append(uuid)
        f = s.frame(int(s.frame_ids[0]))
        if f.sensor_kind is not first.sensor_kind:
            raise ConfigError(f"{merged} and {p}: different sensors (sensor_kind {first.sensor_kind.value} vs "
                              f"{f.sensor_kind.value}); append sessions of the merged store's sensor kind")
        if (first.intrinsics is None) != (f.intrinsics is None):
            kind = {True: "none", False: "pinhole"}
            raise ConfigError(f"{merged} and {p}: different intrinsics (intrinsics {kind[first.intrinsics is None]} "
                              f"vs {kind[f.intrinsics is None]}); append sessions of the merged store's sensor kind")
    # a session the head leaves out may come anew, and an interrupted append's sessions are being finished
    head = set(np.asarray(store.members(), np.int64).tolist())
    pending = {int(s["session"]) for s in (summary.get(PENDING_KEY) or {}).get("sessions", [])}
    origin = lambda provenance: getattr(frame_origin(provenance), "reading", None)  # noqa: E731 - a merged frame's own
    placed = [(f"{merged} (session {k})", frame_readings(store, [f for f in ids if f in head], origin))
              for k, ids in sorted(store_sessions(store).items()) if k not in pending]
    refuse_same_recording([*placed, *((str(p), frame_readings(s)) for p, s in zip(paths, sources, strict=True))])
    return uuids


def interrupted_append(merged: Path, head: int) -> str | None:
    """What an interrupted append left (``append_in_progress`` in the merged store's summary) and the command that
    finishes it; None when no append was interrupted (``driftmap info``, and the refusal of another append)."""
    try:
        summary = json.loads((merged / MERGE_SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        return None
    pending = summary.get(PENDING_KEY) if isinstance(summary, dict) else None
    if not pending:
        return None
    stores = " ".join(str(s["store"]) for s in pending["sessions"])
    numbers = ", ".join(str(s["session"]) for s in pending["sessions"])
    before = int(pending["previous_head"])
    where = (f"the head revision {head} is the map before it" if head == before else
             f"revision {before} is the map before it; the head is now revision {head}")
    return (f"an append of {stores} (session {numbers}) was interrupted: some of its frames may be stored without "
            f"its revision ({where}); finish it by running it again: `driftmap merge {merged} {stores} --append`, "
            f"or abandon it (its frames stay stored, outside the map): `driftmap rollback {merged} --to {before}`")


def abandon_interrupted_append(merged: Path, store: FrameStore) -> str | None:
    """After a rollback: when an append was interrupted and the new head places none of its frames, it is abandoned:
    ``append_in_progress`` moves to ``abandoned_appends`` (its session numbers stay taken, since its frames stay
    stored) and readers take the store again (hostile trial 17 B4: an interrupted append whose session store is gone
    locked the merged store for good). Returns what was done, or None."""
    if not (merged / MERGE_SUMMARY_FILE).is_file():
        return None  # not a merged store
    summary = read_summary(merged)  # a damaged summary is a StoreError naming it (the rollback itself is stored)
    pending = summary.get(PENDING_KEY)
    if not pending:
        return None
    numbers = {int(s["session"]) for s in pending["sessions"]}
    placed = store.members()
    if np.isin(placed // SESSION_ID_STRIDE, list(numbers)).any():
        return None  # the head still places frames of the interrupted append: it is not abandoned
    stored = int(np.isin(store.frame_ids // SESSION_ID_STRIDE, list(numbers)).sum())
    summary.pop(PENDING_KEY)
    summary["abandoned_appends"] = summary.get("abandoned_appends", []) + [
        pending | {"abandoned_by_revision": store.head, "frames_stored": stored}]
    write_summary(merged, summary)
    text = (f"the interrupted append of session {', '.join(map(str, sorted(numbers)))} is abandoned: its {stored} "
            f"stored frames are outside the map from revision {store.head} on")
    logger.warning("%s: %s", merged, text)
    return text


def _abandoned_sessions(summary: dict[str, Any]) -> set[int]:
    """The session numbers of the appends a rollback abandoned (:func:`abandon_interrupted_append`)."""
    return {int(s["session"]) for a in summary.get("abandoned_appends", []) for s in a.get("sessions", [])}


def _refuse_if_interrupted(merged: Path, store: FrameStore, summary: dict[str, Any], paths: list[Path]) -> None:
    """An interrupted append (``append_in_progress``) is finished by the same stores, in the same order, before
    any other: their frames carry its session numbers."""
    pending = summary.get(PENDING_KEY)
    if not pending:
        return
    was = [str(s["store_uuid"]) for s in pending["sessions"]]
    given = []
    for p in paths:
        try:
            given.append(str(read_manifest(p)["store_uuid"]))
        except StoreError:
            given.append("")
    if was != given:
        raise ConfigError(f"{merged}: {interrupted_append(merged, store.head)}; finish it before another append")


def _numbers(merged: Path, summary: dict[str, Any], paths: list[Path], uuids: list[str]) -> tuple[list[int], bool]:
    """The new sessions' numbers (after every session the store ever reported) and whether this finishes an
    interrupted append (then the same stores, in the same order, must be given: their frames carry its numbers)."""
    pending = summary.get(PENDING_KEY)
    if pending:
        return [int(s["session"]) for s in pending["sessions"]], True
    reported = [int(s["session"]) for s in summary["sessions"]]
    reported += [int(s["session"]) for a in summary.get("appends", []) for s in a.get("sessions", [])]
    reported += sorted(_abandoned_sessions(summary))  # an abandoned append's frames stay stored under its numbers
    start = max(reported, default=-1) + 1
    return list(range(start, start + len(paths))), False


def _lc_and_range(summary: dict[str, Any], store: FrameStore, first_session: dict[str, Any],
                  config: BuildConfig) -> tuple[LoopClosureConfig, float | None]:
    """The merge's recorded loop-closure settings and keyframe range (older summaries without the range: the
    odometry range of session 0's store, else of its frames as merged)."""
    if not summary.get("loop_closure_config"):
        raise StoreError(f"{store.path / MERGE_SUMMARY_FILE}: records no loop_closure_config; merge the sessions' "
                         f"stores again")
    lc = LoopClosureConfig.model_validate(summary["loop_closure_config"])
    if config.num_threads is not None:
        lc = lc.model_copy(update={"num_threads": config.num_threads})
    if "keyframe_max_range_m" in summary:
        return lc, summary["keyframe_max_range_m"]
    source0 = Path(first_session["store"])
    if (source0 / "store.json").is_file():
        with FrameStore.open(source0, "r", verify=False) as s0:
            return lc, keyframe_range(lc, odometry_config(s0, config))
    return lc, keyframe_range(lc, odometry_config(store, config))


def _append(merged: Path, store: FrameStore, summary: dict[str, Any], paths: list[Path], sources: list[FrameStore],
            config: BuildConfig, tick: ProgressCallback, tol_m: float, tol_deg: float) -> AppendResult:
    stages: dict[str, float] = {}
    _refuse_if_interrupted(merged, store, summary, paths)
    uuids = _check_new(merged, store, summary, paths, sources)
    numbers, resumed = _numbers(merged, summary, paths, uuids)
    existing = sorted(int(s["session"]) for s in summary["sessions"] if s.get("connected"))
    in_store = store_sessions(store)
    abandoned = _abandoned_sessions(summary)
    if not set(existing) <= set(in_store) or set(in_store) - set(existing) - set(numbers if resumed else []) - abandoned:
        raise StoreError(f"{merged}: its frames hold sessions {sorted(in_store)}, its {MERGE_SUMMARY_FILE} "
                         f"{existing}; they disagree (was the summary replaced?)")
    head = store.head
    existing = _sessions_in_head(merged, store, head, existing)
    by_session = {s["session"]: s for s in summary["sessions"]}
    lc, max_range_m = _lc_and_range(summary, store, by_session[existing[0]], config)

    t = time.perf_counter()
    ids = store.frame_ids
    rows = {k: np.flatnonzero(ids // SESSION_ID_STRIDE == k) for k in existing}
    keyframes: dict[int, list[Keyframe]] = {}
    for k in existing:
        view = _SessionRows(store, rows[k])
        keyframes[k] = keyframe_clouds(view, lc, select_keyframes(view.poses(), lc), max_range_m,  # type: ignore[arg-type]
                                       lambda s, d, n, k=k: tick(f"keyframes, session {k}", d, n))
    for k, src in zip(numbers, sources, strict=True):
        keyframes[k] = session_keyframes(k, src, lc, max_range_m, tick)
    stages["keyframes"] = time.perf_counter() - t
    reports = {k: SessionReport(k, str(p.resolve()), uuids[n], src.head, src.ledger.revision(src.head).source.value,
                                len(src), n_keyframes=len(keyframes[k]), frame_id_offset=k * SESSION_ID_STRIDE,
                                frames_lost_in_source=source_losses(k, p, src))
               for n, (k, p, src) in enumerate(zip(numbers, paths, sources, strict=True))}
    result = AppendResult(store=str(merged.resolve()), sessions=list(reports.values()), pairs=[], not_connected=[],
                          previous_head=head, move_tolerance_m=tol_m, move_tolerance_deg=tol_deg, resumed=resumed,
                          seconds_per_stage=stages)

    t = time.perf_counter()
    pairs: list[PairLoops] = []
    for n, j in enumerate(numbers):
        for i in existing + numbers[:n]:
            stage = f"loops, sessions {i}-{j}"
            pairs.append(find_pair_loops(i, j, keyframes[i], keyframes[j], lc, lambda d, m, s=stage: tick(s, d, m)))
    stages["loops between sessions"] = time.perf_counter() - t
    while True:  # again without the pairs whose agreeing loops the pose graph rejected (drop_graph_rejected)
        result.pairs = [p.summary() for p in pairs]
        result.not_connected, result.loops_reused, result.loops_reverified = [], 0, 0
        placed = _place_new_sessions(store, head, existing, numbers, keyframes, pairs)
        for k in numbers:
            reports[k].connected = k in placed
            if k in placed:
                reports[k].reason = ""
                continue
            reasons = [f"with session {p.session_a if p.session_b == k else p.session_b}: "
                       f"{p.why_not_connected() or 'connected only to new sessions that are not connected'}"
                       for p in pairs if k in (p.session_a, p.session_b)]
            reports[k].reason = "; ".join(reasons)
            result.not_connected.append(k)
            logger.warning("session %d (%s) is not connected to the merged store's sessions: %s; nothing of it is "
                           "appended", k, reports[k].store, reports[k].reason)
        connected_new = [k for k in numbers if k in placed]
        if not connected_new:
            raise MergeError(
                f"no new session could be connected to {merged}: "
                + "; ".join(f"session {k} ({reports[k].store}): {reports[k].reason}" for k in numbers)
                + f"; nothing was written. Are they stores of the same place? (a session needs at least "
                  f"{MIN_CONSISTENT_LOOPS} agreeing loops with another)")
        if resumed and result.not_connected:
            raise MergeError(f"{merged}: finishing the interrupted append, sessions {result.not_connected} no longer "
                             f"connect; their frames stay stored without a revision (the head {head} is the map "
                             f"before the append)")
        poses, covariances, note, rejected = _optimise(store, head, existing, connected_new, keyframes, placed, pairs,
                                                       summary, lc, config, result, tick)
        in_graph = set(existing) | set(connected_new)
        if not drop_graph_rejected([p for p in pairs if p.session_a in in_graph and p.session_b in in_graph],
                                   rejected):
            break
    src_of = dict(zip(numbers, sources, strict=True))
    new_rows = {k: (src_of[k].frame_ids + k * SESSION_ID_STRIDE, src_of[k].ledger.stamps_ns, src_of[k].poses(src_of[k].head))
                for k in connected_new}
    set_poses = _changed_poses(store, head, existing, rows, new_rows, poses, result)
    covariances = {f: c for f, c in covariances.items() if f in set_poses}
    _write(merged, store, summary, result, connected_new, reports, src_of, dict(zip(numbers, paths, strict=True)),
           dict(zip(numbers, uuids, strict=True)), set_poses, covariances, note, tick)
    return result


def _sessions_in_head(merged: Path, store: FrameStore, head: int, connected: list[int]) -> list[int]:
    """The connected sessions the head places -- every frame of each; a session a rollback left out (an append
    undone) is left out of the append too, with a warning: its frames are neither moved nor placed (hostile trial 18
    B2: 26 of its 30 frames came back into the new head). A session the head places in part is refused."""
    ids = store.frame_ids
    placed = np.isin(ids, store.members(head))
    kept, left_out = [], []
    for k in connected:
        inside = placed[ids // SESSION_ID_STRIDE == k]
        if inside.all():
            kept.append(k)
        elif not inside.any():
            left_out.append(k)
        else:
            raise StoreError(f"{merged}: its head (revision {head}) places {int(inside.sum())} of the "
                             f"{len(inside)} frames of session {k}; an append builds on whole sessions: roll the "
                             f"store back to a revision that places all or none of them first")
    if left_out:
        why = "an append undone by a rollback" + (
            f", or whose revision was lost to damage (revisions {preview(store.loss.revision_ids)})"
            if store.loss.revision_ids else "")
        logger.warning("%s: the head (revision %d) does not place session(s) %s (%s): the append leaves them out; they "
                       "stay stored, in the revisions that place them", merged, head, ", ".join(map(str, left_out)), why)
    if not kept:
        raise StoreError(f"{merged}: its head (revision {head}) places none of its sessions; roll it back to a "
                         f"revision that places the map first")
    return kept


def _place_new_sessions(store: FrameStore, head: int, existing: list[int], numbers: list[int],
                        keyframes: dict[int, list[Keyframe]],
                        pairs: list[PairLoops]) -> dict[int, NDArray[np.float64]]:
    """``T_merged_worldk`` of each new session connected to an existing one (through connected pairs, the new ones
    too): an existing session's world lies in the merged one where its first keyframe's head pose says."""
    T: dict[int, NDArray[np.float64]] = {}
    P_head, P0 = store.poses(head), store.poses(0)
    for k in existing:
        row = int(np.searchsorted(store.frame_ids, keyframes[k][0].frame_id))
        T[k] = P_head[row] @ geometry.invert(P0[row])
    grew = True
    while grew:
        grew = False
        for pair in sorted(pairs, key=lambda p: -len(p.consistent)):
            if not pair.connected or pair.T_a_b is None:
                continue
            if pair.session_a in T and pair.session_b not in T:
                T[pair.session_b] = T[pair.session_a] @ pair.T_a_b
                grew = True
            elif pair.session_b in T and pair.session_a not in T:
                T[pair.session_a] = T[pair.session_b] @ geometry.invert(pair.T_a_b)
                grew = True
    return {k: T[k] for k in numbers if k in T}


def _recorded_loops(summary: dict[str, Any], existing: list[int], keyframes: dict[int, list[Keyframe]],
                    lc: LoopClosureConfig, result: AppendResult) -> list:
    """The graph edges of the loops the merge (and earlier appends) accepted between existing sessions: as recorded,
    else verified again on the same keyframes."""
    by_id = {kf.frame_id: kf for k in existing for kf in keyframes[k]}
    edges = []
    for pair in summary.get("pairs", []):
        if pair["session_a"] not in existing or pair["session_b"] not in existing:
            continue
        for rec in pair.get("loops", []):
            if not rec.get("accepted"):
                continue
            if rec.get("T_a_b") is not None and rec.get("information") is not None:
                edges.append((EdgeGroup.LOOP, int(rec["a"]), int(rec["b"]), np.array(rec["T_a_b"]).reshape(4, 4),
                              np.array(rec["information"]).reshape(6, 6)))
                result.loops_reused += 1
                continue
            a, b = by_id.get(int(rec["a"])), by_id.get(int(rec["b"]))
            if a is None or b is None:
                logger.warning("recorded loop %s<->%s: not a keyframe any more; left out", rec["a"], rec["b"])
                continue
            kind, guess = CandidateKind(rec["kind"]), None
            if kind is CandidateKind.SCAN_CONTEXT and a.scan_context is not None and b.scan_context is not None:
                guess = yaw_guess(scan_context_distance(a.scan_context, b.scan_context)[1])
            cand = verify(a, b, kind, lc, path_length_m=math.inf, init_T_a_b=guess)
            if cand.accepted and cand.result is not None and cand.T_a_b is not None:
                edges.append((EdgeGroup.LOOP, cand.a, cand.b, cand.T_a_b, cand.result.information_6x6))
                result.loops_reverified += 1
            else:
                logger.warning("recorded loop %d<->%d: not verified again (%s); left out", a.frame_id, b.frame_id,
                               cand.reason)
    return edges


def _optimise(store: FrameStore, head: int, existing: list[int], connected_new: list[int],
              keyframes: dict[int, list[Keyframe]], placed: dict[int, NDArray[np.float64]], pairs: list[PairLoops],
              summary: dict[str, Any], lc: LoopClosureConfig, config: BuildConfig, result: AppendResult,
              tick: ProgressCallback) -> tuple[dict[int, NDArray[np.float64]], dict, str, set[tuple[int, int]]]:
    """One pose graph over every session (module docstring, 4): the optimised keyframe poses, their covariances,
    the revision's note and the loops the graph rejected (``(a, b)`` frame ids)."""
    t = time.perf_counter()
    from_trajectory = config.odometry_edges != "registration"
    P_head = store.poses(head)
    nodes: list[Keyframe] = []
    edges: list = []
    sessions = existing + connected_new
    for k in sessions:
        if k in placed:
            nodes += [dataclasses.replace(kf, T_world_sensor=placed[k] @ kf.T_world_sensor) for kf in keyframes[k]]
        else:
            at = np.searchsorted(store.frame_ids, [kf.frame_id for kf in keyframes[k]])
            nodes += [dataclasses.replace(kf, T_world_sensor=P_head[r]) for kf, r in zip(keyframes[k], at, strict=True)]
        edges += odometry_edges(keyframes[k], lc, config, from_trajectory,
                                lambda s, d, n, k=k: tick(f"odometry edges, session {k}", d, n))
    result.seconds_per_stage["odometry edges"] = time.perf_counter() - t
    t = time.perf_counter()
    edges += _recorded_loops(summary, existing, keyframes, lc, result)
    result.seconds_per_stage["recorded loops"] = time.perf_counter() - t
    new_loops = [c for p in pairs if p.session_a in sessions and p.session_b in sessions and p.connected
                 for c in p.consistent if c.result is not None]
    result.loops_new = len(new_loops)
    edges += [(EdgeGroup.LOOP, c.a, c.b, c.T_a_b, c.result.information_6x6) for c in new_loops]
    t = time.perf_counter()
    scratch = BuildResult(store=result.store, n_frames=0, n_frames_new=0, mean_invalid_fraction=None,
                          pose_source=PoseSource.LOOP_CLOSURE.value, odometry_fps=None)
    opt = optimize_calibrated(nodes, edges, config, scratch, calibrate_odometry=not from_trajectory)
    result.seconds_per_stage["pose graph"] = time.perf_counter() - t
    result.graph_error_before, result.graph_error_after = opt.initial_error, opt.final_error
    result.information_scale = scratch.information_scale
    rejected = record_graph_verdicts(result, opt)
    new = ", ".join(f"session {s.session}: {s.store} revision {s.head_revision}" for s in result.sessions
                    if s.session in connected_new)
    note = (f"append of {len(connected_new)} session(s) ({new}) to {len(existing)} merged; {len(new_loops)} new "
            f"loops, {result.loops_reused + result.loops_reverified} recorded; graph error {opt.initial_error:.3g} -> "
            f"{opt.final_error:.3g}")
    return dict(opt.poses), dict(opt.covariances or {}), note, rejected


def _session_poses(ids: NDArray[np.int64], stamps: NDArray[np.int64], rev0: NDArray[np.float64],
                   key_poses: dict[int, NDArray[np.float64]]) -> NDArray[np.float64]:
    """Every frame of one session (rows ``ids``): its keyframes' optimised poses, the others following them by the
    store's propagation rule (as ``merge`` applies it, per session)."""
    out = np.array(rev0, copy=True)
    mine = set(ids.tolist())
    keys = np.array(sorted(f for f in key_poses if f in mine), dtype=np.int64)
    prop_ids, prop_poses = propagate_correction(ids, stamps, rev0, keys, np.array([key_poses[int(f)] for f in keys]))
    at = {int(f): n for n, f in enumerate(ids.tolist())}
    for f, P in zip(prop_ids.tolist(), prop_poses, strict=True):
        out[at[f]] = P
    for f in keys.tolist():
        out[at[f]] = key_poses[f]
    return out


def _changed_poses(store: FrameStore, head: int, existing: list[int], rows: dict[int, NDArray[np.intp]],
                   new_rows: dict[int, tuple], poses: dict[int, NDArray[np.float64]],
                   result: AppendResult) -> dict[int, NDArray[np.float64]]:
    """The poses the new revision sets: every existing frame that moves more than the tolerance from its head pose,
    every new frame."""
    ids, stamps, P0, P_head = store.frame_ids, store.ledger.stamps_ns, store.poses(0), store.poses(head)
    out: dict[int, NDArray[np.float64]] = {}
    moved_m: list[float] = []
    kept_m: list[float] = []
    for k in existing:
        r = rows[k]
        P = _session_poses(ids[r], stamps[r], P0[r], poses)
        d_m = np.linalg.norm(P[:, :3, 3] - P_head[r, :3, 3], axis=1)
        d_deg = np.degrees(geometry.relative_rotation_angle_rad(P, P_head[r]))
        moves = (d_m > result.move_tolerance_m) | (d_deg > result.move_tolerance_deg)
        out.update(zip(ids[r][moves].tolist(), P[moves], strict=True))
        moved_m += d_m[moves].tolist()
        kept_m += d_m[~moves].tolist()
    for k, (fids, fstamps, rev0) in new_rows.items():
        out.update(zip(fids.tolist(), _session_poses(fids, fstamps, rev0, poses), strict=True))
    result.existing_frames = len(moved_m) + len(kept_m)
    result.existing_moved, result.existing_kept = len(moved_m), len(kept_m)
    result.max_existing_shift_m = max(moved_m, default=None)
    result.max_kept_shift_m = max(kept_m, default=None)
    return out


def _write(merged: Path, store: FrameStore, summary: dict[str, Any], result: AppendResult, connected_new: list[int],
           reports: dict[int, SessionReport], sources: dict[int, FrameStore], paths: dict[int, Path],
           uuids: dict[int, str], set_poses: dict[int, NDArray[np.float64]], covariances: dict, note: str,
           tick: ProgressCallback) -> None:
    """The frames and the revision in one new segment, all or nothing (module docstring, 6); then the summary."""
    t = time.perf_counter()
    original = (merged / MERGE_SUMMARY_FILE).read_text()
    n_before = len(store)
    summary[PENDING_KEY] = {"previous_head": result.previous_head,
                            "sessions": [{"session": s.session, "store": s.store, "store_uuid": s.store_uuid}
                                         for s in result.sessions]}
    write_summary(merged, summary)
    try:
        copy_frames(store, connected_new, paths, sources, uuids, tick)
        result.seconds_per_stage["frames"] = time.perf_counter() - t
        t = time.perf_counter()
        revision = store.add_revision(set_poses, source=PoseSource.LOOP_CLOSURE, propagate=False,
                                      covariances=covariances, note=note)
    except BaseException as exc:
        discarded = store.discard_session()
        write_summary(merged, original)
        logger.warning("%s: the append failed (%s); %s", merged, exc,
                       "its frames were taken back: the store is as it was" if discarded else "nothing was written")
        if isinstance(exc, OSError):
            raise MergeError(f"{getattr(exc, 'filename', None) or merged}: appending to the merged store failed "
                             f"({exc.strerror or type(exc).__name__}); the store is as it was (head revision "
                             f"{result.previous_head}) and the new stores are untouched") from exc
        raise
    store.close()
    result.revision_id = revision.revision_id
    result.n_frames = len(store)
    result.n_frames_appended = result.n_frames - n_before
    result.seconds_per_stage["revision"] = time.perf_counter() - t
    for k in connected_new:
        first = store.frame_ids[store.frame_ids // SESSION_ID_STRIDE == k][0]
        T0 = sources[k].poses(sources[k].head)[0]
        reports[k].T_merged_session = [float(v) for v in (set_poses[int(first)] @ geometry.invert(T0)).ravel()]
    summary.pop(PENDING_KEY, None)
    summary["sessions"] = summary["sessions"] + [dataclasses.asdict(s) for s in result.sessions]
    summary["pairs"] = summary.get("pairs", []) + result.pairs
    summary["frames_per_session"] = {str(k): v for k, v in summary.get("frames_per_session", {}).items()} | {
        str(k): reports[k].n_frames for k in connected_new}
    summary["not_connected"] = summary.get("not_connected", []) + result.not_connected
    summary["n_frames"], summary["revision_id"] = result.n_frames, result.revision_id
    summary["appends"] = summary.get("appends", []) + [result.to_json()]
    write_summary(merged, summary)
    logger.info("appended %d session(s) (%d frames) to %s: revision %d; %d of %d existing frames moved",
                len(connected_new), result.n_frames_appended, merged, result.revision_id, result.existing_moved,
                result.existing_frames)

