"""A TF buffer: the transform tree of a ROS log, queried like ``tf2``'s ``lookupTransform``.

Edges are ``parent -> child`` transforms ``T_parent_child`` (``p_parent = T_parent_child @ p_child``), as in
``geometry_msgs/msg/TransformStamped`` (``header.frame_id`` is the parent, ``child_frame_id`` the child).
An edge is either **static** (``/tf_static``: one transform, valid at every time) or **dynamic** (``/tf``:
samples at stamps). Every child has exactly one parent, so the frames form a forest;
:meth:`TfBuffer.lookup` walks from both frames up to their common ancestor and composes the edges on the
way, each dynamic edge evaluated at the requested stamp:

* a stamp equal to a sample returns that sample exactly;
* between two samples the edge is interpolated on SE(3) (:func:`driftmap.geometry.interpolate_se3`:
  constant-velocity screw motion; ``tf2`` interpolates translation and rotation separately, the two agree
  to first order for the short gaps between TF samples);
* outside an edge's sample range there is **no extrapolation**: :class:`TfError` names the two frames
  asked for, the edge that has no data and the time range it covers.

Frame names are normalised by dropping a leading ``/`` (ROS 1 ``tf`` allowed ``/base_link``; ``tf2`` does not).
Times are int nanoseconds.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.errors import TfError

logger = logging.getLogger(__name__)


def normalize_frame(frame: str) -> str:
    """``"/base_link"`` -> ``"base_link"`` (tf2 frame ids have no leading slash)."""
    return str(frame).lstrip("/")


QUATERNION_NORM_TOLERANCE = 1e-2
"""A quaternion read from a log must have ``abs(|q| - 1) <= QUATERNION_NORM_TOLERANCE`` (then it is normalised).
Looser than the pose files' 1e-3 (:mod:`driftmap.trajectory`): a log's publishers are not ours to fix and some
write quaternions of a few digits; a norm as far from 1 as this is a writer's bug (an unnormalised or half-filled
quaternion), not rounding."""


def transforms_from_tum(
    translations_m: ArrayLike,
    quats_xyzw: ArrayLike,
    what: str = "transform",
    *,
    stamps_ns: ArrayLike | None = None,
    norm_tolerance: float | None = QUATERNION_NORM_TOLERANCE,
) -> NDArray[np.float64]:
    """(N, 4, 4) transforms from (N, 3) translations and (N, 4) ``x y z w`` quaternions (normalised here).

    Raises :class:`TfError` naming ``what`` (and the sample's stamp, when ``stamps_ns`` are given) when a quaternion
    is zero or not finite, or its norm is off 1 by more than ``norm_tolerance`` (``None``: any non-zero norm).
    """
    t = np.asarray(translations_m, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4)
    stamps = None if stamps_ns is None else np.asarray(stamps_ns, dtype=np.int64).reshape(-1)

    def sample(k: int) -> str:
        if stamps is None or k >= len(stamps):
            return f"sample {k}"
        return f"sample {k} (stamp {_fmt_ns(int(stamps[k]))})"

    norms = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~np.isfinite(norms) | (norms < 1e-12) | ~np.all(np.isfinite(t), axis=1))
    if bad.size:
        raise TfError(
            f"{what}: {sample(int(bad[0]))} has a zero or non-finite quaternion/translation "
            f"(q={q[bad[0]].tolist()}, t={t[bad[0]].tolist()})"
        )
    if norm_tolerance is not None:
        off = np.flatnonzero(np.abs(norms - 1.0) > norm_tolerance)
        if off.size:
            k = int(off[0])
            more = f"; {off.size} such samples" if off.size > 1 else ""
            raise TfError(
                f"{what}: {sample(k)} has a quaternion of norm {norms[k]:.4f}, expected 1 (within "
                f"{norm_tolerance:g}; q={q[k].tolist()}){more}"
            )
    T = np.tile(np.eye(4), (len(t), 1, 1))
    if len(t):
        T[:, :3, :3] = Rotation.from_quat(q / norms[:, None]).as_matrix()
        T[:, :3, 3] = t
    return T


def _fmt_ns(stamp_ns: int) -> str:
    s, ns = divmod(int(stamp_ns), 1_000_000_000)
    return f"{stamp_ns} ns ({s}.{ns:09d} s)"


@dataclass(frozen=True)
class TransformSeries:
    """Timed samples of one transform ``T_parent_child`` (a dynamic TF edge, an odometry or pose topic).

    ``stamps_ns`` are strictly increasing (build with :meth:`from_samples`, which sorts and de-duplicates).
    """

    parent_frame: str
    child_frame: str
    stamps_ns: NDArray[np.int64]
    T_parent_child: NDArray[np.float64]
    """(N, 4, 4)."""
    what: str = ""
    """How to name the series in errors (e.g. the topic)."""

    @staticmethod
    def from_samples(
        parent_frame: str, child_frame: str, stamps_ns: ArrayLike, T_parent_child: ArrayLike, what: str = ""
    ) -> TransformSeries:
        """Sort by stamp; of several samples with the same stamp the last one given wins (like a re-sent TF)."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        T = np.asarray(T_parent_child, dtype=np.float64).reshape(-1, 4, 4)
        if len(stamps) != len(T):
            raise TfError(
                f"{what or parent_frame + ' -> ' + child_frame}: {len(stamps)} stamps but {len(T)} transforms"
            )
        order = np.argsort(stamps, kind="stable")
        stamps, T = stamps[order], T[order]
        if len(stamps) > 1:
            keep = np.append(stamps[1:] != stamps[:-1], True)  # last of each run of equal stamps
            n_dup = int(len(stamps) - np.count_nonzero(keep))
            if n_dup:
                logger.debug(
                    "%s -> %s: %d samples with a repeated stamp; the last one wins", parent_frame, child_frame, n_dup
                )
            stamps, T = stamps[keep], T[keep]
        stamps.setflags(write=False)
        T.setflags(write=False)
        return TransformSeries(normalize_frame(parent_frame), normalize_frame(child_frame), stamps, T, what)

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def time_range_ns(self) -> tuple[int, int]:
        return int(self.stamps_ns[0]), int(self.stamps_ns[-1])

    def _describe(self) -> str:
        name = f"{self.parent_frame} -> {self.child_frame}"
        return f"{name} ({self.what})" if self.what else name

    def first_uncovered(self, stamps_ns: NDArray[np.int64]) -> int | None:
        """The first of ``stamps_ns`` outside the samples' range (any, without samples); ``None`` if all are in it."""
        q = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        if len(self.stamps_ns) == 0:
            return int(q[0]) if q.size else None
        outside = np.flatnonzero((q < self.stamps_ns[0]) | (q > self.stamps_ns[-1]))
        return int(q[outside[0]]) if outside.size else None

    def covers(self, stamp_ns: int) -> bool:
        return len(self.stamps_ns) > 0 and self.stamps_ns[0] <= stamp_ns <= self.stamps_ns[-1]

    def at(self, stamp_ns: int) -> NDArray[np.float64]:
        """``T_parent_child`` at ``stamp_ns``: the sample itself on an exact stamp, else SE(3) interpolation
        between the two neighbouring samples. Raises :class:`TfError` outside the sample range."""
        return self.at_many([int(stamp_ns)])[0]

    def at_many(self, stamps_ns: Sequence[int] | NDArray[np.integer]) -> NDArray[np.float64]:
        """(M, 4, 4) transforms at several stamps (each like :meth:`at`, computed in one batch)."""
        q = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        if q.size == 0:
            return np.empty((0, 4, 4))
        stamps = self.stamps_ns
        if len(stamps) == 0:
            raise TfError(f"{self._describe()}: no samples")
        bad = self.first_uncovered(q)
        if bad is not None:
            first, last = self.time_range_ns
            raise TfError(
                f"{self._describe()}: no data at {_fmt_ns(bad)}; samples cover {_fmt_ns(first)} .. "
                f"{_fmt_ns(last)} ({len(stamps)} samples; no extrapolation)"
            )
        i = np.searchsorted(stamps, q, side="right") - 1
        exact = stamps[i] == q
        out = np.array(self.T_parent_child[i])
        between = np.flatnonzero(~exact)
        if between.size:
            j = i[between]
            s0, s1 = stamps[j], stamps[j + 1]
            alpha = (q[between] - s0) / (s1 - s0).astype(np.float64)
            out[between] = geometry.interpolate_se3(self.T_parent_child[j], self.T_parent_child[j + 1], alpha)
        return out


class TfBuffer:
    """Static and dynamic transforms of a log, with path search and SE(3) interpolation.

    Fill it with :meth:`add_static` / :meth:`add` (single transforms) or :meth:`add_samples` (batches,
    much faster for a whole ``/tf`` topic); query it with :meth:`lookup`. Samples may arrive in any order.
    """

    def __init__(self) -> None:
        self._static: dict[str, tuple[str, NDArray[np.float64]]] = {}
        self._pending: dict[str, list[tuple[str, NDArray[np.int64], NDArray[np.float64]]]] = {}
        self._dynamic: dict[str, TransformSeries] = {}

    # ---- filling
    def add_static(self, parent_frame: str, child_frame: str, T_parent_child: ArrayLike) -> None:
        """A ``/tf_static`` edge; a later static transform for the same child replaces it (like tf2)."""
        parent, child = normalize_frame(parent_frame), normalize_frame(child_frame)
        self._check_parent(parent, child)
        T = geometry.as_rigid(T_parent_child, f"static transform {parent} -> {child}")
        self._static[child] = (parent, T)

    def add(self, parent_frame: str, child_frame: str, stamp_ns: int, T_parent_child: ArrayLike) -> None:
        """One dynamic ``/tf`` sample."""
        T = geometry.as_rigid(T_parent_child, f"transform {parent_frame} -> {child_frame} at {stamp_ns} ns")
        self.add_samples(parent_frame, child_frame, [stamp_ns], T[None])

    def add_samples(self, parent_frame: str, child_frame: str, stamps_ns: ArrayLike, T_parent_child: ArrayLike) -> None:
        """Many dynamic samples of one edge at once ((N,) stamps, (N, 4, 4) transforms, assumed rigid)."""
        parent, child = normalize_frame(parent_frame), normalize_frame(child_frame)
        self._check_parent(parent, child)
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        T = np.asarray(T_parent_child, dtype=np.float64).reshape(-1, 4, 4)
        self._pending.setdefault(child, []).append((parent, stamps, T))  # merged with earlier samples on next use

    def _check_parent(self, parent: str, child: str, where: str = "") -> None:
        """Refuse an edge that makes a frame its own parent or gives it a second parent (``where``: a prefix naming
        the file, topic and message it came from)."""
        prefix = f"{where}: " if where else ""
        if parent == child:
            raise TfError(f"{prefix}transform {parent} -> {child}: a frame cannot be its own parent")
        known = self._parent_of(child)
        if known is not None and known != parent:
            raise TfError(
                f"{prefix}frame {child!r} has two parents, {known!r} and {parent!r} (a TF tree gives every frame one "
                f"parent)"
            )

    def check_edge(self, parent_frame: str, child_frame: str, where: str = "") -> None:
        """:class:`TfError` (prefixed by ``where``) if ``parent -> child`` cannot join this tree."""
        self._check_parent(normalize_frame(parent_frame), normalize_frame(child_frame), where)

    def _parent_of(self, child: str) -> str | None:
        if child in self._static:
            return self._static[child][0]
        if child in self._dynamic:
            return self._dynamic[child].parent_frame
        pending = self._pending.get(child)
        return pending[0][0] if pending else None

    def _edge(self, child: str) -> TransformSeries | None:
        """The dynamic series of ``child``'s edge (merging pending batches on first use)."""
        if child in self._pending:
            batches = self._pending.pop(child)
            old = self._dynamic.get(child)
            stamps = [b[1] for b in batches]
            Ts = [b[2] for b in batches]
            if old is not None:
                stamps.insert(0, old.stamps_ns)
                Ts.insert(0, old.T_parent_child)
            self._dynamic[child] = TransformSeries.from_samples(
                batches[0][0], child, np.concatenate(stamps), np.concatenate(Ts), what="/tf"
            )
        return self._dynamic.get(child)

    # ---- inspection
    def frames(self) -> list[str]:
        """Every frame that appears as a parent or a child."""
        names = set(self._static) | set(self._pending) | set(self._dynamic)
        names |= {p for p, _ in self._static.values()}
        names |= {b[0][0] for b in self._pending.values()} | {s.parent_frame for s in self._dynamic.values()}
        return sorted(names)

    def edges(self) -> list[tuple[str, str, bool]]:
        """``(parent, child, is_static)`` of every edge."""
        out = [(p, c, True) for c, (p, _) in self._static.items()]
        for child in sorted(set(self._pending) | set(self._dynamic)):
            if child not in self._static:
                out.append((self._parent_of(child), child, False))  # type: ignore[arg-type]
        return sorted(out)

    def parent(self, frame: str) -> str | None:
        return self._parent_of(normalize_frame(frame))

    def series(self, parent_frame: str, child_frame: str) -> TransformSeries:
        """The dynamic samples of the edge ``parent -> child``."""
        parent, child = normalize_frame(parent_frame), normalize_frame(child_frame)
        edge = self._edge(child)
        if edge is None or edge.parent_frame != parent:
            raise TfError(f"no dynamic edge {parent} -> {child} (edges: {self._edge_list()})")
        return edge

    def static_transform(self, parent_frame: str, child_frame: str) -> NDArray[np.float64]:
        parent, child = normalize_frame(parent_frame), normalize_frame(child_frame)
        if child not in self._static or self._static[child][0] != parent:
            raise TfError(f"no static edge {parent} -> {child} (edges: {self._edge_list()})")
        return np.array(self._static[child][1])

    def _edge_list(self, limit: int = 20) -> str:
        edges = [f"{p}->{c}{' (static)' if s else ''}" for p, c, s in self.edges()]
        more = f", ... ({len(edges) - limit} more)" if len(edges) > limit else ""
        return ", ".join(edges[:limit]) + more if edges else "none"

    def __len__(self) -> int:
        return len(self.edges())

    def __repr__(self) -> str:
        return f"TfBuffer({len(self.frames())} frames, {len(self)} edges)"

    # ---- queries
    def _chain(self, frame: str) -> list[str]:
        """``[frame, parent, grandparent, ..., root]``."""
        chain = [frame]
        seen = {frame}
        while (parent := self._parent_of(chain[-1])) is not None:
            if parent in seen:
                raise TfError(f"the TF tree has a cycle through {parent!r}: {' -> '.join(reversed([*chain, parent]))}")
            chain.append(parent)
            seen.add(parent)
        return chain

    def _path(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """Frames from ``source`` up to the common ancestor and from ``target`` up to it (ancestor excluded)."""
        known = set(self.frames())
        for name in (target, source):
            if name not in known:
                listed = ", ".join(sorted(known)[:30]) or "none"
                raise TfError(f"lookup {target} <- {source}: frame {name!r} is not in the TF tree (frames: {listed})")
        up_source = self._chain(source)
        up_target = self._chain(target)
        ancestors = set(up_target)
        common = next((f for f in up_source if f in ancestors), None)
        if common is None:
            raise TfError(
                f"no TF path between {target!r} and {source!r}: they are in different trees "
                f"(roots {up_target[-1]!r} and {up_source[-1]!r})"
            )
        return up_source[: up_source.index(common)], up_target[: up_target.index(common)]

    def can_transform(self, target_frame: str, source_frame: str, stamp_ns: int | None = None) -> bool:
        try:
            self.lookup(target_frame, source_frame, stamp_ns)
        except TfError:
            return False
        return True

    def is_static(self, target_frame: str, source_frame: str) -> bool:
        """Whether every edge between the two frames is static (then the lookup needs no stamp)."""
        up_source, up_target = self._path(normalize_frame(target_frame), normalize_frame(source_frame))
        return all(f in self._static for f in up_source + up_target)

    def time_range_ns(self, target_frame: str, source_frame: str) -> tuple[int, int] | None:
        """Stamps at which :meth:`lookup` succeeds (intersection of the dynamic edges' ranges); ``None``
        when the path is static; raises :class:`TfError` if the ranges do not overlap."""
        target, source = normalize_frame(target_frame), normalize_frame(source_frame)
        up_source, up_target = self._path(target, source)
        lo, hi = None, None
        for child in up_source + up_target:
            if child in self._static:
                continue
            edge = self._edge(child)
            assert edge is not None
            first, last = edge.time_range_ns
            lo = first if lo is None else max(lo, first)
            hi = last if hi is None else min(hi, last)
        if lo is None or hi is None:
            return None
        if lo > hi:
            raise TfError(
                f"lookup {target} <- {source}: the dynamic edges on the path have no common time "
                f"(latest start {_fmt_ns(lo)} > earliest end {_fmt_ns(hi)})"
            )
        return lo, hi

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: int | None = None) -> NDArray[np.float64]:
        """``T_target_source`` (maps points in ``source_frame`` into ``target_frame``) at ``stamp_ns``.

        ``stamp_ns=None`` uses the latest time at which every edge on the path has data (tf2's "time 0").
        Raises :class:`TfError` naming both frames when a frame is unknown, the frames are not connected,
        or a dynamic edge on the path has no data at the stamp.
        """
        target, source = normalize_frame(target_frame), normalize_frame(source_frame)
        if target == source:
            return np.eye(4)
        if stamp_ns is None:
            time_range = self.time_range_ns(target, source)
            stamp_ns = 0 if time_range is None else time_range[1]  # a static path holds at any time
        return self.lookup_many(target, source, [int(stamp_ns)])[0]

    def lookup_many(self, target_frame: str, source_frame: str, stamps_ns: Iterable[int]) -> NDArray[np.float64]:
        """(M, 4, 4) lookups at several stamps (each like :meth:`lookup`, every edge interpolated in one batch)."""
        q = np.fromiter((int(s) for s in stamps_ns), dtype=np.int64)
        target, source = normalize_frame(target_frame), normalize_frame(source_frame)
        if q.size == 0:
            return np.empty((0, 4, 4))
        if target == source:
            return np.tile(np.eye(4), (q.size, 1, 1))
        up_source, up_target = self._path(target, source)

        def edges_at(child: str) -> NDArray[np.float64]:
            if child in self._static:
                return self._static[child][1][None]
            edge = self._edge(child)
            assert edge is not None
            try:
                return edge.at_many(q)
            except TfError as exc:
                raise TfError(f"lookup {target} <- {source} at {_fmt_ns(edge.first_uncovered(q))}: {exc}") from None

        T_anc_source = np.tile(np.eye(4), (q.size, 1, 1))
        for child in up_source:
            T_anc_source = edges_at(child) @ T_anc_source
        T_anc_target = np.tile(np.eye(4), (q.size, 1, 1))
        for child in up_target:
            T_anc_target = edges_at(child) @ T_anc_target
        return geometry.invert(T_anc_target) @ T_anc_source
