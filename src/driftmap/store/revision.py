"""Pose revisions as records: :class:`Revision` (one revision: the poses it sets and where they came from, with its
JSON form as stored in a segment) and :class:`PoseDiff` (how two revisions' poses differ). The ledger that holds
them is :mod:`driftmap.store.ledger`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from driftmap import geometry
from driftmap.errors import StoreError, TransformError
from driftmap.frame import PoseSource
from driftmap.store.values import as_int, as_source, preview, readonly

#: Version of the dictionary layout written by :meth:`Revision.to_json`.
REVISION_SCHEMA_VERSION = 1

_EMPTY_IDS = np.zeros(0, dtype=np.int64)


def _pose_table(poses: Mapping[Any, ArrayLike], what: str) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Sorted frame ids and the (K, 4, 4) read-only float64 stack of a ``frame_id -> 4x4`` mapping."""
    if not isinstance(poses, Mapping):
        raise StoreError(f"{what} must be a mapping frame_id -> 4x4 pose, got {type(poses).__name__}")
    if not poses:
        return _EMPTY_IDS, readonly(np.zeros((0, 4, 4)))
    ids = np.fromiter((as_int(k, f"{what}: frame id") for k in poses), dtype=np.int64, count=len(poses))
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
    return readonly(ids), readonly(stack)


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
    frames' own poses. ``covariances`` (optional) holds the uncertainty of poses set directly, as the pose graph
    that made them gives it (GTSAM marginals): ``frame_id -> 6x6`` in driftmap order ``[translation, rotation]``
    (m^2, rad^2), in the frame's own sensor frame. ``frames`` (optional) are the frames the revision is a pose
    estimate for (its members: sorted ids, a superset of the frames it changes); frames stored later, or left out by a
    rollback, are not in it. ``None``: not recorded (revisions written before driftmap recorded it); the ledger then
    takes the frames stored before the revision. Instances compare equal when every field is equal, matrices bit for
    bit.
    """

    revision_id: int
    parent_id: int | None
    source: PoseSource
    created_ns: int
    note: str = ""
    set_directly: Mapping[int, NDArray[np.float64]] = field(default_factory=dict, repr=False)
    propagated: Mapping[int, NDArray[np.float64]] = field(default_factory=dict, repr=False)
    restores: int | None = None
    covariances: Mapping[int, NDArray[np.float64]] = field(default_factory=dict, repr=False)
    frames: NDArray[np.int64] | None = field(default=None, repr=False)
    # sorted changed ids, their poses and whether each was set directly (derived, for fast array access)
    _ids: NDArray[np.int64] = field(init=False, repr=False)
    _poses: NDArray[np.float64] = field(init=False, repr=False)
    _direct: NDArray[np.bool_] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        rid = as_int(self.revision_id, "Revision.revision_id")
        if rid < 0:
            raise StoreError(f"Revision.revision_id must be >= 0, got {rid}")
        parent = None if self.parent_id is None else as_int(self.parent_id, f"revision {rid}: parent_id")
        if rid == 0 and parent is not None:
            raise StoreError(f"revision 0 has no parent, got parent_id={parent}")
        if rid > 0 and (parent is None or not 0 <= parent < rid):
            raise StoreError(f"revision {rid}: parent_id must be an earlier revision (0..{rid - 1}), got {parent}")
        restores = None if self.restores is None else as_int(self.restores, f"revision {rid}: restores")
        if restores is not None and not 0 <= restores < rid:
            raise StoreError(f"revision {rid}: restores must be an earlier revision (0..{rid - 1}), got {restores}")
        if not isinstance(self.note, str):
            raise StoreError(f"revision {rid}: note must be a string, got {type(self.note).__name__}")
        direct_ids, direct_poses = _pose_table(self.set_directly, f"revision {rid}: set_directly")
        prop_ids, prop_poses = _pose_table(self.propagated, f"revision {rid}: propagated")
        both = np.intersect1d(direct_ids, prop_ids)
        if both.size:
            raise StoreError(f"revision {rid}: frames {preview(both.tolist())} are both set directly and propagated")
        ids = np.concatenate([direct_ids, prop_ids])
        order = np.argsort(ids, kind="stable")
        setattr_ = object.__setattr__
        setattr_(self, "revision_id", rid)
        setattr_(self, "parent_id", parent)
        setattr_(self, "source", as_source(self.source))
        setattr_(self, "created_ns", as_int(self.created_ns, f"revision {rid}: created_ns"))
        setattr_(self, "restores", restores)
        setattr_(self, "set_directly", MappingProxyType(dict(zip(direct_ids.tolist(), direct_poses, strict=True))))
        setattr_(self, "propagated", MappingProxyType(dict(zip(prop_ids.tolist(), prop_poses, strict=True))))
        setattr_(self, "covariances", MappingProxyType(_covariance_table(self.covariances, direct_ids, rid)))
        setattr_(self, "_ids", readonly(ids[order]))
        setattr_(self, "frames", _member_ids(self.frames, self._ids, rid))
        setattr_(self, "_poses", readonly(np.concatenate([direct_poses, prop_poses])[order]))
        direct = np.concatenate([np.ones(len(direct_ids), dtype=bool), np.zeros(len(prop_ids), dtype=bool)])
        setattr_(self, "_direct", readonly(direct[order]))

    @property
    def changed_frame_ids(self) -> NDArray[np.int64]:
        """Sorted ids of every frame this revision changes (set directly or propagated)."""
        return self._ids

    @property
    def changed_poses(self) -> NDArray[np.float64]:
        """The (K, 4, 4) read-only poses of :attr:`changed_frame_ids`, in that order."""
        return self._poses

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
            and sorted(self.covariances) == sorted(other.covariances)
            and all(self.covariances[k].tobytes() == other.covariances[k].tobytes() for k in self.covariances)
            and (self.frames is None) == (other.frames is None)
            and (self.frames is None or np.array_equal(self.frames, other.frames))
        )

    __hash__ = None  # type: ignore[assignment]  # mutable-looking payload; compare, don't hash

    # ---- JSON ------------------------------------------------------------------------------------------------

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict; each matrix is a row-major list of 16 Python floats, which ``json`` writes with
        the shortest repr that reads back as the same float64, so :meth:`from_json` restores it bit for bit."""

        def table(ids: NDArray[np.int64], poses: NDArray[np.float64]) -> dict[str, list[Any]]:
            return {"frame_ids": ids.tolist(), "T_world_sensor": poses.reshape(-1, 16).tolist()}

        direct = self._direct
        out = {
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
        if self.covariances:  # absent when none: revisions without keep the layout they always had
            ids = sorted(self.covariances)
            out["covariances"] = {"frame_ids": ids, "covariance_6x6": [self.covariances[k].ravel().tolist() for k in ids]}
        if self.frames is not None:  # absent when not recorded (as revisions written before it was)
            out["frames"] = id_ranges(self.frames)
        return out

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
                covariances=_covariances_json(data.get("covariances"), rid),
                revision_id=data["revision_id"],
                parent_id=data["parent_id"],
                source=data["source"],
                created_ns=data["created_ns"],
                note=data["note"],
                set_directly=table("set_directly"),
                propagated=table("propagated"),
                restores=data.get("restores"),
                frames=_frames_json(data.get("frames"), rid),
            )
        except TransformError as exc:
            raise StoreError(f"revision {rid}: damaged pose in JSON: {exc}") from exc


def id_ranges(ids: NDArray[np.int64]) -> list[list[int]]:
    """Sorted distinct ids as inclusive ranges ``[[first, last], ...]`` (a session's frames are one range)."""
    if len(ids) == 0:
        return []
    breaks = np.flatnonzero(np.diff(ids) != 1)
    firsts = np.concatenate([ids[:1], ids[breaks + 1]])
    lasts = np.concatenate([ids[breaks], ids[-1:]])
    return [[int(a), int(b)] for a, b in zip(firsts, lasts, strict=True)]


def _frames_json(part: Any, rid: Any) -> NDArray[np.int64] | None:
    """The member ids of a revision's JSON ``frames`` (inclusive ranges), or ``None`` when absent."""
    if part is None:
        return None
    if not isinstance(part, list) or any(
            not isinstance(r, list) or len(r) != 2 or any(isinstance(x, bool) or not isinstance(x, int) for x in r)
            or r[0] > r[1] for r in part):
        raise StoreError(f"revision {rid}: frames must be a list of [first, last] integer ranges")
    total = sum(b - a + 1 for a, b in part)
    if total > 1 << 31:
        raise StoreError(f"revision {rid}: frames name {total} frames, more than a store can hold")
    if not part:
        return _EMPTY_IDS
    return np.concatenate([np.arange(a, b + 1, dtype=np.int64) for a, b in part])


def _member_ids(frames: Any, changed: NDArray[np.int64], rid: int) -> NDArray[np.int64] | None:
    """Validated sorted distinct read-only member ids holding every changed frame, or ``None``."""
    if frames is None:
        return None
    try:
        ids = np.asarray(frames)
        if ids.size and not np.issubdtype(ids.dtype, np.integer):
            raise TypeError(ids.dtype)
        ids = ids.astype(np.int64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise StoreError(f"revision {rid}: frames must be frame ids (integers)") from exc
    if len(ids) > 1 and not np.all(np.diff(ids) > 0):
        ids = np.unique(ids)
    outside = np.setdiff1d(changed, ids)
    if outside.size:
        raise StoreError(f"revision {rid}: changes frames {preview(outside.tolist())} that are not among its frames")
    return readonly(np.array(ids, copy=True))


def _covariance_table(covariances: Mapping[Any, ArrayLike], set_ids: NDArray[np.int64],
                      rid: int) -> dict[int, NDArray[np.float64]]:
    """Validated read-only 6x6 covariances of frames set directly: finite, symmetric (symmetrised), no negative
    variance."""
    if not isinstance(covariances, Mapping):
        raise StoreError(f"revision {rid}: covariances must be a mapping frame_id -> 6x6")
    out: dict[int, NDArray[np.float64]] = {}
    for key, value in covariances.items():
        fid = as_int(key, f"revision {rid}: covariance frame id")
        if fid not in set_ids:
            raise StoreError(f"revision {rid}: a covariance for frame {fid}, whose pose the revision does not set")
        try:
            cov = np.array(value, dtype=np.float64).reshape(6, 6)
        except (TypeError, ValueError) as exc:
            raise StoreError(f"revision {rid}: covariance of frame {fid} is not 6x6 numbers") from exc
        scale = float(np.abs(cov).max()) if np.all(np.isfinite(cov)) else np.inf
        if not np.isfinite(scale) or float(np.abs(cov - cov.T).max()) > 1e-9 * max(scale, 1e-12) \
                or np.any(np.diag(cov) < 0):
            raise StoreError(f"revision {rid}: covariance of frame {fid} is not a finite symmetric 6x6 with "
                             "non-negative variances")
        out[fid] = readonly(0.5 * (cov + cov.T))
    return out


def _covariances_json(part: Any, rid: Any) -> dict[int, Any]:
    if part is None:
        return {}
    if not isinstance(part, Mapping) or not isinstance(part.get("frame_ids"), list) \
            or not isinstance(part.get("covariance_6x6"), list):
        raise StoreError(f"revision {rid}: covariances must hold the lists 'frame_ids' and 'covariance_6x6'")
    ids, covs = part["frame_ids"], part["covariance_6x6"]
    if len(ids) != len(covs) or any(not isinstance(c, list) or len(c) != 36 for c in covs) \
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for c in covs for x in c):
        raise StoreError(f"revision {rid}: covariances: one list of 36 numbers per frame id")
    if any(isinstance(i, bool) or not isinstance(i, int) for i in ids) or len(set(ids)) != len(ids):
        raise StoreError(f"revision {rid}: covariances: frame ids must be distinct integers")
    return dict(zip(ids, covs, strict=True))


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


