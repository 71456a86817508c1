"""The diagnostics' samples: a bounded random subset of every frame's sensor-frame points, each with a normal
estimated *within its own frame* (smearing between frames cannot corrupt it), its planarity and a sensor-noise
level along the normal (:class:`DiagnosticCloud`); placed in the world with one revision's poses
(:class:`PlacedCloud`), cheaply, so one set of samples serves many revisions and perturbation experiments.

Every measure of :mod:`driftmap.diagnostics` (double walls, attribution, coverage, causes) reads these samples.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from pydantic import ConfigDict, Field

from driftmap.config import SettingsModel
from driftmap.errors import GeometryError
from driftmap.frame import Frame, SensorKind
from driftmap.preprocess.cloud import estimate_normals
from driftmap.preprocess.deskew import point_motions, scan_motion
from driftmap.preprocess.noise import NoiseModel

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)

UNIT_NORMAL_TOLERANCE = 0.05
"""A stored normal is used only when its length is within this of 1 (zero or NaN normal fields are not normals)."""


class SamplingConfig(SettingsModel):
    """How many points of each frame the diagnostics look at, and how their own-frame normals are made.

    The work is bounded per store: ``points_budget`` samples in total, shared by the frames (at least
    ``min_points_per_frame``, at most ``max_points_per_frame`` each), unless ``points_per_frame`` fixes it.
    Few frames get more points each, which is where the statistics need them most.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    points_budget: int = Field(600_000, ge=1000, description="samples in total over all frames")
    points_per_frame: int | None = Field(None, ge=50, description="fixed samples per frame (overrides the budget)")
    min_points_per_frame: int = Field(1000, ge=50, description="lower bound of the per-frame share of the budget")
    max_points_per_frame: int = Field(20_000, ge=50, description="upper bound of the per-frame share of the budget")
    normals_oversample: float = Field(2.0, ge=1.0, description="normals are estimated on this many times the kept points (same frame)")
    normals_k: int = Field(16, ge=5, le=100, description="nearest neighbours (same frame) per normal")
    min_normal_confidence: float = Field(0.5, ge=0.0, le=1.0, description="drop points whose normal is ill-defined (1 - l0/l1 below this)")
    max_curvature: float = Field(0.05, gt=0.0, le=1.0 / 3.0, description="drop non-planar points (surface variation l0/(l0+l1+l2) above this)")
    seed: int = 0

    def per_frame(self, n_frames: int) -> int:
        """Samples kept per frame for a store of ``n_frames`` frames."""
        if self.points_per_frame is not None:
            return self.points_per_frame
        share = self.points_budget // max(n_frames, 1)
        return int(min(max(share, self.min_points_per_frame), self.max_points_per_frame))


@dataclass(frozen=True)
class DiagnosticCloud:
    """Per-frame samples in their sensor frames: points, own-frame normals and noise along the normal.

    Points of frame row ``k`` are ``points_sensor[offsets[k]:offsets[k + 1]]``; rows are in time order.
    Use :meth:`place` to put them in the world with a revision's poses.
    """

    frame_ids: NDArray[np.int64]
    stamps_ns: NDArray[np.int64]
    offsets: NDArray[np.int64]
    points_sensor: NDArray[np.float32]
    normals_sensor: NDArray[np.float32]
    sigma_normal_m: NDArray[np.float32]
    sensor_kinds: tuple[SensorKind, ...]
    n_points_source: NDArray[np.int64]
    """How many points each frame had before sampling."""
    rejected_points_sensor: NDArray[np.float32] = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    """Drawn samples without a usable normal (thinned like the kept ones), frame row ``k``'s at
    ``rejected_offsets[k]:rejected_offsets[k + 1]``, with their :class:`RejectReason`: where the map holds points
    the measures cannot use (the coverage report)."""
    rejected_offsets: NDArray[np.int64] | None = None
    rejected_reason: NDArray[np.uint8] = field(default_factory=lambda: np.zeros(0, np.uint8))
    sample_counts: NDArray[np.int64] | None = None
    """(M, 3) per frame: samples drawn for normals, of them without a defined normal, of them not planar."""
    stored_normals_refused: NDArray[np.bool_] | None = None
    """(M,) frames whose stored normals were not unit vectors (estimated from the points instead)."""
    time_offset_ns: NDArray[np.int64] | None = None
    """(N,) per-point time of every sample relative to its frame's stamp (``PointAttributes.time_offset_ns``), 0 for
    frames without per-point times; None when no frame has them. :meth:`place` deskews the ``timed`` frames."""
    rejected_time_offset_ns: NDArray[np.int64] | None = None
    """The same for the rejected samples (``rejected_points_sensor``)."""
    timed: NDArray[np.bool_] | None = None
    """(M,) frames with per-point times (None: none has them)."""
    time_span_ns: NDArray[np.int64] | None = None
    """(M,) span of each frame's per-point times over *all* its points (as the map view judges a scan), 0 untimed."""
    row_group: NDArray[np.int64] | None = None
    """(M,) session of each row when the rows are ordered session by session (deskew neighbours stay within one
    session); None: one time line."""

    @property
    def n_frames(self) -> int:
        return len(self.frame_ids)

    @property
    def n_points(self) -> int:
        return int(self.offsets[-1])

    def frame_index(self) -> NDArray[np.int64]:
        """Row (into ``frame_ids``) of every sample."""
        return np.repeat(np.arange(self.n_frames), np.diff(self.offsets))

    @classmethod
    def from_frames(cls, frames: Iterable[Frame], config: SamplingConfig | None = None,
                    noise: NoiseModel | None = None,
                    sessions: Mapping[int, Sequence[int]] | None = None) -> DiagnosticCloud:
        """Sample frames (any order; rows are sorted by stamp, session by session with ``sessions``: see
        :meth:`from_store`). ``noise`` defaults per sensor kind."""
        cfg = config or SamplingConfig()
        frames = list(frames)
        keep = cfg.per_frame(len(frames))
        rows = []
        for frame in frames:
            rows.append(_sample_frame(frame.frame_id, frame.stamp_ns, frame.sensor_kind, frame.points_sensor,
                                      frame.attributes.normal_sensor, cfg, keep, noise, frame.attributes.time_offset_ns))
        return cls._assemble(rows, _session_of_frames(sessions))

    @classmethod
    def from_store(cls, store: FrameStore, config: SamplingConfig | None = None, noise: NoiseModel | None = None,
                   frame_ids: Sequence[int] | None = None,
                   progress: Callable[[str, int, int | None], None] | None = None,
                   sessions: Mapping[int, Sequence[int]] | None = None) -> DiagnosticCloud:
        """Sample the frames of a store (all, or ``frame_ids``); poses are not needed here. ``progress(stage, done,
        total)`` is called after each frame (the sampling with its normals is most of a diagnosis' time).
        ``sessions`` (a merged store's ``{session: [frame ids]}``): the rows session by session, each in time order
        -- sessions recorded apart may share stamps (every data set's log starts at 0), and rows in stamp order would
        interleave them and run the travel back and forth between them (trial 14)."""
        cfg = config or SamplingConfig()
        ids = store.frame_ids if frame_ids is None else np.asarray(frame_ids, dtype=np.int64)
        keep = cfg.per_frame(len(ids))
        rows = []
        for k, fid in enumerate(ids):
            frame = store.frame(int(fid))
            rows.append(_sample_frame(frame.frame_id, frame.stamp_ns, frame.sensor_kind, frame.points_sensor,
                                      frame.attributes.normal_sensor, cfg, keep, noise, frame.attributes.time_offset_ns))
            if progress is not None:
                progress("sampling frames", k + 1, len(ids))
        return cls._assemble(rows, _session_of_frames(sessions))

    @classmethod
    def _assemble(cls, rows: list[tuple], group: Mapping[int, int] | None = None) -> DiagnosticCloud:
        if not rows:
            raise GeometryError("diagnostics: no frames to sample")
        rows.sort(key=lambda r: (-1 if group is None else group.get(r[0], -1), r[1], r[0]))
        counts = np.array([len(r[3]) for r in rows], dtype=np.int64)
        refused = np.array([r[10] for r in rows], dtype=bool)
        if refused.any():
            ids = [r[0] for r in rows if r[10]]
            logger.warning("%d of %d frames carry stored normals that are mostly not unit vectors (zero, NaN or not "
                           "normalised; frames %s): their normals are estimated from their points instead", len(ids),
                           len(rows), ", ".join(map(str, ids[:5])) + (" ..." if len(ids) > 5 else ""))
        rejected_counts = np.array([len(r[7]) for r in rows], dtype=np.int64)
        timed = np.array([r[11] is not None for r in rows], dtype=bool)
        times: dict = {}
        if timed.any():
            times = {
                "time_offset_ns": np.concatenate([np.zeros(len(r[3]), np.int64) if r[11] is None else r[11]
                                                  for r in rows]).astype(np.int64),
                "rejected_time_offset_ns": np.concatenate([np.zeros(len(r[7]), np.int64) if r[12] is None else r[12]
                                                           for r in rows]).astype(np.int64),
                "timed": timed,
                "time_span_ns": np.array([r[13] for r in rows], dtype=np.int64),
            }
        if group is not None:
            times["row_group"] = np.array([group.get(r[0], -1) for r in rows], dtype=np.int64)
        return cls(
            **times,
            rejected_points_sensor=np.concatenate([r[7] for r in rows]).astype(np.float32).reshape(-1, 3),
            rejected_offsets=np.concatenate([[0], np.cumsum(rejected_counts)]).astype(np.int64),
            rejected_reason=np.concatenate([r[8] for r in rows]).astype(np.uint8),
            sample_counts=np.array([r[9] for r in rows], dtype=np.int64).reshape(-1, 3),
            stored_normals_refused=refused,
            frame_ids=np.array([r[0] for r in rows], dtype=np.int64),
            stamps_ns=np.array([r[1] for r in rows], dtype=np.int64),
            offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
            points_sensor=np.concatenate([r[3] for r in rows]).astype(np.float32),
            normals_sensor=np.concatenate([r[4] for r in rows]).astype(np.float32),
            sigma_normal_m=np.concatenate([r[5] for r in rows]).astype(np.float32),
            sensor_kinds=tuple(r[2] for r in rows),
            n_points_source=np.array([r[6] for r in rows], dtype=np.int64),
        )

    def subset(self, rows: Sequence[int] | NDArray[np.integer]) -> DiagnosticCloud:
        """The samples of some frame rows only (kept in time order)."""
        rows = np.unique(np.asarray(rows, dtype=np.int64))
        if rows.size == 0 or rows[0] < 0 or rows[-1] >= self.n_frames:
            raise GeometryError(f"subset: rows must be a non-empty subset of 0..{self.n_frames - 1}")
        counts = np.diff(self.offsets)[rows]
        idx = np.concatenate([np.arange(self.offsets[r], self.offsets[r + 1]) for r in rows])
        return DiagnosticCloud(
            frame_ids=self.frame_ids[rows], stamps_ns=self.stamps_ns[rows],
            offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
            points_sensor=self.points_sensor[idx], normals_sensor=self.normals_sensor[idx],
            sigma_normal_m=self.sigma_normal_m[idx], sensor_kinds=tuple(self.sensor_kinds[r] for r in rows),
            n_points_source=self.n_points_source[rows], **self._rejected_subset(rows), **self._times_subset(rows, idx),
        )

    def _times_subset(self, rows: NDArray[np.int64], idx: NDArray[np.int64]) -> dict:
        out: dict = {}
        if self.row_group is not None:
            out["row_group"] = self.row_group[rows]
        if self.timed is None or self.time_offset_ns is None or not self.timed[rows].any():
            return out
        out.update(time_offset_ns=self.time_offset_ns[idx], timed=self.timed[rows],
                   time_span_ns=None if self.time_span_ns is None else self.time_span_ns[rows])
        if self.rejected_time_offset_ns is not None and self.rejected_offsets is not None:
            ridx = np.concatenate([np.arange(self.rejected_offsets[r], self.rejected_offsets[r + 1]) for r in rows])
            out["rejected_time_offset_ns"] = self.rejected_time_offset_ns[ridx]
        return out

    def _rejected_subset(self, rows: NDArray[np.int64]) -> dict:
        if self.rejected_offsets is None:
            return {}
        counts = np.diff(self.rejected_offsets)[rows]
        idx = np.concatenate([np.arange(self.rejected_offsets[r], self.rejected_offsets[r + 1]) for r in rows])
        return {"rejected_points_sensor": self.rejected_points_sensor[idx],
                "rejected_offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
                "rejected_reason": self.rejected_reason[idx],
                "sample_counts": None if self.sample_counts is None else self.sample_counts[rows],
                "stored_normals_refused": None if self.stored_normals_refused is None else self.stored_normals_refused[rows]}

    def place(self, poses: NDArray[np.float64]) -> PlacedCloud:
        """World positions and normals with ``poses[k] = T_world_sensor`` of frame row ``k``."""
        T = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(T) != self.n_frames:
            raise GeometryError(f"place: {len(T)} poses for {self.n_frames} frames")
        pts = np.empty((self.n_points, 3), np.float64)
        nrm = np.empty((self.n_points, 3), np.float64)
        for k in range(self.n_frames):
            a, b = self.offsets[k], self.offsets[k + 1]
            R, t = T[k, :3, :3], T[k, :3, 3]
            pts[a:b] = self.points_sensor[a:b].astype(np.float64) @ R.T + t
            nrm[a:b] = self.normals_sensor[a:b].astype(np.float64) @ R.T
        motions = self.scan_motions(T)
        times = self.time_offset_ns
        for k, (xi, dt) in motions.items():  # frames with per-point times: deskewed as the map view places them
            a, b = self.offsets[k], self.offsets[k + 1]
            if b > a and times is not None:
                D = point_motions(times[a:b], xi, dt)
                pts[a:b] = _apply(D, self.points_sensor[a:b], T[k])
                nrm[a:b] = _apply(D, self.normals_sensor[a:b], T[k], rotate_only=True)
        origins = T[:, :3, 3].copy()
        steps = np.linalg.norm(np.diff(origins, axis=0), axis=1)
        path = np.concatenate([[0.0], np.cumsum(steps)])
        return PlacedCloud(self, T, pts, nrm, self.frame_index(), origins, path, motions)

    def scan_motions(self, poses: NDArray[np.float64]) -> dict[int, tuple[NDArray[np.float64], int]]:
        """``{row: (xi, dt_ns)}``: the constant motion that deskews each frame row with per-point times, from
        ``poses`` (rows' ``T_world_sensor``) as the map view takes it (:func:`driftmap.preprocess.deskew.scan_motion`: towards
        the next frame in time, the last one extrapolating the motion before it). Rows that cannot be deskewed are
        left out (placed rigidly; the reason is logged at debug level). Empty when no frame has per-point times."""
        if self.timed is None or self.time_offset_ns is None or not self.timed.any():
            return {}
        T = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        group = np.zeros(self.n_frames, np.int64) if self.row_group is None else self.row_group
        span = np.zeros(self.n_frames, np.int64) if self.time_span_ns is None else self.time_span_ns
        out: dict[int, tuple[NDArray[np.float64], int]] = {}
        rigid: list[str] = []
        for g in np.unique(group[self.timed]):
            rows = np.flatnonzero(group == g)
            order = rows[np.argsort(self.stamps_ns[rows], kind="stable")]
            rank = np.zeros(self.n_frames, np.int64)
            rank[order] = np.arange(len(order))
            for r in order[self.timed[order]]:
                motion, why = scan_motion(self.stamps_ns, T, int(r), order, rank, int(span[r]))
                if motion is None:
                    rigid.append(f"frame {int(self.frame_ids[r])}: {why}")
                else:
                    out[int(r)] = (motion.xi, int(motion.dt_ns))
        if rigid:
            logger.debug("diagnostics: %d of %d frames with per-point times are not deskewed (placed with their pose "
                         "alone): %s", len(rigid), int(self.timed.sum()), "; ".join(rigid[:5]) + (" ..." if len(rigid) > 5 else ""))
        return out


class RejectReason(enum.IntEnum):
    """Why a drawn sample has no usable own-frame normal (kept, without a normal, for the coverage report)."""

    NO_NORMAL = 1
    """too few neighbours in its frame, or an ill-defined normal (confidence below ``min_normal_confidence``)"""
    NOT_PLANAR = 2
    """its neighbourhood is not a surface (surface variation above ``max_curvature``: edges, clutter, foliage)"""


def _usable_stored_normals(frame_id: int, normals: NDArray[np.float32] | None) -> NDArray[np.float32] | None:
    """A frame's stored normals, or None when most of them are not unit vectors (zero, NaN, not normalised: a
    normal field that is not normals, such as the all-zero ones of some PCD writers)."""
    if normals is None or len(normals) == 0:
        return normals
    length = np.linalg.norm(np.asarray(normals, dtype=np.float64), axis=1)
    unit = np.isfinite(length) & (np.abs(length - 1.0) <= UNIT_NORMAL_TOLERANCE)
    if np.count_nonzero(unit) >= 0.5 * len(unit):
        return normals
    logger.debug("frame %d: %d of %d stored normals are not unit vectors", frame_id, len(unit) - int(unit.sum()), len(unit))
    return None


def _session_of_frames(sessions: Mapping[int, Sequence[int]] | None) -> dict[int, int] | None:
    return None if not sessions else {int(f): int(k) for k, fs in sessions.items() for f in fs}


def _apply(D: NDArray[np.float64], v_sensor: NDArray[np.float32], T_world_sensor: NDArray[np.float64],
           rotate_only: bool = False) -> NDArray[np.float64]:
    """``T_world_sensor @ D_i @ v_i`` per sample (float64; directions such as normals: rotations only)."""
    local = np.einsum("nij,nj->ni", D[:, :3, :3], np.asarray(v_sensor, dtype=np.float64))
    if rotate_only:
        return local @ T_world_sensor[:3, :3].T
    return (local + D[:, :3, 3]) @ T_world_sensor[:3, :3].T + T_world_sensor[:3, 3]


def _sample_frame(frame_id: int, stamp_ns: int, kind: SensorKind, points: NDArray[np.float32],
                  normals: NDArray[np.float32] | None, cfg: SamplingConfig, keep_n: int, noise: NoiseModel | None,
                  times: NDArray[np.int64] | None = None) -> tuple:
    """``(frame_id, stamp_ns, kind, points, normals, sigma, n_source, rejected points, rejected reasons,
    (drawn, no_normal, not_planar), stored normals refused, times of the points, times of the rejected points,
    span of the frame's times)`` of one frame (the times None and the span 0 without per-point times)."""
    rng = np.random.default_rng([cfg.seed, frame_id & 0x7FFFFFFF])
    pts = np.asarray(points, dtype=np.float32)
    finite = np.flatnonzero(np.all(np.isfinite(pts), axis=1))
    n_src = len(pts)
    n_norm = min(len(finite), int(keep_n * cfg.normals_oversample))
    pick = finite if n_norm == len(finite) else rng.choice(finite, n_norm, replace=False)
    sub = pts[pick]
    usable = _usable_stored_normals(frame_id, normals)
    refused = normals is not None and usable is None
    reason = np.zeros(len(sub), np.uint8)
    if usable is not None:
        nrm = np.asarray(usable, dtype=np.float32)[pick]
        length = np.linalg.norm(nrm.astype(np.float64), axis=1)
        ok = np.isfinite(length) & (np.abs(length - 1.0) <= UNIT_NORMAL_TOLERANCE)
        reason[~ok] = RejectReason.NO_NORMAL
    elif len(sub) >= cfg.normals_k:
        res = estimate_normals(sub, k=cfg.normals_k)
        nrm = res.normals
        defined = (res.confidence >= cfg.min_normal_confidence) & np.all(np.isfinite(nrm), axis=1)
        planar = res.curvature <= cfg.max_curvature
        ok = defined & planar
        reason[~defined] = RejectReason.NO_NORMAL
        reason[defined & ~planar] = RejectReason.NOT_PLANAR
    else:
        nrm, ok = np.zeros_like(sub), np.zeros(len(sub), bool)
        reason[:] = RejectReason.NO_NORMAL
    keep = np.flatnonzero(ok)
    n_ok = len(keep)
    if len(keep) > keep_n:
        keep = np.sort(rng.choice(keep, keep_n, replace=False))
    # the rejected samples, thinned as the usable ones were: both populations at the same density
    bad = np.flatnonzero(~ok)
    rate = len(keep) / n_ok if n_ok else min(1.0, keep_n / max(len(bad), 1))
    n_bad = int(round(len(bad) * rate))
    if n_bad < len(bad):
        bad = np.sort(rng.choice(bad, n_bad, replace=False))
    model = noise or NoiseModel.for_sensor(kind)
    sigma = model.sigma_normal_m(sub[keep], nrm[keep]) if len(keep) else np.zeros(0)
    counts = (len(sub), int(np.count_nonzero(reason == RejectReason.NO_NORMAL)),
              int(np.count_nonzero(reason == RejectReason.NOT_PLANAR)))
    t_keep = t_bad = None
    span = 0
    if times is not None and len(times) == n_src:
        t_all = np.asarray(times, dtype=np.int64)
        span = int(np.ptp(t_all)) if len(t_all) else 0  # the whole scan's, as the map view judges it
        t_keep, t_bad = t_all[pick][keep], t_all[pick][bad]
    return (int(frame_id), int(stamp_ns), kind, sub[keep], nrm[keep], sigma, n_src, sub[bad], reason[bad], counts, refused,
            t_keep, t_bad, span)


@dataclass(frozen=True)
class PlacedCloud:
    """A :class:`DiagnosticCloud` placed in the world with one set of poses (float64)."""

    samples: DiagnosticCloud
    poses: NDArray[np.float64]
    points_world: NDArray[np.float64]
    normals_world: NDArray[np.float64]
    frame_index: NDArray[np.int64]
    origins_world: NDArray[np.float64]
    """(M, 3) sensor origin of every frame."""
    path_length_m: NDArray[np.float64]
    """(M,) distance travelled by the sensor up to each frame (frames in time order)."""
    scan_motions: Mapping[int, tuple[NDArray[np.float64], int]] = field(default_factory=dict)
    """``{row: (xi, dt_ns)}`` of the frame rows whose samples were deskewed (:meth:`DiagnosticCloud.scan_motions`)."""

    @property
    def frame_ids(self) -> NDArray[np.int64]:
        return self.samples.frame_ids

    @property
    def stamps_ns(self) -> NDArray[np.int64]:
        return self.samples.stamps_ns

    @property
    def sigma_normal_m(self) -> NDArray[np.float32]:
        return self.samples.sigma_normal_m

    @cached_property
    def rejected_world(self) -> NDArray[np.float64]:
        """World positions of the samples without a usable normal (:attr:`DiagnosticCloud.rejected_points_sensor`)."""
        s = self.samples
        if s.rejected_offsets is None or len(s.rejected_points_sensor) == 0:
            return np.zeros((0, 3))
        rows = np.repeat(np.arange(s.n_frames), np.diff(s.rejected_offsets))
        p = s.rejected_points_sensor.astype(np.float64)
        R, t = self.poses[rows, :3, :3], self.poses[rows, :3, 3]
        world = np.einsum("nij,nj->ni", R, p) + t
        if self.scan_motions and s.rejected_time_offset_ns is not None:
            for k, (xi, dt) in self.scan_motions.items():
                a, b = s.rejected_offsets[k], s.rejected_offsets[k + 1]
                if b > a:
                    world[a:b] = _apply(point_motions(s.rejected_time_offset_ns[a:b], xi, dt),
                                        s.rejected_points_sensor[a:b], self.poses[k])
        return world

    @cached_property
    def world_columns(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``points_world`` and ``normals_world`` as (3, N) contiguous columns, made once per placed cloud: numpy's
        per-point arithmetic and gathers on a column run several times faster than on (N, 3) rows."""
        return np.ascontiguousarray(self.points_world.T), np.ascontiguousarray(self.normals_world.T)

