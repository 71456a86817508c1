"""The pose ledger: every pose revision of every frame, kept in memory.

Revision 0 holds the poses that produced the frames (``add_frame``). Every later revision records only the
frames it changes, split into the poses it was given (``set_directly``) and the poses it derived from them
(``propagated``), plus its parent. A frame's pose in revision ``r`` is the pose set for it by the nearest
revision on ``r``'s ancestry chain (``r``, ``parent(r)``, ..., 1) that changes it, else its revision-0 pose;
so a correction may branch from an older revision and a rollback is just another revision.

Changing the ledger is two steps: ``plan_correction`` / ``plan_rollback`` validate and return a new
:class:`Revision` without adding it, and ``commit`` appends it. The store persists a planned revision
(``Revision.to_json``) first and commits it in memory only once that succeeded.

Correction propagation. For keyframes ``k`` given new poses ``N_k`` whose parent-revision poses are ``O_k``,
the world-frame correction of a keyframe is ``D_k = N_k @ inv(O_k)``. Frames are ordered by
``(stamp_ns, frame_id)``; a non-keyframe ``f`` (stamp ``t``) takes the keyframe ``a`` just before it and
``b`` just after it in that order. With only one of them it uses that keyframe's ``D`` (so it keeps its pose
relative to that keyframe exactly); with ``t_a == t_b`` it uses ``D_a``; otherwise
``D = interpolate_se3(D_a, D_b, alpha)`` with ``alpha = (t - t_a) / (t_b - t_a)``. Its new pose is
``D @ O_f``.
"""

from __future__ import annotations

import enum
import logging
import numbers
import time
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from driftmap import geometry
from driftmap.errors import StoreError, TransformError, parse_enum
from driftmap.frame import PoseSource
from driftmap.trajectory import Trajectory

logger = logging.getLogger(__name__)

#: Version of the dictionary layout written by :meth:`Revision.to_json`.
REVISION_SCHEMA_VERSION = 1

#: How many revisions' full pose arrays :meth:`PoseLedger.poses` keeps (least recently used are dropped).
POSE_CACHE_SIZE = 8

_EMPTY_IDS = np.zeros(0, dtype=np.int64)


def _preview(values: Iterable[Any], limit: int = 10) -> str:
    """``[1, 2, 3]`` or ``[1, 2, ..., 40] (40 in all)`` for error messages."""
    values = list(values)
    if len(values) <= limit:
        return str(values)
    return f"[{', '.join(str(v) for v in values[:limit])}, ...] ({len(values)} in all)"


def _as_int(value: Any, what: str) -> int:
    if type(value) is int:  # the common case, without the (slow) ABC check below
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise StoreError(f"{what} must be an integer, got {value!r}")
    return int(value)


def _as_source(value: Any) -> PoseSource:
    return parse_enum(PoseSource, value, "unknown pose source", StoreError)


def _readonly(array: NDArray[Any]) -> NDArray[Any]:
    array.setflags(write=False)
    return array


def _pose_table(poses: Mapping[Any, ArrayLike], what: str) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Sorted frame ids and the (K, 4, 4) read-only float64 stack of a ``frame_id -> 4x4`` mapping."""
    if not isinstance(poses, Mapping):
        raise StoreError(f"{what} must be a mapping frame_id -> 4x4 pose, got {type(poses).__name__}")
    if not poses:
        return _EMPTY_IDS, _readonly(np.zeros((0, 4, 4)))
    ids = np.fromiter((_as_int(k, f"{what}: frame id") for k in poses), dtype=np.int64, count=len(poses))
    if len(np.unique(ids)) != len(ids):
        raise StoreError(f"{what}: a frame id appears twice (e.g. as int and numpy int)")
    try:
        stack = np.array([np.asarray(v, dtype=np.float64) for v in poses.values()], dtype=np.float64)
    except ValueError as exc:
        raise TransformError(f"{what}: every pose must be a 4x4 matrix ({exc})") from exc
    if stack.shape[1:] != (4, 4):
        raise TransformError(f"{what}: every pose must be a 4x4 matrix, got a stack of shape {stack.shape}")
    order = np.argsort(ids, kind="stable")
    ids, stack = ids[order], np.ascontiguousarray(stack[order])
    geometry.require_rigid_stack(stack, ids, what)
    return _readonly(ids), _readonly(stack)


SAME_POSE_M = 1e-6
"""Pose differences below this translation (and :data:`SAME_POSE_DEG`) are text round-off, not a change (a TUM
file written with 9 decimals and read back moves poses by ~1e-9 m)."""
SAME_POSE_DEG = 1e-5


# --------------------------------------------------------------------------------------------------------------
# Revision
# --------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Revision:
    """One pose revision: the frames it changes and where the new poses came from.

    ``set_directly`` holds the poses a caller gave (``frame_id -> T_world_sensor``), ``propagated`` the poses
    derived from them; both are read-only mappings of read-only 4x4 float64 arrays and never share a frame.
    ``restores`` is the revision a rollback restores (``None`` otherwise). Revision 0 has no parent and sets the
    frames' own poses. Instances compare equal when every field is equal, matrices bit for bit.
    """

    revision_id: int
    parent_id: int | None
    source: PoseSource
    created_ns: int
    note: str = ""
    set_directly: Mapping[int, NDArray[np.float64]] = field(default_factory=dict, repr=False)
    propagated: Mapping[int, NDArray[np.float64]] = field(default_factory=dict, repr=False)
    restores: int | None = None
    # sorted changed ids, their poses and whether each was set directly (derived, for fast array access)
    _ids: NDArray[np.int64] = field(init=False, repr=False)
    _poses: NDArray[np.float64] = field(init=False, repr=False)
    _direct: NDArray[np.bool_] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        rid = _as_int(self.revision_id, "Revision.revision_id")
        if rid < 0:
            raise StoreError(f"Revision.revision_id must be >= 0, got {rid}")
        parent = None if self.parent_id is None else _as_int(self.parent_id, f"revision {rid}: parent_id")
        if rid == 0 and parent is not None:
            raise StoreError(f"revision 0 has no parent, got parent_id={parent}")
        if rid > 0 and (parent is None or not 0 <= parent < rid):
            raise StoreError(f"revision {rid}: parent_id must be an earlier revision (0..{rid - 1}), got {parent}")
        restores = None if self.restores is None else _as_int(self.restores, f"revision {rid}: restores")
        if restores is not None and not 0 <= restores < rid:
            raise StoreError(f"revision {rid}: restores must be an earlier revision (0..{rid - 1}), got {restores}")
        if not isinstance(self.note, str):
            raise StoreError(f"revision {rid}: note must be a string, got {type(self.note).__name__}")
        direct_ids, direct_poses = _pose_table(self.set_directly, f"revision {rid}: set_directly")
        prop_ids, prop_poses = _pose_table(self.propagated, f"revision {rid}: propagated")
        both = np.intersect1d(direct_ids, prop_ids)
        if both.size:
            raise StoreError(f"revision {rid}: frames {_preview(both.tolist())} are both set directly and propagated")
        ids = np.concatenate([direct_ids, prop_ids])
        order = np.argsort(ids, kind="stable")
        setattr_ = object.__setattr__
        setattr_(self, "revision_id", rid)
        setattr_(self, "parent_id", parent)
        setattr_(self, "source", _as_source(self.source))
        setattr_(self, "created_ns", _as_int(self.created_ns, f"revision {rid}: created_ns"))
        setattr_(self, "restores", restores)
        setattr_(self, "set_directly", MappingProxyType(dict(zip(direct_ids.tolist(), direct_poses, strict=True))))
        setattr_(self, "propagated", MappingProxyType(dict(zip(prop_ids.tolist(), prop_poses, strict=True))))
        setattr_(self, "_ids", _readonly(ids[order]))
        setattr_(self, "_poses", _readonly(np.concatenate([direct_poses, prop_poses])[order]))
        direct = np.concatenate([np.ones(len(direct_ids), dtype=bool), np.zeros(len(prop_ids), dtype=bool)])
        setattr_(self, "_direct", _readonly(direct[order]))

    @property
    def changed_frame_ids(self) -> NDArray[np.int64]:
        """Sorted ids of every frame this revision changes (set directly or propagated)."""
        return self._ids

    @property
    def n_changed(self) -> int:
        return len(self._ids)

    def __repr__(self) -> str:
        extra = "" if self.restores is None else f", restores={self.restores}"
        return (
            f"Revision(revision_id={self.revision_id}, parent_id={self.parent_id}, source={self.source.value}, "
            f"n_set_directly={len(self.set_directly)}, n_propagated={len(self.propagated)}{extra}, note={self.note!r})"
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Revision):
            return NotImplemented
        return (
            (self.revision_id, self.parent_id, self.source, self.created_ns, self.note, self.restores)
            == (other.revision_id, other.parent_id, other.source, other.created_ns, other.note, other.restores)
            and np.array_equal(self._ids, other._ids)
            and np.array_equal(self._direct, other._direct)
            and self._poses.tobytes() == other._poses.tobytes()
        )

    __hash__ = None  # type: ignore[assignment]  # mutable-looking payload; compare, don't hash

    # ---- JSON ------------------------------------------------------------------------------------------------

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict; each matrix is a row-major list of 16 Python floats, which ``json`` writes with
        the shortest repr that reads back as the same float64, so :meth:`from_json` restores it bit for bit."""

        def table(ids: NDArray[np.int64], poses: NDArray[np.float64]) -> dict[str, list[Any]]:
            return {"frame_ids": ids.tolist(), "T_world_sensor": poses.reshape(-1, 16).tolist()}

        direct = self._direct
        return {
            "schema_version": REVISION_SCHEMA_VERSION,
            "revision_id": self.revision_id,
            "parent_id": self.parent_id,
            "source": self.source.value,
            "created_ns": self.created_ns,
            "note": self.note,
            "restores": self.restores,
            "set_directly": table(self._ids[direct], self._poses[direct]),
            "propagated": table(self._ids[~direct], self._poses[~direct]),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Revision:
        """Inverse of :meth:`to_json`; anything malformed is a :class:`StoreError` naming the revision."""
        if not isinstance(data, Mapping):
            raise StoreError(f"revision JSON must be an object, got {type(data).__name__}")
        rid = data.get("revision_id", "?")
        version = data.get("schema_version")
        if version != REVISION_SCHEMA_VERSION:
            raise StoreError(
                f"revision {rid}: unsupported schema_version {version!r} (expected {REVISION_SCHEMA_VERSION})"
            )
        required = ("revision_id", "parent_id", "source", "created_ns", "note", "set_directly", "propagated")
        missing = [k for k in required if k not in data]
        if missing:
            raise StoreError(f"revision {rid}: JSON lacks {missing}")

        def table(name: str) -> dict[int, NDArray[np.float64]]:
            part = data[name]
            if not isinstance(part, Mapping) or "frame_ids" not in part or "T_world_sensor" not in part:
                raise StoreError(f"revision {rid}: {name} must hold 'frame_ids' and 'T_world_sensor'")
            ids, mats = part["frame_ids"], part["T_world_sensor"]
            if not isinstance(ids, list) or not isinstance(mats, list):
                raise StoreError(f"revision {rid}: {name}: 'frame_ids' and 'T_world_sensor' must be lists")
            if any(isinstance(i, bool) or not isinstance(i, int) for i in ids) or len(set(ids)) != len(ids):
                raise StoreError(f"revision {rid}: {name}: frame ids must be distinct integers")
            if len(ids) != len(mats):
                raise StoreError(f"revision {rid}: {name} has {len(ids)} frame ids but {len(mats)} matrices")
            if any(not isinstance(m, list) or len(m) != 16 for m in mats):
                raise StoreError(f"revision {rid}: {name}: every matrix must be a list of 16 numbers")
            if any(isinstance(x, bool) or not isinstance(x, (int, float)) for m in mats for x in m):
                raise StoreError(f"revision {rid}: {name}: matrices must hold numbers only")
            stack = np.array(mats, dtype=np.float64).reshape(-1, 4, 4)
            return dict(zip(ids, stack, strict=True))

        try:
            return cls(
                revision_id=data["revision_id"],
                parent_id=data["parent_id"],
                source=data["source"],
                created_ns=data["created_ns"],
                note=data["note"],
                set_directly=table("set_directly"),
                propagated=table("propagated"),
                restores=data.get("restores"),
            )
        except TransformError as exc:
            raise StoreError(f"revision {rid}: damaged pose in JSON: {exc}") from exc


# --------------------------------------------------------------------------------------------------------------
# Diff
# --------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PoseDiff:
    """Per-frame pose difference between two revisions, aligned with ``frame_ids``."""

    frame_ids: NDArray[np.int64]
    translation_m: NDArray[np.float64]
    rotation_deg: NDArray[np.float64]

    @property
    def max_translation_m(self) -> float:
        return float(self.translation_m.max()) if len(self.translation_m) else 0.0

    @property
    def max_rotation_deg(self) -> float:
        return float(self.rotation_deg.max()) if len(self.rotation_deg) else 0.0

    @property
    def n_changed(self) -> int:
        """Frames that moved by more than :data:`SAME_POSE_M` or turned by more than :data:`SAME_POSE_DEG`."""
        return int(np.count_nonzero((self.translation_m > SAME_POSE_M) | (self.rotation_deg > SAME_POSE_DEG)))


# --------------------------------------------------------------------------------------------------------------
# PoseLedger
# --------------------------------------------------------------------------------------------------------------


class PoseLedger:
    """Frames' revision-0 poses plus every committed pose revision (see the module docstring)."""

    def __init__(self, base_source: PoseSource = PoseSource.ODOMETRY, *, created_ns: int | None = None) -> None:
        self._base_source = _as_source(base_source)
        self._created_ns = time.time_ns() if created_ns is None else _as_int(created_ns, "created_ns")
        self._known: set[int] = set()
        self._frame_sources: set[PoseSource] = set()
        # frames arrive one at a time: appended to these lists and merged into the sorted arrays on demand
        self._pending_ids: list[int] = []
        self._pending_stamps: list[int] = []
        self._pending_poses: list[NDArray[np.float64]] = []
        self._ids: NDArray[np.int64] = _readonly(np.zeros(0, dtype=np.int64))
        self._stamps: NDArray[np.int64] = _readonly(np.zeros(0, dtype=np.int64))
        self._base: NDArray[np.float64] = _readonly(np.zeros((0, 4, 4)))
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
        fid = _as_int(frame_id, "frame_id")
        stamp = _as_int(stamp_ns, f"frame {fid}: stamp_ns")
        T = geometry.as_rigid(T_world_sensor, f"frame {fid}: T_world_sensor")
        if fid in self._known:
            raise StoreError(f"frame {fid} is already in the pose ledger")
        self._known.add(fid)
        if source is not None:
            self._frame_sources.add(_as_source(source))
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
        self._ids, self._stamps = _readonly(ids[order]), _readonly(stamps[order])
        self._base = _readonly(base[order])
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
        rid = _as_int(revision_id, what)
        if not 0 <= rid <= self.head:
            raise StoreError(f"{what} {rid} does not exist (the ledger has revisions 0..{self.head})")
        return rid

    def _parent_of(self, rid: int) -> int:
        parent = self._committed[rid - 1].parent_id
        assert parent is not None
        return parent

    # ---- poses -----------------------------------------------------------------------------------------------

    def poses(self, revision_id: int) -> NDArray[np.float64]:
        """(M, 4, 4) read-only ``T_world_sensor`` of every frame in a revision, aligned with :attr:`frame_ids`."""
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
            out[self._index_of(rev._ids)] = rev._poses
        out = _readonly(out)
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
            poses = _readonly(grown)
            self._pose_cache[rid] = (self._ids, poses)
        return poses

    def pose(self, revision_id: int, frame_id: int) -> NDArray[np.float64]:
        """Read-only ``T_world_sensor`` of one frame in one revision."""
        rid = self._require_revision(revision_id)
        fid = _as_int(frame_id, "frame_id")
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
    ) -> Revision:
        """A new revision (not yet committed) setting ``poses`` (``frame_id -> T_world_sensor``) on top of
        ``parent`` (default: head). With ``propagate`` every other frame gets the interpolated world-frame
        correction of the keyframes around it in time (module docstring); otherwise only ``poses`` change.

        Raises StoreError for unknown frames or parent and TransformError for a non-rigid pose.
        """
        parent_id = self.head if parent is None else self._require_revision(parent, "parent revision")
        source = _as_source(source)
        if not isinstance(poses, Mapping) or not poses:
            raise StoreError("a correction needs a non-empty mapping frame_id -> T_world_sensor")
        keys = [_as_int(k, "correction frame id") for k in poses]
        unknown = sorted({k for k in keys if k not in self._known})
        if unknown:
            raise StoreError(f"correction names {len(unknown)} frame(s) not in the pose ledger: {_preview(unknown)}")
        if len(set(keys)) != len(keys):
            raise StoreError("correction names a frame twice (e.g. as int and numpy int)")
        given = {
            k: geometry.as_rigid(T, f"correction pose of frame {k}") for k, T in zip(keys, poses.values(), strict=True)
        }
        key_ids = np.array(sorted(given), dtype=np.int64)
        key_poses = np.array([given[k] for k in key_ids.tolist()])

        propagated: dict[int, NDArray[np.float64]] = {}
        if propagate and len(key_ids) < self.n_frames:
            prop_ids, prop_poses = self._propagate(self.poses(parent_id), key_ids, key_poses)
            propagated = dict(zip(prop_ids.tolist(), prop_poses, strict=True))
        revision = Revision(
            revision_id=self.head + 1,
            parent_id=parent_id,
            source=source,
            created_ns=time.time_ns() if created_ns is None else created_ns,
            note=note,
            set_directly=given,
            propagated=propagated,
        )
        logger.debug(
            "planned revision %d on %d (%s): %d set, %d propagated",
            revision.revision_id, parent_id, source.value, len(given), len(propagated),
        )
        return revision

    def _propagate(
        self, O: NDArray[np.float64], key_ids: NDArray[np.int64], key_poses: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Ids and new poses of every non-keyframe (vectorised; see the module docstring for the rule)."""
        ids, stamps = self.frame_ids, self.stamps_ns
        n = len(ids)
        key_idx = self._index_of(key_ids)
        D_key = key_poses @ geometry.invert(O[key_idx])  # world-frame correction of each keyframe
        key_row = np.full(n, -1, dtype=np.intp)
        key_row[key_idx] = np.arange(len(key_idx))

        # neighbouring keyframes in (stamp, frame_id) order, found by forward / backward fill
        order = np.lexsort((ids, stamps))
        is_key = key_row[order] >= 0
        pos = np.arange(n)
        prev_pos = np.maximum.accumulate(np.where(is_key, pos, -1))
        next_pos = np.minimum.accumulate(np.where(is_key, pos, n)[::-1])[::-1]
        prev_key = np.full(n, -1, dtype=np.intp)
        next_key = np.full(n, -1, dtype=np.intp)
        prev_key[order] = np.where(prev_pos >= 0, key_row[order[np.clip(prev_pos, 0, n - 1)]], -1)
        next_key[order] = np.where(next_pos < n, key_row[order[np.clip(next_pos, 0, n - 1)]], -1)

        f = np.flatnonzero(key_row < 0)  # non-keyframes, in frame-id order
        a, b = prev_key[f], next_key[f]
        D = np.empty((len(f), 4, 4))
        only_a, only_b = b < 0, a < 0
        D[only_a] = D_key[a[only_a]]
        D[only_b] = D_key[b[only_b]]
        both = np.flatnonzero((a >= 0) & (b >= 0))
        if both.size:
            ka, kb = a[both], b[both]
            t = stamps[f[both]]
            t_a, t_b = stamps[key_idx[ka]], stamps[key_idx[kb]]
            span = t_b - t_a
            alpha = np.where(span > 0, (t - t_a) / np.where(span > 0, span, 1), 0.0)
            # one relative twist per keyframe interval; identical corrections need no interpolation at all
            pairs, inverse = np.unique(np.stack([ka, kb], axis=1), axis=0, return_inverse=True)
            inverse = inverse.reshape(-1)
            Da, Db = D_key[pairs[:, 0]], D_key[pairs[:, 1]]
            xi = geometry.se3_log(geometry.invert(Da) @ Db)
            xi[np.all(Da == Db, axis=(1, 2))] = 0.0
            D_both = D_key[ka] @ geometry.se3_exp(alpha[:, None] * xi[inverse])
            # exactly on a keyframe's stamp: that keyframe's correction, bit for bit
            at_a, at_b = alpha == 0.0, alpha == 1.0
            D_both[at_a] = D_key[ka[at_a]]
            D_both[at_b] = D_key[kb[at_b]]
            D[both] = D_both
        new = D @ O[f]
        new[:, 3] = (0.0, 0.0, 0.0, 1.0)
        return ids[f], new

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
                f"cannot commit revision {revision.revision_id}: frames {_preview(unknown)} are not in the pose ledger"
            )
        self._committed.append(revision)
        logger.info(
            "committed pose revision %d (parent %d, %s): %d set, %d propagated",
            revision.revision_id, parent, revision.source.value, len(revision.set_directly), len(revision.propagated),
        )
        return revision

    def plan_rollback(self, to: int, *, note: str = "", created_ns: int | None = None) -> Revision:
        """A new revision on head that restores revision ``to`` exactly: it sets the pose of ``to`` for every
        frame whose pose in head differs from it in any bit."""
        target = self._require_revision(to, "rollback target revision")
        head = self.head
        P_to, P_head = self.poses(target), self.poses(head)
        differs = np.any(P_to.view(np.uint64) != P_head.view(np.uint64), axis=(1, 2))
        changed = np.flatnonzero(differs)
        revision = Revision(
            revision_id=head + 1,
            parent_id=head,
            source=PoseSource.ROLLBACK,
            created_ns=time.time_ns() if created_ns is None else created_ns,
            note=note,
            set_directly=dict(zip(self.frame_ids[changed].tolist(), P_to[changed], strict=True)),
            restores=target,
        )
        logger.debug(
            "planned rollback %d: head %d -> revision %d, %d frames", revision.revision_id, head, target, len(changed)
        )
        return revision

    # ---- comparisons -----------------------------------------------------------------------------------------

    def _difference(self, a: int, b: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        P_a, P_b = self.poses(a), self.poses(b)
        translation_m = np.linalg.norm(P_a[:, :3, 3] - P_b[:, :3, 3], axis=1)
        return translation_m, geometry.relative_rotation_angle_rad(P_a, P_b)

    def diff(self, a: int, b: int) -> PoseDiff:
        """Per-frame position distance (m) and relative rotation angle (deg) between revisions ``a`` and ``b``."""
        translation_m, rotation_rad = self._difference(a, b)
        return PoseDiff(self.frame_ids, _readonly(translation_m), _readonly(np.degrees(rotation_rad)))

    def changed_frames(self, a: int, b: int, *, eps_m: float = 1e-9, eps_rad: float = 1e-9) -> NDArray[np.int64]:
        """Ids of the frames whose pose moves more than ``eps_m`` or turns more than ``eps_rad`` from ``a`` to ``b``."""
        translation_m, rotation_rad = self._difference(a, b)
        return self.frame_ids[(translation_m > eps_m) | (rotation_rad > eps_rad)]


# --------------------------------------------------------------------------------------------------------------
# Importing poses from a trajectory file
# --------------------------------------------------------------------------------------------------------------


class PoseMatchMode(enum.Enum):
    """How rows of a trajectory file are matched to stored frames."""

    STAMP = "stamp"  #: nearest stamp within a tolerance
    INDEX = "index"  #: row i (0-based data row) is frame_id i


@dataclass(frozen=True, slots=True)
class PoseMatch:
    """Result of :func:`match_trajectory`: ``poses`` (``frame_id -> T``) and ``rows`` (``frame_id -> file row``)
    for the matched frames, the file rows that matched no stored frame and the stored frames with no row."""

    poses: dict[int, NDArray[np.float64]]
    unmatched_rows: list[int]
    unmatched_frames: list[int]
    rows: dict[int, int] = field(default_factory=dict)

    @property
    def n_matched(self) -> int:
        return len(self.poses)


def match_pose_rows(
    trajectory: Trajectory,
    format: str,
    frame_ids: ArrayLike,
    stamps_ns: ArrayLike | None,
    *,
    match: PoseMatchMode | str,
    max_dt_ns: int = 10_000_000,
) -> PoseMatch:
    """:func:`match_trajectory` for a pose file read as ``format`` (``correct``, ``diagnose --gt``): a Redwood
    ``.log`` names its frames (the ``i`` of each ``i j n`` line), so ``match="index"`` takes those ids rather than
    the row numbers; every other format as :func:`match_trajectory` (``index``: row i is frame_id i)."""
    mode = parse_enum(PoseMatchMode, match, "unknown pose match mode", StoreError)
    if format == "redwood" and mode is PoseMatchMode.INDEX:
        ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        named = trajectory.frame_ids if trajectory.frame_ids is not None else np.arange(len(trajectory))
        return match_trajectory(Trajectory(np.asarray(named, dtype=np.int64), trajectory.poses, trajectory.frame_ids),
                                ids, ids, match=PoseMatchMode.STAMP, max_dt_ns=0)  # the same id, exactly
    return match_trajectory(trajectory, frame_ids, stamps_ns, match=mode, max_dt_ns=max_dt_ns)


def stamp_ranges_text(trajectory: Trajectory, stamps_ns: ArrayLike) -> str:
    """The file's and the frames' stamp ranges, for a message about stamps that do not meet."""
    def span(values: NDArray[np.int64]) -> str:
        return f"{values.min() / 1e9:.3f}..{values.max() / 1e9:.3f} s" if values.size else "none"
    return (f"the file's stamps span {span(np.asarray(trajectory.stamps_ns, dtype=np.int64))}, the frames' "
            f"{span(np.asarray(stamps_ns, dtype=np.int64))}")


def match_trajectory(
    trajectory: Trajectory,
    frame_ids: ArrayLike,
    stamps_ns: ArrayLike | None,
    *,
    match: PoseMatchMode | str,
    max_dt_ns: int = 10_000_000,
) -> PoseMatch:
    """Match the rows of ``trajectory`` to stored frames (``frame_ids`` with their ``stamps_ns``).

    ``match="index"``: row i is the pose of frame_id i (``stamps_ns`` is not used), so a full-length file
    serves a store built from a slice; rows for ids not stored are reported in ``unmatched_rows``.
    ``match="stamp"``: each frame takes the row with the nearest stamp (halfway between two rows: the earlier
    one) if ``|dt| <= max_dt_ns``; a row is never given to two frames (the closer one keeps it, ties to the
    lower frame id; the other frame is unmatched rather than moved to its second-best row).
    """
    mode = parse_enum(PoseMatchMode, match, "unknown pose match mode", StoreError)
    ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
    if len(np.unique(ids)) != len(ids):
        raise StoreError("match_trajectory: frame_ids contain duplicates")
    n_rows = len(trajectory)

    if mode is PoseMatchMode.INDEX:
        ok = (ids >= 0) & (ids < n_rows)
        frame_idx = np.flatnonzero(ok)
        row_of = ids[ok]
    else:
        if stamps_ns is None:
            raise StoreError("match_trajectory: matching by stamp needs the frames' stamps_ns")
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        if len(stamps) != len(ids):
            raise StoreError(f"match_trajectory: {len(ids)} frame ids but {len(stamps)} stamps")
        max_dt = _as_int(max_dt_ns, "max_dt_ns")
        if max_dt < 0:
            raise StoreError(f"max_dt_ns must be >= 0, got {max_dt}")
        if n_rows == 0 or len(ids) == 0:
            frame_idx, row_of = np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
        else:
            row_stamps = np.asarray(trajectory.stamps_ns, dtype=np.int64)
            by_stamp = np.argsort(row_stamps, kind="stable")
            sorted_stamps = row_stamps[by_stamp]
            j = np.searchsorted(sorted_stamps, stamps)
            left, right = np.clip(j - 1, 0, n_rows - 1), np.clip(j, 0, n_rows - 1)
            dt_left, dt_right = np.abs(stamps - sorted_stamps[left]), np.abs(sorted_stamps[right] - stamps)
            take_right = dt_right < dt_left
            row = by_stamp[np.where(take_right, right, left)]
            dt = np.where(take_right, dt_right, dt_left)
            candidates = np.flatnonzero(dt <= max_dt)
            # one row per frame at most: per row keep the closest frame (then the lowest id)
            order = candidates[np.lexsort((ids[candidates], dt[candidates], row[candidates]))]
            first = np.ones(len(order), dtype=bool)
            first[1:] = row[order][1:] != row[order][:-1]
            frame_idx = np.sort(order[first])
            row_of = row[frame_idx]

    used = np.zeros(n_rows, dtype=bool)
    used[row_of] = True
    unmatched = np.ones(len(ids), dtype=bool)
    unmatched[frame_idx] = False
    matched_ids = ids[frame_idx].tolist()
    result = PoseMatch(
        poses={
            fid: np.array(trajectory.poses[r], dtype=np.float64)
            for fid, r in zip(matched_ids, row_of.tolist(), strict=True)
        },
        unmatched_rows=np.flatnonzero(~used).tolist(),
        unmatched_frames=np.sort(ids[unmatched]).tolist(),
        rows=dict(zip(matched_ids, row_of.tolist(), strict=True)),
    )
    logger.debug(
        "matched %d of %d frames to %d trajectory rows by %s (%d rows unmatched)",
        result.n_matched, len(ids), n_rows, mode.value, len(result.unmatched_rows),
    )
    return result
