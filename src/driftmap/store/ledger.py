"""The pose ledger: every pose revision of every frame, kept in memory.

Revision 0 holds the poses that produced the frames (``add_frame``). Every later revision records only the
frames it changes, split into the poses it was given (``set_directly``) and the poses it derived from them
(``propagated``), plus its parent. A frame's pose in revision ``r`` is the pose set for it by the nearest
revision on ``r``'s ancestry chain (``r``, ``parent(r)``, ..., 1) that changes it, else its revision-0 pose;
so a correction may branch from an older revision and a rollback is just another revision.

Each revision is a pose estimate for a set of frames, its *members* (:meth:`PoseLedger.members`): revision 0 holds
every frame; a later revision the frames it was made over (recorded as ``Revision.frames``): its parent's members
plus the frames it sets. A frame stored after a revision is not one of its members, so an older revision never
shows frames added later at poses it never gave them (a session appended by ``merge --append``, the frames of a
``build --resume``), and a rollback to it restores its set of frames. The head alone also shows the frames stored
after it, at their revision-0 poses, until a revision places them (a live robot appending to a store). Revisions
stored before membership was recorded take the frames stored before them (store order), a rollback its target's.

Changing the ledger is two steps: ``plan_correction`` / ``plan_rollback`` validate and return a new
:class:`Revision` without adding it, and ``commit`` appends it. The store persists a planned revision
(``Revision.to_json``) first and commits it in memory only once that succeeded.

Correction propagation (how the poses given for keyframes move the other frames) is described and done in
:mod:`driftmap.store.propagation`; the revision records themselves are :mod:`driftmap.store.revision`, and matching
a trajectory file's rows to frames is :mod:`driftmap.store.pose_match` (all re-exported here).
"""

from __future__ import annotations

import logging
import numbers
import time
from collections import OrderedDict
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from driftmap import geometry
from driftmap.errors import StoreError, TransformError, parse_enum
from driftmap.frame import PoseSource
from driftmap.store.pose_match import PoseMatch, PoseMatchMode, match_pose_rows, match_trajectory, stamp_ranges_text
from driftmap.store.propagation import propagate_correction
from driftmap.store.revision import REVISION_SCHEMA_VERSION, SAME_POSE_DEG, SAME_POSE_M, PoseDiff, Revision
from driftmap.store.values import as_int, as_source, preview, readonly
from driftmap.trajectory import Trajectory

logger = logging.getLogger(__name__)

#: what this module offers: the ledger, and (as before the revision records, propagation and pose-file matching
#: moved to modules of their own) the names it used to define
__all__ = [
    "POSE_CACHE_SIZE", "REVISION_SCHEMA_VERSION", "SAME_POSE_DEG", "SAME_POSE_M", "PoseDiff", "PoseLedger",
    "PoseMatch", "PoseMatchMode", "PoseSource", "Revision", "StoreError", "Trajectory", "TransformError",
    "match_pose_rows", "match_trajectory", "parse_enum", "stamp_ranges_text",
]

#: How many revisions' full pose arrays :meth:`PoseLedger.poses` keeps (least recently used are dropped).
POSE_CACHE_SIZE = 8




class PoseLedger:
    """Frames' revision-0 poses plus every committed pose revision (see the module docstring)."""

    def __init__(self, base_source: PoseSource = PoseSource.ODOMETRY, *, created_ns: int | None = None) -> None:
        self._base_source = as_source(base_source)
        self._created_ns = time.time_ns() if created_ns is None else as_int(created_ns, "created_ns")
        self._known: set[int] = set()
        self._order: list[int] = []  # frame ids in the order they were added (the store order)
        self._known_at: list[int] = []  # per committed revision: how many frames the ledger held when it was committed
        self._recorded: list[NDArray[np.int64]] = []  # per committed revision: its member ids (sorted)
        self._frame_sources: set[PoseSource] = set()
        # frames arrive one at a time: appended to these lists and merged into the sorted arrays on demand
        self._pending_ids: list[int] = []
        self._pending_stamps: list[int] = []
        self._pending_poses: list[NDArray[np.float64]] = []
        self._ids: NDArray[np.int64] = readonly(np.zeros(0, dtype=np.int64))
        self._stamps: NDArray[np.int64] = readonly(np.zeros(0, dtype=np.int64))
        self._base: NDArray[np.float64] = readonly(np.zeros((0, 4, 4)))
        self._committed: list[Revision] = []  # revisions 1..head
        self._revision0: Revision | None = None
        # revision -> (the sorted frame ids it was built for, their poses); frames added later are filled in with
        # their revision-0 poses when the entry is next used (no revision can name a frame it predates)
        self._pose_cache: OrderedDict[int, tuple[NDArray[np.int64], NDArray[np.float64]]] = OrderedDict()

    # ---- frames ----------------------------------------------------------------------------------------------

    def add_frame(self, frame_id: int, stamp_ns: int, T_world_sensor: ArrayLike, source: PoseSource | str | None = None) -> None:
        """Register a frame and its revision-0 pose (validated rigid). A duplicate ``frame_id`` is a StoreError;
        a rejected call leaves the ledger unchanged. ``source``: where that pose came from; when every frame
        names the same one, revision 0 is labelled with it (else with the ledger's ``base_source``)."""
        fid = as_int(frame_id, "frame_id")
        stamp = as_int(stamp_ns, f"frame {fid}: stamp_ns")
        T = geometry.as_rigid(T_world_sensor, f"frame {fid}: T_world_sensor")
        if fid in self._known:
            raise StoreError(f"frame {fid} is already in the pose ledger")
        self._known.add(fid)
        self._order.append(fid)
        if source is not None:
            self._frame_sources.add(as_source(source))
        self._pending_ids.append(fid)
        self._pending_stamps.append(stamp)
        self._pending_poses.append(T)
        self._revision0 = None

    def _consolidate(self) -> None:
        if not self._pending_ids:
            return
        ids = np.concatenate([self._ids, np.asarray(self._pending_ids, dtype=np.int64)])
        stamps = np.concatenate([self._stamps, np.asarray(self._pending_stamps, dtype=np.int64)])
        base = np.concatenate([self._base, np.asarray(self._pending_poses, dtype=np.float64).reshape(-1, 4, 4)])
        order = np.argsort(ids, kind="stable")
        self._ids, self._stamps = readonly(ids[order]), readonly(stamps[order])
        self._base = readonly(base[order])
        self._pending_ids, self._pending_stamps, self._pending_poses = [], [], []

    @property
    def frame_ids(self) -> NDArray[np.int64]:
        """Sorted frame ids (read-only); every per-frame array of the ledger is aligned with it."""
        self._consolidate()
        return self._ids

    @property
    def stamps_ns(self) -> NDArray[np.int64]:
        """Frame stamps aligned with :attr:`frame_ids`."""
        self._consolidate()
        return self._stamps

    @property
    def n_frames(self) -> int:
        return len(self._known)

    def __contains__(self, frame_id: object) -> bool:
        if isinstance(frame_id, bool) or not isinstance(frame_id, numbers.Integral):
            return False
        return int(frame_id) in self._known

    def _index_of(self, frame_ids: NDArray[np.int64]) -> NDArray[np.intp]:
        """Positions of known frame ids in :attr:`frame_ids`."""
        return np.searchsorted(self.frame_ids, frame_ids)

    # ---- revisions -------------------------------------------------------------------------------------------

    @property
    def head(self) -> int:
        """Id of the latest revision (0 before any correction)."""
        return len(self._committed)

    @property
    def revisions(self) -> list[Revision]:
        """All revisions; the list index is the revision id."""
        return [self.revision(0), *self._committed]

    def revision(self, revision_id: int) -> Revision:
        rid = self._require_revision(revision_id)
        if rid > 0:
            return self._committed[rid - 1]
        if self._revision0 is None:
            self._consolidate()
            self._revision0 = Revision(
                revision_id=0,
                parent_id=None,
                source=next(iter(self._frame_sources)) if len(self._frame_sources) == 1 else self._base_source,
                created_ns=self._created_ns,
                note="poses that produced the frames",
                set_directly=dict(zip(self._ids.tolist(), self._base, strict=True)),
            )
        return self._revision0

    def _require_revision(self, revision_id: Any, what: str = "revision") -> int:
        rid = as_int(revision_id, what)
        if not 0 <= rid <= self.head:
            raise StoreError(f"{what} {rid} does not exist (the ledger has revisions 0..{self.head})")
        return rid

    def _parent_of(self, rid: int) -> int:
        parent = self._committed[rid - 1].parent_id
        assert parent is not None
        return parent

    def members(self, revision_id: int, *, later: bool = True) -> NDArray[np.int64]:
        """Sorted read-only ids of the frames revision ``revision_id`` places (module docstring): every frame for
        revision 0; for a later revision the frames it was made over, and for the head also the frames stored
        after it (unless ``later`` is False)."""
        rid = self._require_revision(revision_id)
        if rid == 0:
            return self.frame_ids
        recorded = self._recorded[rid - 1]
        if later and rid == self.head and self._known_at[rid - 1] < len(self._order):
            stored_since = np.asarray(self._order[self._known_at[rid - 1]:], dtype=np.int64)
            recorded = readonly(np.union1d(recorded, stored_since))
        return recorded

    def member_rows(self, revision_id: int) -> NDArray[np.intp]:
        """Positions of :meth:`members` in :attr:`frame_ids` (rows of :meth:`poses`)."""
        return self._index_of(self.members(revision_id))

    # ---- poses -----------------------------------------------------------------------------------------------

    def poses(self, revision_id: int) -> NDArray[np.float64]:
        """(M, 4, 4) read-only ``T_world_sensor`` of every frame, aligned with :attr:`frame_ids`, as revision
        ``revision_id`` has them; a frame that is not one of its :meth:`members` has its revision-0 pose here (or
        the pose an ancestor gave it): take :meth:`member_rows` for the revision's own frames."""
        rid = self._require_revision(revision_id)
        self._consolidate()
        cached = self._cached_poses(rid)
        if cached is not None:
            self._pose_cache.move_to_end(rid)
            return cached
        # walk up the ancestry to a cached revision, revision 0, or a revision that changes every frame
        chain: list[int] = []
        start: NDArray[np.float64] | None = None
        cur = rid
        while cur != 0:
            if (start := self._cached_poses(cur)) is not None:
                break
            chain.append(cur)
            if self._committed[cur - 1].n_changed == len(self._ids):
                start = np.zeros_like(self._base)
                break
            cur = self._parent_of(cur)
        out = np.array(self._base if start is None else start, copy=True)
        for cur in reversed(chain):  # oldest first, so nearer revisions overwrite
            rev = self._committed[cur - 1]
            out[self._index_of(rev.changed_frame_ids)] = rev.changed_poses
        out = readonly(out)
        self._pose_cache[rid] = (self._ids, out)
        while len(self._pose_cache) > POSE_CACHE_SIZE:
            self._pose_cache.popitem(last=False)
        return out

    def _cached_poses(self, rid: int) -> NDArray[np.float64] | None:
        """The cached poses of a revision, brought up to the current frames (consolidated), or ``None``."""
        entry = self._pose_cache.get(rid)
        if entry is None:
            return None
        ids, poses = entry
        if ids is not self._ids:
            grown = np.array(self._base, copy=True)
            grown[self._index_of(ids)] = poses
            poses = readonly(grown)
            self._pose_cache[rid] = (self._ids, poses)
        return poses

    def pose(self, revision_id: int, frame_id: int) -> NDArray[np.float64]:
        """Read-only ``T_world_sensor`` of one frame in one revision."""
        rid = self._require_revision(revision_id)
        fid = as_int(frame_id, "frame_id")
        if fid not in self._known:
            raise StoreError(f"frame {fid} is not in the pose ledger")
        cur = rid
        while cur != 0:
            rev = self._committed[cur - 1]
            T = rev.set_directly.get(fid)
            if T is None:
                T = rev.propagated.get(fid)
            if T is not None:
                return T
            cur = self._parent_of(cur)
        self._consolidate()
        return self._base[int(self._index_of(np.array([fid]))[0])]

    # ---- corrections -----------------------------------------------------------------------------------------

    def plan_correction(
        self,
        poses: Mapping[int, ArrayLike],
        *,
        source: PoseSource,
        parent: int | None = None,
        propagate: bool = True,
        note: str = "",
        created_ns: int | None = None,
        covariances: Mapping[int, ArrayLike] | None = None,
    ) -> Revision:
        """A new revision (not yet committed) setting ``poses`` (``frame_id -> T_world_sensor``) on top of
        ``parent`` (default: head). With ``propagate`` every other frame gets the interpolated world-frame
        correction of the keyframes around it in time (module docstring); otherwise only ``poses`` change.
        ``covariances``: the 6x6 uncertainty of some of ``poses`` (:class:`Revision`).

        Raises StoreError for unknown frames or parent and TransformError for a non-rigid pose.
        """
        parent_id = self.head if parent is None else self._require_revision(parent, "parent revision")
        source = as_source(source)
        if not isinstance(poses, Mapping) or not poses:
            raise StoreError("a correction needs a non-empty mapping frame_id -> T_world_sensor")
        keys = [as_int(k, "correction frame id") for k in poses]
        unknown = sorted({k for k in keys if k not in self._known})
        if unknown:
            raise StoreError(f"correction names {len(unknown)} frame(s) not in the pose ledger: {preview(unknown)}")
        if len(set(keys)) != len(keys):
            raise StoreError("correction names a frame twice (e.g. as int and numpy int)")
        given = {
            k: geometry.as_rigid(T, f"correction pose of frame {k}") for k, T in zip(keys, poses.values(), strict=True)
        }
        key_ids = np.array(sorted(given), dtype=np.int64)
        key_poses = np.array([given[k] for k in key_ids.tolist()])

        # the new revision is made over its parent's frames and the frames it sets (module docstring); a frame the
        # parent does not place (stored later, or left out by a rollback) is not moved by propagation
        placed = self.members(parent_id)
        scope = np.union1d(placed, key_ids)
        # only frames the parent places have a correction (new pose against the parent's) to propagate: a frame it
        # does not place has no pose of the parent's, and its stored fallback is another world frame's (hostile
        # trial 18 B5: rows only for frames a rollback left out moved the head's frames by 1.3-1.6 m)
        anchors = np.isin(key_ids, placed)
        propagated: dict[int, NDArray[np.float64]] = {}
        if propagate and anchors.any() and len(key_ids) < len(scope):
            rows = self._index_of(scope)
            prop_ids, prop_poses = propagate_correction(scope, self.stamps_ns[rows], self.poses(parent_id)[rows],
                                                         key_ids[anchors], key_poses[anchors])
            propagated = {f: T for f, T in zip(prop_ids.tolist(), prop_poses, strict=True) if f not in given}
        elif propagate and len(key_ids) < len(scope):
            logger.warning("correction of revision %d: none of its %d frames is placed by revision %d, so there is no "
                           "correction to carry to that revision's frames: they keep its poses", self.head + 1,
                           len(key_ids), parent_id)
        revision = Revision(
            revision_id=self.head + 1,
            parent_id=parent_id,
            source=source,
            created_ns=time.time_ns() if created_ns is None else created_ns,
            note=note,
            set_directly=given,
            propagated=propagated,
            covariances=covariances or {},
            frames=scope,
        )
        logger.debug(
            "planned revision %d on %d (%s): %d set, %d propagated",
            revision.revision_id, parent_id, source.value, len(given), len(propagated),
        )
        return revision


    def commit(self, revision: Revision) -> Revision:
        """Append a planned revision after re-checking it against the ledger as it is now."""
        if not isinstance(revision, Revision):
            raise StoreError(f"commit expects a Revision, got {type(revision).__name__}")
        if revision.revision_id != self.head + 1:
            raise StoreError(
                f"cannot commit revision {revision.revision_id}: the next revision id is {self.head + 1} "
                "(was another revision committed after this one was planned?)"
            )
        parent = revision.parent_id
        if parent is None or not 0 <= parent <= self.head:
            raise StoreError(f"cannot commit revision {revision.revision_id}: parent {parent} does not exist")
        if revision.restores is not None and not 0 <= revision.restores <= self.head:
            raise StoreError(
                f"cannot commit revision {revision.revision_id}: restores unknown revision {revision.restores}"
            )
        changed = revision.changed_frame_ids
        unknown = changed[~np.isin(changed, self.frame_ids)].tolist()
        if unknown:
            raise StoreError(
                f"cannot commit revision {revision.revision_id}: frames {preview(unknown)} are not in the pose ledger"
            )
        if revision.frames is not None:
            recorded = revision.frames
            absent = recorded[~np.isin(recorded, self.frame_ids)].tolist()
            if absent:
                raise StoreError(f"cannot commit revision {revision.revision_id}: its frames {preview(absent)} are "
                                 "not in the pose ledger")
        elif revision.restores is not None:  # written before membership was recorded: the target's frames
            recorded = self.members(revision.restores)
        else:  # written before membership was recorded: the frames stored before it
            recorded = self.frame_ids
        self._committed.append(revision)
        self._known_at.append(len(self._order))
        self._recorded.append(readonly(np.array(recorded, dtype=np.int64, copy=True)))
        logger.info(
            "committed pose revision %d (parent %d, %s): %d set, %d propagated",
            revision.revision_id, parent, revision.source.value, len(revision.set_directly), len(revision.propagated),
        )
        return revision

    def covariances(self, revision_id: int) -> dict[int, NDArray[np.float64]]:
        """The pose uncertainty of each frame in ``revision_id``, where the revision that last set the frame's pose
        (on its ancestry) came with one (:attr:`Revision.covariances`, 6x6 ``[translation, rotation]``). A frame
        that revision propagated takes the covariance of the revision's keyframe nearest to it in time. Frames
        whose pose came from a revision without covariances (the odometry, a pose file) are absent."""
        rid = self._require_revision(revision_id)
        by_id = {r.revision_id: r for r in self._committed}
        out: dict[int, NDArray[np.float64]] = {}
        seen: set[int] = set()
        rev = by_id.get(rid)
        while rev is not None and rev.revision_id > 0:
            fresh = [int(f) for f in rev.changed_frame_ids if int(f) not in seen]
            seen.update(fresh)
            if rev.covariances and fresh:
                keys = np.array(sorted(rev.covariances), dtype=np.int64)
                key_stamps = self.stamps_ns[self._index_of(keys)]
                by_time = np.argsort(key_stamps, kind="stable")
                keys, key_stamps = keys[by_time], key_stamps[by_time]
                stamps = self.stamps_ns[self._index_of(np.array(fresh, dtype=np.int64))]
                pos = np.clip(np.searchsorted(key_stamps, stamps), 1, max(len(keys) - 1, 1))
                left = np.clip(pos - 1, 0, len(keys) - 1)
                right = np.clip(pos, 0, len(keys) - 1)
                nearest = np.where(np.abs(stamps - key_stamps[left]) <= np.abs(key_stamps[right] - stamps), left, right)
                for f, k in zip(fresh, nearest.tolist(), strict=True):
                    out[f] = rev.covariances[int(keys[k])]
            rev = by_id.get(rev.parent_id) if rev.parent_id is not None else None
        return out

    def plan_rollback(self, to: int, *, note: str = "", created_ns: int | None = None) -> Revision:
        """A new revision on head that restores revision ``to`` exactly: its frames are those ``to`` was made over
        (:meth:`members` without the frames stored after it, even when ``to`` is the head: rolling back to the head
        drops frames stored since, e.g. an interrupted append's), and it sets the pose of ``to`` for every one of them
        whose pose in head differs from it in any bit or that head does not place."""
        target = self._require_revision(to, "rollback target revision")
        head = self.head
        frames = self.members(target, later=False)
        rows = self._index_of(frames)
        P_to, P_head = self.poses(target)[rows], self.poses(head)[rows]
        differs = np.any(P_to.view(np.uint64) != P_head.view(np.uint64), axis=(1, 2))
        changed = np.flatnonzero(differs | ~np.isin(frames, self.members(head)))
        revision = Revision(
            revision_id=head + 1,
            parent_id=head,
            source=PoseSource.ROLLBACK,
            created_ns=time.time_ns() if created_ns is None else created_ns,
            note=note,
            set_directly=dict(zip(frames[changed].tolist(), P_to[changed], strict=True)),
            restores=target,
            frames=frames,
        )
        logger.debug(
            "planned rollback %d: head %d -> revision %d, %d frames", revision.revision_id, head, target, len(changed)
        )
        return revision

    # ---- comparisons -----------------------------------------------------------------------------------------

    def _difference(self, a: int, b: int) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """The frames both revisions place, and how far each moves and turns from ``a`` to ``b``."""
        ids = np.intersect1d(self.members(a), self.members(b))
        rows = self._index_of(ids)
        P_a, P_b = self.poses(a)[rows], self.poses(b)[rows]
        translation_m = np.linalg.norm(P_a[:, :3, 3] - P_b[:, :3, 3], axis=1)
        return ids, translation_m, geometry.relative_rotation_angle_rad(P_a, P_b)

    def diff(self, a: int, b: int) -> PoseDiff:
        """Per-frame position distance (m) and relative rotation angle (deg) between revisions ``a`` and ``b``, over
        the frames both place (:meth:`members`)."""
        ids, translation_m, rotation_rad = self._difference(a, b)
        return PoseDiff(readonly(ids), readonly(translation_m), readonly(np.degrees(rotation_rad)))

    def changed_frames(self, a: int, b: int, *, eps_m: float = 1e-9, eps_rad: float = 1e-9) -> NDArray[np.int64]:
        """Ids of the frames (placed by both) whose pose moves more than ``eps_m`` or turns more than ``eps_rad``
        from ``a`` to ``b``."""
        ids, translation_m, rotation_rad = self._difference(a, b)
        return ids[(translation_m > eps_m) | (rotation_rad > eps_rad)]

