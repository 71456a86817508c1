"""Double walls: where the map holds the same surface twice, how far apart the two layers are, and which
frames put them there. Also the smearing score (one number in metres) and, for comparison with the
literature, Mean Map Entropy and Mean Plane Variance.

Method (see ``docs/diagnostics.md`` for the reasoning and the measured numbers):

1. **Samples** (:class:`DiagnosticCloud`): a bounded random subset of every frame's sensor-frame points,
   each with a normal estimated *within its own frame* (smearing between frames cannot corrupt it), its
   planarity, and a sensor-noise level along the normal (Kinect-style ``sigma_z = a + b (z - z0)^2`` or a
   constant LiDAR range sigma). Placing the samples with a revision's poses is cheap, so one cloud serves
   many revisions (and the perturbation experiments).
2. **Per voxel, per scale** (:func:`detect_double_walls`): the dominant normal of the voxel's own-frame
   normals (a second one for the points that disagree with it), points within ``normal_max_angle_deg``
   of it, split by which side the sensor was on; the two halves of a surface that a voxel face cuts along its
   normal are joined (else each half holds a truncated noise band and separations read short). Offsets along the normal are referred to a *lateral cell
   reference* (the mean offset of all frames in a small cell of the surface), which removes real relief
   (a door recess, a curb) seen by every frame; what is left between frames is pose disagreement.
3. Per frame, the mean residual offset; a two-layer split of the frames (1-D 2-means, per-frame mean
   offsets as samples) is accepted as a double wall when the two-component model wins by BIC, the
   layers are far apart relative to their widths (Ashman's D), the separation exceeds both the minimum
   and its own uncertainty, the smaller layer is not tiny, the layers overlap laterally, and the
   **time/frame purity** holds: points of each frame lie on that frame's layer about as often as the
   sensor noise allows (two-layer geometry seen within single frames fails this).
4. The separation is measured where both layers were seen: per shared lateral cell, the difference of
   the two layers' mean offsets; its uncertainty combines the spread over cells and the frame-to-frame
   jitter of each layer.
5. **Smearing score**: per group, its frames are split into *visits* (runs without ``visit_gap_m`` of travel
   between two frames that saw it); the visits' mean offsets should agree. Their dispersion, less what the
   sensor noise and the group's own frame-to-frame jitter within visits explain, is the group's smearing; the
   score is its RMS over the groups (a group seen in one visit counts 0: drift without a revisit is
   invisible). Within-visit jitter (viewpoint-dependent depth distortion, pose jitter) is the same for every
   pose estimate, so leaving it out is what separates a drifting map from a good one. The frame-level
   score (between-frame instead of between-visit dispersion) is kept beside it: it also sees a jump inside
   one pass.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.special import ndtr

from driftmap.errors import ConfigError, GeometryError
from driftmap.frame import Frame, SensorKind
from driftmap.preprocess.cloud import estimate_normals

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)

UNIT_NORMAL_TOLERANCE = 0.05
"""A stored normal is used only when its length is within this of 1 (zero or NaN normal fields are not normals)."""
_DENSE_SPAN_PER_KEY = 16
_DENSE_SPAN_MIN = 1 << 22


# ---------------------------------------------------------------------------------------------- noise model


class NoiseModelKind(enum.Enum):
    """How the sensor noise grows with distance."""

    QUADRATIC_DEPTH = "quadratic_depth"
    """Structured-light depth camera: ``sigma_z = a + b (z - z0)^2`` along the ray, z = depth (Nguyen et al. 2012)."""
    CONSTANT_RANGE = "constant_range"
    """LiDAR / ToF: a constant range sigma along the ray."""


class NoiseModel(BaseModel):
    """Per-point measurement noise along the viewing ray, projected onto the surface normal."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: NoiseModelKind = NoiseModelKind.QUADRATIC_DEPTH
    a_m: float = Field(0.0012, ge=0.0, description="quadratic model: constant term (m)")
    b_per_m: float = Field(0.0019, ge=0.0, description="quadratic model: coefficient of (z - z0)^2 (1/m)")
    z0_m: float = Field(0.4, description="quadratic model: depth of least noise (m)")
    range_sigma_m: float = Field(0.02, gt=0.0, description="constant model: range sigma (m)")
    min_incidence_cos: float = Field(0.3, gt=0.0, le=1.0,
                                     description="floor of |cos(ray, normal)| in the projection (grazing views are not noise-free)")

    @classmethod
    def for_sensor(cls, kind: SensorKind) -> NoiseModel:
        """Kinect-v1 quadratic model for depth cameras, 2 cm range sigma for LiDAR."""
        if kind is SensorKind.LIDAR:
            return cls(kind=NoiseModelKind.CONSTANT_RANGE)
        return cls()

    def sigma_ray_m(self, points_sensor: NDArray[np.floating]) -> NDArray[np.float64]:
        """Noise sigma along the viewing ray of sensor-frame points (optical/z axis forward for depth cameras)."""
        p = np.asarray(points_sensor, dtype=np.float64)
        if self.kind is NoiseModelKind.CONSTANT_RANGE:
            return np.full(len(p), self.range_sigma_m)
        return self.a_m + self.b_per_m * (p[:, 2] - self.z0_m) ** 2

    def sigma_normal_m(self, points_sensor: NDArray[np.floating], normals_sensor: NDArray[np.floating]) -> NDArray[np.float64]:
        """Noise sigma along each point's normal: ``sigma_ray * max(|ray . normal|, min_incidence_cos)``."""
        p = np.asarray(points_sensor, dtype=np.float64)
        ray = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9)
        cos = np.abs(np.einsum("ij,ij->i", ray, np.asarray(normals_sensor, dtype=np.float64)))
        return self.sigma_ray_m(p) * np.maximum(np.nan_to_num(cos, nan=1.0), self.min_incidence_cos)


# ---------------------------------------------------------------------------------------------- samples


class SamplingConfig(BaseModel):
    """How many points of each frame the diagnostics look at, and how their own-frame normals are made.

    The work is bounded per store: ``points_budget`` samples in total, shared by the frames (at least
    ``min_points_per_frame``, at most ``max_points_per_frame`` each), unless ``points_per_frame`` fixes it.
    Few frames get more points each, which is where the statistics need them most.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
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
                    noise: NoiseModel | None = None) -> DiagnosticCloud:
        """Sample frames (any order; rows are sorted by stamp). ``noise`` defaults per sensor kind."""
        cfg = config or SamplingConfig()
        frames = list(frames)
        keep = cfg.per_frame(len(frames))
        rows = []
        for frame in frames:
            rows.append(_sample_frame(frame.frame_id, frame.stamp_ns, frame.sensor_kind, frame.points_sensor,
                                      frame.attributes.normal_sensor, cfg, keep, noise))
        return cls._assemble(rows)

    @classmethod
    def from_store(cls, store: FrameStore, config: SamplingConfig | None = None, noise: NoiseModel | None = None,
                   frame_ids: Sequence[int] | None = None,
                   progress: Callable[[str, int, int | None], None] | None = None) -> DiagnosticCloud:
        """Sample the frames of a store (all, or ``frame_ids``); poses are not needed here. ``progress(stage, done,
        total)`` is called after each frame (the sampling with its normals is most of a diagnosis' time)."""
        cfg = config or SamplingConfig()
        ids = store.frame_ids if frame_ids is None else np.asarray(frame_ids, dtype=np.int64)
        keep = cfg.per_frame(len(ids))
        rows = []
        for k, fid in enumerate(ids):
            frame = store.frame(int(fid))
            rows.append(_sample_frame(frame.frame_id, frame.stamp_ns, frame.sensor_kind, frame.points_sensor,
                                      frame.attributes.normal_sensor, cfg, keep, noise))
            if progress is not None:
                progress("sampling frames", k + 1, len(ids))
        return cls._assemble(rows)

    @classmethod
    def _assemble(cls, rows: list[tuple]) -> DiagnosticCloud:
        if not rows:
            raise GeometryError("diagnostics: no frames to sample")
        rows.sort(key=lambda r: (r[1], r[0]))
        counts = np.array([len(r[3]) for r in rows], dtype=np.int64)
        refused = np.array([r[10] for r in rows], dtype=bool)
        if refused.any():
            ids = [r[0] for r in rows if r[10]]
            logger.warning("%d of %d frames carry stored normals that are mostly not unit vectors (zero, NaN or not "
                           "normalised; frames %s): their normals are estimated from their points instead", len(ids),
                           len(rows), ", ".join(map(str, ids[:5])) + (" ..." if len(ids) > 5 else ""))
        rejected_counts = np.array([len(r[7]) for r in rows], dtype=np.int64)
        return cls(
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
            n_points_source=self.n_points_source[rows], **self._rejected_subset(rows),
        )

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
        origins = T[:, :3, 3].copy()
        steps = np.linalg.norm(np.diff(origins, axis=0), axis=1)
        path = np.concatenate([[0.0], np.cumsum(steps)])
        return PlacedCloud(self, T, pts, nrm, self.frame_index(), origins, path)


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


def _sample_frame(frame_id: int, stamp_ns: int, kind: SensorKind, points: NDArray[np.float32],
                  normals: NDArray[np.float32] | None, cfg: SamplingConfig, keep_n: int, noise: NoiseModel | None) -> tuple:
    """``(frame_id, stamp_ns, kind, points, normals, sigma, n_source, rejected points, rejected reasons,
    (drawn, no_normal, not_planar), stored normals refused)`` of one frame."""
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
    return (int(frame_id), int(stamp_ns), kind, sub[keep], nrm[keep], sigma, n_src, sub[bad], reason[bad], counts, refused)


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
        return np.einsum("nij,nj->ni", R, p) + t

    @cached_property
    def world_columns(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``points_world`` and ``normals_world`` as (3, N) contiguous columns, made once per placed cloud: numpy's
        per-point arithmetic and gathers on a column run several times faster than on (N, 3) rows."""
        return np.ascontiguousarray(self.points_world.T), np.ascontiguousarray(self.normals_world.T)


# ---------------------------------------------------------------------------------------------- helpers


def _dense_ids(keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Compact non-negative int64 keys to 0..U-1 (ids in key order) without sorting when the key span is small."""
    if len(keys) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    span = int(keys.max()) + 1
    if span <= max(_DENSE_SPAN_PER_KEY * len(keys), _DENSE_SPAN_MIN):
        mark = np.zeros(span, bool)
        mark[keys] = True
        uniq = np.flatnonzero(mark)
        remap = np.empty(span, np.int32)
        remap[uniq] = np.arange(len(uniq), dtype=np.int32)
        return remap[keys].astype(np.int64), uniq
    uniq, inverse = np.unique(keys, return_inverse=True)
    return inverse.astype(np.int64), uniq


def _grid_keys(columns: NDArray[np.float64], size_m: float) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Voxel key per point of the (3, N) coordinate ``columns`` (``(k0 * span1 + k1) * span2 + k2`` of the integer
    coordinates shifted to start at 0), the shift ``lo`` and the grid's span per axis."""
    k = [np.floor(col / size_m).astype(np.int64) for col in columns]
    lo = np.array([int(ki.min()) for ki in k])
    span = np.array([int(ki.max()) for ki in k]) - lo + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0**62:
        raise ConfigError(f"voxel grid too large to index at {size_m} m")
    return ((k[0] - lo[0]) * span[1] + (k[1] - lo[1])) * span[2] + (k[2] - lo[2]), lo, span


def _sums(ids: NDArray[np.int64], n: int, weights: NDArray | None = None) -> NDArray[np.float64]:
    return np.bincount(ids, weights=weights, minlength=n).astype(np.float64)


def _dominant_axis(ids: NDArray[np.int64], n: int, normals: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per group, the axis the (3, N) normal columns cluster around (sign-free: top eigenvector of sum n n^T)."""
    S = np.empty((n, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            S[:, a, b] = S[:, b, a] = _sums(ids, n, normals[a] * normals[b])
    _, vec = np.linalg.eigh(S)
    return vec[:, :, 2]


def _dot_gathered(columns: NDArray[np.float64], table: NDArray[np.float64], ids: NDArray[np.int64]) -> NDArray[np.float64]:
    """``columns[:, i] . table[ids[i]]`` for every point i: (3, N) columns against rows of a small (G, 3) table."""
    t = np.ascontiguousarray(table.T)
    return columns[0] * t[0].take(ids) + columns[1] * t[1].take(ids) + columns[2] * t[2].take(ids)


def _tangent_basis(n: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    helper = np.where(np.abs(n[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(n, u)


# ---------------------------------------------------------------------------------------------- detector


class DoubleWallConfig(BaseModel):
    """Parameters of the double-wall detector and the smearing score (indoor RGB-D defaults)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    voxel_sizes_m: tuple[float, ...] = Field((0.1, 0.2, 0.4), description="voxel sizes evaluated (m); use ~0.25..2 m outdoors")
    cell_fraction: float = Field(0.25, gt=0.0, le=1.0, description="lateral cell size as a fraction of the voxel size")
    max_cell_m: float | None = Field(None, gt=0.0, description="upper bound of the lateral cell size (m); relief finer than a cell is not removed")
    normal_max_angle_deg: float = Field(20.0, gt=0.0, lt=90.0, description="own-frame normals within this angle of the voxel's dominant normal")
    second_surface: bool = Field(True, description="also evaluate the dominant normal of the points that disagree with the first")
    min_points: int = Field(40, ge=4, description="points per surface group to evaluate it")
    min_points_per_frame: int = Field(2, ge=1, description="points a frame needs in a group to count")
    frame_jitter_floor_m: float = Field(0.002, gt=0.0, description="floor of a frame's mean-offset uncertainty (m): no frame counts as exact")
    min_frames: int = Field(3, ge=2, description="frames per surface group to evaluate it")
    min_frames_per_layer: int = Field(2, ge=1, description="frames each layer needs")
    min_layer_fraction: float = Field(0.1, ge=0.0, lt=0.5, description="the smaller layer holds at least this share of the points")
    min_separation_m: float = Field(0.01, ge=0.0, description="smallest separation reported as a double wall (m)")
    min_separation_sigmas: float = Field(3.0, ge=0.0, description="separation / its uncertainty at least this")
    min_ashman_d: float = Field(4.0, ge=0.0, description="separation relative to the layers' frame-to-frame widths")
    min_delta_bic: float = Field(10.0, description="BIC(one layer) - BIC(two layers) at least this")
    bic_mixing_weight: float = Field(1.0, ge=0.0, le=1.0, description="weight of the layer-share term of the two-layer likelihood")
    min_purity: float = Field(0.85, ge=0.0, le=1.5, description="noise-normalised time purity (1: every frame on one layer; 0: as mixed as chance)")
    min_overlap: float = Field(0.25, ge=0.0, le=1.0, description="share of the smaller layer's points in lateral cells both layers saw")
    min_shared_cells: int = Field(2, ge=1, description="lateral cells seen by both layers")
    kmeans_iterations: int = Field(8, ge=1, description="Lloyd iterations of the 1-D two-layer split")
    visit_gap_m: float = Field(1.0, gt=0.0, description="a surface seen again after this much travel without seeing it is a new visit (m)")
    merge_angle_deg: float = Field(25.0, gt=0.0, description="flagged voxels merge into one region when their normals agree within this")


@dataclass(frozen=True)
class ScaleResult:
    """Every evaluated surface group (voxel x dominant normal x sensor side) at one voxel size."""

    voxel_size_m: float
    centers_m: NDArray[np.float64]
    normals: NDArray[np.float64]
    n_points: NDArray[np.int64]
    n_frames: NDArray[np.int64]
    evaluated: NDArray[np.bool_]
    flagged: NDArray[np.bool_]
    separation_m: NDArray[np.float64]
    """B minus A along the normal, in the shared cells (signed; A is the layer of lower mean offset)."""
    separation_sigma_m: NDArray[np.float64]
    ashman_d: NDArray[np.float64]
    delta_bic: NDArray[np.float64]
    purity: NDArray[np.float64]
    overlap: NDArray[np.float64]
    layer_fraction: NDArray[np.float64]
    smear_m: NDArray[np.float64]
    """Per group: sqrt of the between-frame dispersion of mean offsets minus what noise explains."""
    path_span_m: NDArray[np.float64]
    """Per group: distance travelled between the first and the last frame that saw it."""
    visit_smear_m: NDArray[np.float64]
    """Per group: sqrt of the between-visit dispersion of mean offsets minus what noise and within-visit jitter
    explain (NaN for a group seen in one visit)."""
    n_visits: NDArray[np.int64]
    """Per group: visits (runs of frames without ``visit_gap_m`` of travel between them)."""
    gf_group: NDArray[np.int64]
    """Per (group, frame) pair: the group, the frame row, its point count, its mean residual offset, its layer
    (0: A, 1: B, -1: none)."""
    gf_frame: NDArray[np.int64]
    gf_points: NDArray[np.int64]
    gf_mean_m: NDArray[np.float64]
    gf_layer: NDArray[np.int8]
    grouped_point_index: NDArray[np.int32] | None = None
    """Index into the placed cloud of every point in a surface group, and its group (for the coverage report)."""
    grouped_point_group: NDArray[np.int32] | None = None
    min_separation_m: float = 0.0

    @property
    def voxels_evaluated(self) -> int:
        return int(self.evaluated.sum())

    @property
    def voxels_flagged(self) -> int:
        return int(self.flagged.sum())

    @property
    def score_m(self) -> float:
        """Smearing score: RMS over evaluated groups of how far their visits disagree beyond noise and
        within-visit jitter (m); a group seen in one visit shows no drift and counts as 0."""
        s = self.visit_smear_m[self.evaluated]
        return float(np.sqrt(np.mean(np.nan_to_num(s, nan=0.0) ** 2))) if s.size else float("nan")

    @property
    def frame_score_m(self) -> float:
        """The frame-level smearing score: RMS over evaluated groups of their excess between-frame dispersion (m).
        Sees a jump inside one pass too, but also the frame-to-frame jitter of every pose estimate."""
        s = self.smear_m[self.evaluated]
        return float(np.sqrt(np.mean(s**2))) if s.size else float("nan")

    @property
    def groups_revisited(self) -> int:
        """Evaluated groups seen in two visits or more (the groups the smearing score can see drift in)."""
        return int(np.count_nonzero(self.evaluated & (self.n_visits >= 2)))

    def revisit_score_m(self, min_path_m: float = 1.0) -> float:
        """The frame-level smearing score over the groups seen again after ``min_path_m`` of travel."""
        s = self.smear_m[self.evaluated & (self.path_span_m >= min_path_m)]
        return float(np.sqrt(np.mean(s**2))) if s.size else float("nan")


@dataclass(frozen=True)
class DoubleWallRegion:
    """Flagged surface groups merged into one region (adjacent, same normal, same separation)."""

    center_m: NDArray[np.float64]
    normal: NDArray[np.float64]
    separation_m: float
    separation_sigma_m: float
    offset_b_minus_a_m: float
    """Signed: where layer B (the later frames) lies relative to layer A, along ``normal``."""
    frames_a: NDArray[np.int64]
    frames_b: NDArray[np.int64]
    stamp_ns_a: tuple[int, int]
    stamp_ns_b: tuple[int, int]
    n_voxels: int
    voxel_sizes_m: tuple[float, ...]
    n_points: int
    rows_a: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    """Frame rows (of the diagnostic cloud) of layer A and B: what :mod:`driftmap.diagnostics.causes` reads."""
    rows_b: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    members: tuple[tuple[int, int], ...] = ()
    """(scale index, group index) of the flagged surface groups merged into this region."""

    def to_json(self) -> dict:
        return {
            "center_m": [float(v) for v in self.center_m],
            "normal": [float(v) for v in self.normal],
            "separation_m": float(self.separation_m),
            "separation_sigma_m": float(self.separation_sigma_m),
            "frames_a": [int(v) for v in self.frames_a],
            "frames_b": [int(v) for v in self.frames_b],
            "stamp_ns_a": [int(self.stamp_ns_a[0]), int(self.stamp_ns_a[1])],
            "stamp_ns_b": [int(self.stamp_ns_b[0]), int(self.stamp_ns_b[1])],
            "offset_b_minus_a_m": float(self.offset_b_minus_a_m),
            "n_voxels": int(self.n_voxels),
            "voxel_sizes_m": [float(v) for v in self.voxel_sizes_m],
            "n_points": int(self.n_points),
        }


@dataclass(frozen=True)
class DoubleWallResult:
    scales: list[ScaleResult]
    regions: list[DoubleWallRegion]
    frame_ids: NDArray[np.int64]
    stamps_ns: NDArray[np.int64]
    config: DoubleWallConfig = field(default_factory=DoubleWallConfig)

    @property
    def voxels_evaluated(self) -> int:
        return sum(s.voxels_evaluated for s in self.scales)

    @property
    def voxels_flagged(self) -> int:
        return sum(s.voxels_flagged for s in self.scales)

    @property
    def fraction_flagged(self) -> float:
        n = self.voxels_evaluated
        return self.voxels_flagged / n if n else 0.0

    @property
    def median_separation_m(self) -> float | None:
        seps = np.concatenate([np.abs(s.separation_m[s.flagged]) for s in self.scales]) if self.scales else np.zeros(0)
        return float(np.median(seps)) if seps.size else None

    @property
    def score_per_scale_m(self) -> dict[float, float]:
        return {s.voxel_size_m: s.score_m for s in self.scales}

    @property
    def smearing_score_m(self) -> float:
        """RMS of the per-scale smearing scores (every scale weighs the same)."""
        return _rms([s.score_m for s in self.scales])

    @property
    def voxels_revisited(self) -> int:
        """Evaluated groups (all scales) seen in two visits or more: 0 means the smearing score cannot see drift."""
        return sum(s.groups_revisited for s in self.scales)

    @property
    def frame_smearing_score_m(self) -> float:
        """RMS of the per-scale frame-level smearing scores."""
        return _rms([s.frame_score_m for s in self.scales])

    def revisit_score_m(self, min_path_m: float = 1.0) -> float:
        """The frame-level score over revisited groups only (RMS of the per-scale values); NaN without a revisit."""
        vals = np.array([v for s in self.scales if np.isfinite(v := s.revisit_score_m(min_path_m))])
        return float(np.sqrt(np.mean(vals**2))) if vals.size else float("nan")

    def to_json(self) -> dict:
        return {
            "voxels_evaluated": self.voxels_evaluated,
            "voxels_flagged": self.voxels_flagged,
            "fraction_flagged": self.fraction_flagged,
            "median_separation_m": self.median_separation_m,
            "regions": [r.to_json() for r in self.regions],
            "per_scale": [
                {"voxel_size_m": s.voxel_size_m, "voxels_evaluated": s.voxels_evaluated, "voxels_flagged": s.voxels_flagged,
                 "smearing_score_m": _finite_or_none(s.score_m), "smearing_score_frames_m": _finite_or_none(s.frame_score_m),
                 "voxels_revisited": s.groups_revisited}
                for s in self.scales
            ],
        }


def _rms(values: Sequence[float]) -> float:
    vals = np.array([v for v in values if np.isfinite(v)])
    return float(np.sqrt(np.mean(vals**2))) if vals.size else float("nan")


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def detect_double_walls(cloud: PlacedCloud, config: DoubleWallConfig | None = None) -> DoubleWallResult:
    """Evaluate every voxel at every configured size; flag double walls and merge them into regions."""
    cfg = config or DoubleWallConfig()
    if not cfg.voxel_sizes_m or min(cfg.voxel_sizes_m) <= 0:
        raise ConfigError(f"voxel_sizes_m must be positive, got {cfg.voxel_sizes_m}")
    scales = [_evaluate_scale(cloud, float(s), cfg) for s in cfg.voxel_sizes_m]
    regions = _merge_regions(scales, cloud, cfg)
    for s in scales:
        logger.info("double walls at %.2f m: %d of %d surface groups flagged; smearing %.4f m", s.voxel_size_m,
                    s.voxels_flagged, s.voxels_evaluated, s.score_m)
    return DoubleWallResult(scales, regions, cloud.frame_ids.copy(), cloud.stamps_ns.copy(), cfg)


@dataclass(frozen=True)
class SurfaceGroups:
    """Points sorted into surface groups (voxel x dominant normal x sensor side) and lateral cells."""

    voxel_size_m: float
    point_index: NDArray[np.int64]
    """Index into the placed cloud of every grouped point."""
    group: NDArray[np.int64]
    cell: NDArray[np.int64]
    offset_m: NDArray[np.float64]
    """Offset along the group normal from the group centroid."""
    n_groups: int
    n_cells: int
    normals: NDArray[np.float64]
    centers_m: NDArray[np.float64]
    n_points: NDArray[np.float64]
    cell_group: NDArray[np.int64]


def surface_groups(cloud: PlacedCloud, size_m: float, *, normal_max_angle_deg: float = 20.0, second_surface: bool = True,
                   min_points: int = 40, cell_fraction: float = 0.25, max_cell_m: float | None = None,
                   join_faces: bool = True) -> SurfaceGroups:
    """Group the samples by voxel, by the voxel's dominant own-frame normal (and a second one) and by the side
    the sensor was on; cut every group into lateral cells of ``cell_fraction * size_m``.

    With ``join_faces`` a surface that lies close to a voxel face along its normal (both groups' centroids within
    0.35 voxel of it) is one group across that face: otherwise the face cuts the noise band of the surface (and of
    the layers of a double wall) along the normal, the layer means are truncated towards each other and the
    separation reads short (or the two layers land in two groups and are not seen at all)."""
    P, Nw = cloud.world_columns  # (3, N) columns
    n_pts = P.shape[1]
    cos_max = math.cos(math.radians(normal_max_angle_deg))
    keys, lo, span = _grid_keys(P, size_m) if n_pts else (np.zeros(0, np.int64), np.zeros(3, np.int64), np.ones(3, np.int64))
    vox, vox_keys = _dense_ids(keys)
    n_vox = int(vox.max()) + 1 if len(vox) else 0
    axis1 = _dominant_axis(vox, n_vox, Nw)
    c1 = _dot_gathered(Nw, axis1, vox)
    surface = np.where(np.abs(c1) >= cos_max, 0, -1)
    side = c1 > 0
    if second_surface:
        rest = np.flatnonzero(surface < 0)
        vox_r, Nw_r = vox[rest], Nw.take(rest, axis=1)
        axis2 = _dominant_axis(vox_r, n_vox, Nw_r)
        c2 = _dot_gathered(Nw_r, axis2, vox_r)
        ok2 = np.abs(c2) >= cos_max
        surface[rest[ok2]] = 1
        side[rest] = np.where(ok2, c2 > 0, side[rest])
    use = np.flatnonzero(surface >= 0)
    g, g_keys = _dense_ids(vox[use] * 4 + surface[use] * 2 + side[use])
    G = int(g.max()) + 1 if len(g) else 0
    # per group: point count, sum of normals, sum of positions (points in no group go to the extra bin G)
    g_all = np.full(n_pts, G, np.int64)
    g_all[use] = g
    cnt = _sums(g, G)
    n_sum = np.stack([_sums(g_all, G + 1, Nw[k])[:G] for k in range(3)], axis=1)
    p_sum = np.stack([_sums(g_all, G + 1, P[k])[:G] for k in range(3)], axis=1)
    label = np.arange(G, dtype=np.int64)
    if join_faces and G:
        label, n_lab = _join_across_faces(cnt, n_sum, p_sum, g_keys, vox_keys, lo, span, size_m, cos_max)
        if n_lab < G:
            G = n_lab
            cnt = _sums(label, G, cnt)
            n_sum = np.stack([_sums(label, G, n_sum[:, k]) for k in range(3)], axis=1)
            p_sum = np.stack([_sums(label, G, p_sum[:, k]) for k in range(3)], axis=1)
    big = cnt >= min_points
    final = np.where(big, np.cumsum(big) - 1, -1)[label]  # first-pass group -> kept group (-1: too few points)
    g = final[g]
    keep = g >= 0
    use, g = use[keep], g[keep]
    G = int(big.sum())
    cnt = cnt[big]
    normal = n_sum[big]
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    center = p_sum[big] / np.maximum(cnt, 1)[:, None]
    p = P.take(use, axis=1)
    def from_center(axes: NDArray[np.float64]) -> NDArray[np.float64]:
        """Each point's offset from its group's centroid along the group's axis: ``p . a - c . a``."""
        return _dot_gathered(p, axes, g) - np.einsum("ij,ij->i", center, axes).take(g)

    o = from_center(normal)  # along the normal; in the tangent plane below
    cell_m = size_m * cell_fraction if max_cell_m is None else min(size_m * cell_fraction, max_cell_m)
    K = int(math.ceil(2.0 * math.sqrt(6.0) * size_m / cell_m)) + 2  # a group joined across a face spans 1 x 1 x 2 voxels
    u, v = _tangent_basis(normal) if G else (np.zeros((0, 3)), np.zeros((0, 3)))
    cu = np.clip(np.floor(from_center(u) / cell_m).astype(np.int64) + K // 2, 0, K - 1)
    cv = np.clip(np.floor(from_center(v) / cell_m).astype(np.int64) + K // 2, 0, K - 1)
    c, _ = _dense_ids((g * K + cu) * K + cv)
    C = int(c.max()) + 1 if len(c) else 0
    cell_group = np.zeros(C, np.int64)
    cell_group[c] = g
    return SurfaceGroups(size_m, use, g, c, o, G, C, normal, center, cnt, cell_group)


def _join_across_faces(cnt: NDArray[np.float64], n_sum: NDArray[np.float64], p_sum: NDArray[np.float64],
                       g_keys: NDArray[np.int64], vox_keys: NDArray[np.int64], lo: NDArray[np.int64], span: NDArray[np.int64],
                       size_m: float, cos_max: float, margin: float = 0.35, max_tilt_deg: float = 10.0) -> tuple[NDArray[np.int64], int]:
    """Join the group pairs that are one surface cut by a voxel face along its normal.

    Groups (keys ``g_keys`` = ``vox * 4 + surface * 2 + side``, per-group point counts and sums of normals and
    positions) in voxels adjacent along the grid axis ``a`` closest to their normal are joined when their normals
    agree within the grouping angle, both centroids lie within ``margin`` voxels of the shared face and ``a`` is the
    closest axis of both. A centroid is near one face at most (``margin < 0.5``), so a joined group spans two
    voxels at most (usually a pair of groups; the first and second surface of one voxel may both join the same
    neighbour). Returns a label per group and the number of labels."""
    G = len(g_keys)
    normal = n_sum / np.maximum(np.linalg.norm(n_sum, axis=1, keepdims=True), 1e-12)
    center = p_sum / np.maximum(cnt, 1)[:, None]
    key = vox_keys[g_keys // 4]  # the group's voxel, decoded to its (shifted) grid coordinates
    vk = np.stack([key // (span[1] * span[2]), (key // span[2]) % span[1], key % span[2]], axis=1)
    axis = np.argmax(np.abs(normal), axis=1)
    rows = np.arange(G)
    frac = center[rows, axis] / size_m - (vk[rows, axis] + lo[axis])  # 0 .. 1 inside the voxel along the axis
    aligned = np.abs(normal[rows, axis]) >= math.cos(math.radians(max_tilt_deg))  # the face cuts along the normal
    near_hi, near_lo = aligned & (frac >= 1.0 - margin), aligned & (frac <= margin)
    src = np.flatnonzero(near_hi & (vk[rows, axis] + 1 < span[axis]))
    identity = (np.arange(G, dtype=np.int64), G)
    if not len(src):
        return identity
    nb = vk[src].copy()
    nb[np.arange(len(src)), axis[src]] += 1
    nb_key = (nb[:, 0] * span[1] + nb[:, 1]) * span[2] + nb[:, 2]
    nb_vox = np.searchsorted(vox_keys, nb_key)
    nb_vox_ok = (nb_vox < len(vox_keys)) & (vox_keys[np.minimum(nb_vox, len(vox_keys) - 1)] == nb_key)
    best, best_dot = np.full(len(src), -1, np.int64), np.full(len(src), -np.inf)
    for sub in range(4):  # surface 0/1 x side 0/1 in the neighbouring voxel
        sub_key = nb_vox * 4 + sub
        h = np.minimum(np.searchsorted(g_keys, sub_key), G - 1)
        dot = np.einsum("ij,ij->i", normal[src], normal[h])
        ok = nb_vox_ok & (g_keys[h] == sub_key) & near_lo[h] & (axis[h] == axis[src]) & (dot >= cos_max) & (dot > best_dot)
        best = np.where(ok, h, best)
        best_dot = np.where(ok, dot, best_dot)
    pair = best >= 0
    if not pair.any():
        return identity
    A = coo_matrix((np.ones(int(pair.sum())), (src[pair], best[pair])), shape=(G, G))
    n_lab, labels = connected_components(A, directed=False)
    return labels.astype(np.int64), int(n_lab)


def _evaluate_scale(cloud: PlacedCloud, size_m: float, cfg: DoubleWallConfig) -> ScaleResult:
    M = cloud.samples.n_frames
    sg = surface_groups(cloud, size_m, normal_max_angle_deg=cfg.normal_max_angle_deg, second_surface=cfg.second_surface,
                        min_points=cfg.min_points, cell_fraction=cfg.cell_fraction, max_cell_m=cfg.max_cell_m)
    g, c, o, G, C = sg.group, sg.cell, sg.offset_m, sg.n_groups, sg.n_cells
    f = cloud.frame_index[sg.point_index]
    s2 = cloud.sigma_normal_m[sg.point_index].astype(np.float64) ** 2
    normal, center, cnt, cell_group = sg.normals, sg.centers_m, sg.n_points, sg.cell_group

    # lateral cells on the surface: the reference that removes relief every frame sees
    c_n = _sums(c, C)
    c_sum = _sums(c, C, o)
    ff = f.astype(np.float64)
    c_f1, c_f2 = _sums(c, C, ff), _sums(c, C, ff * ff)
    multi = (c_f2 / np.maximum(c_n, 1) - (c_f1 / np.maximum(c_n, 1)) ** 2) > 1e-9  # >1 distinct frame
    r = o - c_sum[c] / np.maximum(c_n[c], 1)
    valid = multi[c]

    # per (group, frame): mean residual offset and the noise of that mean
    gf, gf_keys = _dense_ids(g * M + f)
    E = len(gf_keys)
    e_group, e_frame = gf_keys // M, gf_keys % M
    wv = valid.astype(np.float64)
    e_n = _sums(gf, E, wv)
    e_sum = _sums(gf, E, r * wv)
    e_sq = _sums(gf, E, r * r * wv)
    e_s2 = _sums(gf, E, s2 * wv)
    e_ok = e_n >= cfg.min_points_per_frame
    okf = e_ok.astype(np.float64)
    e_mean = np.where(e_ok, e_sum / np.maximum(e_n, 1), 0.0)
    # per-point scatter along the normal: pooled within-frame variance, at least the sensor model's
    within = np.maximum(e_sq - e_n * e_mean**2, 0.0) * okf
    dof = _sums(e_group, G, np.maximum(e_n - 1, 0) * okf)
    point_var = np.maximum(_sums(e_group, G, within) / np.maximum(dof, 1),
                           _sums(e_group, G, e_s2 * okf) / np.maximum(_sums(e_group, G, e_n * okf), 1))
    point_var = np.maximum(point_var, 1e-8)
    e_v = np.where(e_ok, point_var[e_group] / np.maximum(e_n, 1), np.inf)
    w = np.where(e_ok, e_n, 0.0)
    n_frames = _sums(e_group, G, okf).astype(np.int64)
    n_valid = _sums(e_group, G, w)
    evaluated = (n_frames >= cfg.min_frames) & (n_valid >= cfg.min_points)

    # smearing: between-frame dispersion of mean residual offsets (point-weighted) minus the noise part
    W = np.maximum(n_valid, 1e-12)
    mbar = _sums(e_group, G, w * e_mean) / W
    disp = _sums(e_group, G, w * (e_mean - mbar[e_group]) ** 2) / W
    noise = point_var * n_frames / W
    smear = np.sqrt(np.maximum(disp - noise, 0.0))
    # path travelled between the first and the last frame that saw the group (a revisit when large)
    e_path = cloud.path_length_m[e_frame]
    s_lo, s_hi = np.full(G, np.inf), np.full(G, -np.inf)
    np.minimum.at(s_lo, e_group[e_ok], e_path[e_ok])
    np.maximum.at(s_hi, e_group[e_ok], e_path[e_ok])
    path_span = np.where(n_frames > 0, s_hi - s_lo, 0.0)
    visit_smear, n_visits = _visit_smear(e_group, e_path, e_n.astype(np.float64), e_mean, e_ok, point_var, G, cfg.visit_gap_m)

    # two layers of frames: precision-weighted 1-D 2-means on the per-frame means
    floor2 = cfg.frame_jitter_floor_m**2
    pw = np.where(e_ok, 1.0 / (np.where(e_ok, e_v, 1.0) + floor2), 0.0)

    def wmean(weights: NDArray[np.float64], values: NDArray[np.float64]) -> NDArray[np.float64]:
        return _sums(e_group, G, weights * values) / np.maximum(_sums(e_group, G, weights), 1e-300)

    thr = wmean(pw, e_mean)
    for _ in range(cfg.kmeans_iterations):
        isB = e_mean > thr[e_group]
        muA, muB = wmean(pw * ~isB, e_mean), wmean(pw * isB, e_mean)
        both = (_sums(e_group, G, okf * ~isB) > 0) & (_sums(e_group, G, okf * isB) > 0)
        thr = np.where(both, 0.5 * (muA + muB), thr)
    isB = e_mean > thr[e_group]
    nA, nB = _sums(e_group, G, okf * ~isB), _sums(e_group, G, okf * isB)
    wA, wB = _sums(e_group, G, w * ~isB), _sums(e_group, G, w * isB)
    ev = np.where(e_ok, e_v, 0.0)

    def layer_fit(member: NDArray[np.bool_]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Mean, between-frame jitter (moments, noise removed), observed width and log-likelihood of a layer."""
        m = member & e_ok
        wt = np.where(m, pw, 0.0)
        mu = wmean(wt, e_mean)
        obs = wmean(wt, (e_mean - mu[e_group]) ** 2)
        tau2 = np.maximum(obs - wmean(wt, ev), 0.0)
        for _ in range(2):
            wt = np.where(m, 1.0 / (tau2[e_group] + ev + floor2), 0.0)
            mu = wmean(wt, e_mean)
            tau2 = np.maximum(wmean(wt, (e_mean - mu[e_group]) ** 2) - wmean(wt, ev), 0.0)
        var = tau2[e_group] + ev + floor2
        ll = -0.5 * _sums(e_group, G, np.where(m, np.log(2 * np.pi * var) + (e_mean - mu[e_group]) ** 2 / var, 0.0))
        return mu, tau2, obs, ll

    muA, tauA2, obsA, llA = layer_fit(~isB)
    muB, tauB2, obsB, llB = layer_fit(isB)
    _, _, _, ll1 = layer_fit(np.ones(E, bool))
    nF = np.maximum(nA + nB, 1)
    ll2 = llA + llB + cfg.bic_mixing_weight * (nA * np.log(np.maximum(nA, 1e-12) / nF) + nB * np.log(np.maximum(nB, 1e-12) / nF))
    delta_bic = 2.0 * (ll2 - ll1) - 3.0 * np.log(nF)
    ashman = (muB - muA) / np.sqrt(0.5 * (obsA + obsB) + floor2)
    precA = _sums(e_group, G, np.where(e_ok & ~isB, 1.0 / (tauA2[e_group] + ev + floor2), 0.0))
    precB = _sums(e_group, G, np.where(e_ok & isB, 1.0 / (tauB2[e_group] + ev + floor2), 0.0))

    # separation where both layers were seen: per lateral cell, mean(B) - mean(A) of the raw offsets
    e_layer = np.where(e_ok, isB.astype(np.int8), np.int8(-1))
    layer = e_layer[gf]
    inA, inB = (layer == 0).astype(np.float64), (layer == 1).astype(np.float64)
    cA, cB = _sums(c, C, inA), _sums(c, C, inB)
    sA, sB = _sums(c, C, inA * o), _sums(c, C, inB * o)
    shared = (cA > 0) & (cB > 0)
    d_c = np.where(shared, sB / np.maximum(cB, 1) - sA / np.maximum(cA, 1), 0.0)
    w_c = np.where(shared, cA * cB / np.maximum(cA + cB, 1), 0.0)
    Wc = _sums(cell_group, G, w_c)
    sep = _sums(cell_group, G, w_c * d_c) / np.maximum(Wc, 1e-12)
    var_c = _sums(cell_group, G, w_c * (d_c - sep[cell_group]) ** 2) / np.maximum(Wc, 1e-12)
    neff = Wc**2 / np.maximum(_sums(cell_group, G, w_c**2), 1e-12)
    n_shared = _sums(cell_group, G, shared.astype(np.float64))
    sep_sigma = np.sqrt(var_c / np.maximum(neff, 1.0) + 1.0 / np.maximum(precA, 1e-12) + 1.0 / np.maximum(precB, 1e-12))
    # lateral overlap: share of the smaller layer's points in shared cells
    ptsA, ptsB = _sums(cell_group, G, cA), _sums(cell_group, G, cB)
    shA, shB = _sums(cell_group, G, cA * shared), _sums(cell_group, G, cB * shared)
    small_is_A = ptsA <= ptsB
    overlap = np.where(small_is_A, shA / np.maximum(ptsA, 1), shB / np.maximum(ptsB, 1))
    layer_fraction = np.minimum(wA, wB) / np.maximum(wA + wB, 1e-12)

    # time purity in the shared cells: a point lies on its frame's layer (beyond the midpoint)
    mid = np.where(shared, 0.5 * (sA / np.maximum(cA, 1) + sB / np.maximum(cB, 1)), 0.0)
    on_shared = shared[c] & (layer >= 0)
    sgn = np.where(layer == 1, 1.0, -1.0)
    correct = ((o - mid[c]) * sgn * np.sign(sep[g]) > 0) & on_shared
    expect = ndtr(np.abs(sep) / (2.0 * np.sqrt(point_var)))[g] * on_shared
    n_sh = _sums(g, G, on_shared.astype(np.float64))
    purity = (_sums(g, G, correct.astype(np.float64)) - 0.5 * n_sh) / np.maximum(_sums(g, G, expect) - 0.5 * n_sh, 1e-12)
    purity = np.clip(purity, 0.0, 1.5)

    abs_sep = np.abs(sep)
    flagged = (
        evaluated
        & (nA >= cfg.min_frames_per_layer) & (nB >= cfg.min_frames_per_layer)
        & (layer_fraction >= cfg.min_layer_fraction)
        & (n_shared >= cfg.min_shared_cells)
        & (overlap >= cfg.min_overlap)
        & (abs_sep >= cfg.min_separation_m)
        & (abs_sep >= cfg.min_separation_sigmas * sep_sigma)
        & (ashman >= cfg.min_ashman_d)
        & (delta_bic >= cfg.min_delta_bic)
        & (purity >= cfg.min_purity)
    )
    return ScaleResult(
        voxel_size_m=size_m, centers_m=center, normals=normal, n_points=cnt.astype(np.int64), n_frames=n_frames,
        evaluated=evaluated, flagged=flagged, separation_m=sep, separation_sigma_m=sep_sigma, ashman_d=ashman,
        delta_bic=delta_bic, purity=purity, overlap=overlap, layer_fraction=layer_fraction, smear_m=smear, path_span_m=path_span,
        visit_smear_m=visit_smear, n_visits=n_visits,
        gf_group=e_group, gf_frame=e_frame, gf_points=e_n.astype(np.int64), gf_mean_m=e_mean, gf_layer=e_layer,
        grouped_point_index=sg.point_index.astype(np.int32), grouped_point_group=g.astype(np.int32),
        min_separation_m=cfg.min_separation_m,
    )


def _visit_smear(e_group: NDArray[np.int64], e_path: NDArray[np.float64], e_n: NDArray[np.float64], e_mean: NDArray[np.float64],
                 e_ok: NDArray[np.bool_], point_var: NDArray[np.float64], G: int, gap_m: float) -> tuple[NDArray, NDArray]:
    """Per group: how far its visits disagree beyond what noise and frame-to-frame jitter explain (m; NaN with one visit).

    A visit is a run of the group's frames, ordered by path travelled, without a gap of more than ``gap_m``. Each
    visit's mean offset is point-weighted; the frame-to-frame jitter *within* visits (sensor distortion that changes
    with the viewpoint, pose jitter) is estimated from the group itself and removed from the visit means' variance, so
    what is left is the disagreement that needs travel: drift, a pose jump, a loop that did not close."""
    idx = np.flatnonzero(e_ok)
    n_visits = np.zeros(G, np.int64)
    out = np.full(G, np.nan)
    if idx.size == 0:
        return out, n_visits
    idx = idx[np.lexsort((e_path[idx], e_group[idx]))]
    g, p, n, m = e_group[idx], e_path[idx], e_n[idx], e_mean[idx]
    start = np.r_[True, (g[1:] != g[:-1]) | (np.diff(p) > gap_m)]
    v = np.cumsum(start) - 1
    V = int(v[-1]) + 1
    vg = g[start]
    n_visits = np.bincount(vg, minlength=G).astype(np.int64)
    N = _sums(v, V, n)
    mv = _sums(v, V, n * m) / np.maximum(N, 1e-12)
    pv = point_var[vg]
    # within-visit jitter tau^2 (pooled per group): E[sum n (m - m_v)^2] = pv (F_v - 1) + tau^2 (N_v - sum n^2 / N_v)
    n2 = _sums(v, V, n * n)
    F = np.bincount(v, minlength=V).astype(np.float64)
    A = _sums(vg, G, _sums(v, V, n * (m - mv[v]) ** 2))
    B = _sums(vg, G, pv * (F - 1.0))
    C = _sums(vg, G, N - n2 / np.maximum(N, 1e-12))
    tau2 = np.where(C > 0, np.maximum(A - B, 0.0) / np.maximum(C, 1e-12), 0.0)
    var_v = pv / np.maximum(N, 1e-12) + tau2[vg] * n2 / np.maximum(N, 1e-12) ** 2
    # between visits: point-weighted dispersion of the visit means minus its expectation under noise alone
    W = _sums(vg, G, N)
    mbar = _sums(vg, G, N * mv) / np.maximum(W, 1e-12)
    disp = _sums(vg, G, N * (mv - mbar[vg]) ** 2) / np.maximum(W, 1e-12)
    noise = _sums(vg, G, N * var_v * (1.0 - N / np.maximum(W[vg], 1e-12))) / np.maximum(W, 1e-12)
    out = np.where(n_visits >= 2, np.sqrt(np.maximum(disp - noise, 0.0)), np.nan)
    return out, n_visits


def _merge_regions(scales: list[ScaleResult], cloud: PlacedCloud, cfg: DoubleWallConfig) -> list[DoubleWallRegion]:
    """Connected flagged groups (overlapping voxels, normals within ``merge_angle_deg``, compatible separations)."""
    items = []
    for si, s in enumerate(scales):
        for gi in np.flatnonzero(s.flagged):
            items.append((si, int(gi)))
    if not items:
        return []
    centers = np.array([scales[si].centers_m[gi] for si, gi in items])
    normals = np.array([scales[si].normals[gi] for si, gi in items])
    sizes = np.array([scales[si].voxel_size_m for si, _ in items])
    seps = np.array([scales[si].separation_m[gi] for si, gi in items])
    sigmas = np.array([scales[si].separation_sigma_m[gi] for si, gi in items])
    npts = np.array([scales[si].n_points[gi] for si, gi in items], dtype=np.float64)
    # orient the layers by time: A = the layer seen earlier
    stamps = cloud.stamps_ns.astype(np.float64)
    frames_of: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []
    by_scale = {}
    for si, s in enumerate(scales):
        order = np.argsort(s.gf_group, kind="stable")
        starts = np.searchsorted(s.gf_group[order], np.arange(len(s.evaluated) + 1))
        by_scale[si] = (order, starts)
    flip = np.zeros(len(items), bool)
    for k, (si, gi) in enumerate(items):
        order, starts = by_scale[si]
        rows = order[starts[gi]:starts[gi + 1]]
        lay, fr = scales[si].gf_layer[rows], scales[si].gf_frame[rows]
        fa, fb = fr[lay == 0], fr[lay == 1]
        if np.median(stamps[fb]) < np.median(stamps[fa]):
            fa, fb = fb, fa
            flip[k] = True
        frames_of.append((fa, fb))
    signed = np.where(flip, -seps, seps)
    tree = cKDTree(centers)
    pairs = tree.query_pairs(r=float(sizes.max()) * 1.8, output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        near = np.linalg.norm(centers[i] - centers[j], axis=1) <= 0.9 * (sizes[i] + sizes[j])
        same_n = np.einsum("ij,ij->i", normals[i], normals[j]) >= math.cos(math.radians(cfg.merge_angle_deg))
        tol = 3.0 * np.hypot(sigmas[i], sigmas[j]) + 0.25 * np.maximum(np.abs(signed[i]), np.abs(signed[j]))
        same_s = np.abs(signed[i] - signed[j]) <= tol
        keep = near & same_n & same_s
        i, j = i[keep], j[keep]
    else:
        i = j = np.zeros(0, np.int64)
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(len(items), len(items)))
    n_comp, label = connected_components(graph, directed=False)
    regions = []
    ids = cloud.frame_ids
    for comp in range(n_comp):
        members = np.flatnonzero(label == comp)
        wts = npts[members]
        center = np.average(centers[members], axis=0, weights=wts)
        nsum = np.sum(normals[members] * wts[:, None], axis=0)
        normal = nsum / max(np.linalg.norm(nsum), 1e-12)
        iv = 1.0 / np.maximum(sigmas[members], 1e-6) ** 2
        off = float(np.sum(iv * signed[members]) / np.sum(iv))
        sig = float(max(np.sqrt(1.0 / np.sum(iv)) * math.sqrt(len({items[m][0] for m in members})),
                        np.std(signed[members]) / math.sqrt(len(members)) if len(members) > 1 else 0.0))
        fa = np.unique(np.concatenate([frames_of[m][0] for m in members]))
        fb = np.unique(np.concatenate([frames_of[m][1] for m in members]))
        st = cloud.stamps_ns
        regions.append(DoubleWallRegion(
            center_m=center, normal=normal, separation_m=abs(off), separation_sigma_m=sig, offset_b_minus_a_m=off,
            frames_a=ids[fa], frames_b=ids[fb],
            stamp_ns_a=(int(st[fa].min()), int(st[fa].max())), stamp_ns_b=(int(st[fb].min()), int(st[fb].max())),
            n_voxels=len(members), voxel_sizes_m=tuple(sorted({float(sizes[m]) for m in members})), n_points=int(wts.sum()),
            rows_a=fa, rows_b=fb, members=tuple(items[m] for m in members),
        ))
    regions.sort(key=lambda r: -r.n_points)
    return regions


# ---------------------------------------------------------------------------------------------- MME / MPV


@dataclass(frozen=True)
class MapEntropy:
    """Mean Map Entropy and Mean Plane Variance with the neighbourhood rules that produced them."""

    mme: float
    """Mean over points of h = 0.5 ln det(2 pi e Sigma) of the neighbours within ``radius_m`` (nats; lower is crisper)."""
    mpv_m2: float
    """Mean over points of the smallest eigenvalue of the same covariance (m^2; Skoltech map-metrics' definition)."""
    radius_m: float
    min_neighbors: int
    max_neighbors: int
    n_points_used: int
    n_points_queried: int


def map_entropy(points_world: NDArray[np.floating], *, radius_m: float = 0.1, min_neighbors: int = 10,
                max_neighbors: int = 64, max_query_points: int | None = 100_000, seed: int = 0,
                tree: cKDTree | None = None) -> MapEntropy:
    """MME and MPV (Razlaw et al. 2015; Kornilova & Ferrer 2021) on a point set.

    Rules: per query point, the neighbours within ``radius_m`` (itself included), at most the
    ``max_neighbors`` nearest; points with fewer than ``min_neighbors`` are skipped (not counted). Up to
    ``max_query_points`` query points are drawn at random (all neighbours still come from the full set).
    """
    pts = np.asarray(points_world, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GeometryError(f"map_entropy: expected (N, 3) points, got {pts.shape}")
    if len(pts) == 0:
        return MapEntropy(float("nan"), float("nan"), radius_m, min_neighbors, max_neighbors, 0, 0)
    rng = np.random.default_rng(seed)
    q = np.arange(len(pts)) if max_query_points is None or len(pts) <= max_query_points else rng.choice(len(pts), max_query_points, replace=False)
    tree = tree or cKDTree(pts)
    dist, idx = tree.query(pts[q], k=max_neighbors, distance_upper_bound=radius_m, workers=-1)
    ok = np.isfinite(dist)
    n = ok.sum(axis=1)
    use = n >= min_neighbors
    ok, idx, n = ok[use], idx[use], n[use]
    if not len(n):
        return MapEntropy(float("nan"), float("nan"), radius_m, min_neighbors, max_neighbors, 0, len(q))
    nb = pts[np.where(ok, idx, 0)] * ok[:, :, None]
    mean = nb.sum(axis=1) / n[:, None]
    d = (nb - mean[:, None, :]) * ok[:, :, None]
    cov = np.einsum("nki,nkj->nij", d, d) / n[:, None, None]
    lam = np.linalg.eigvalsh(cov)
    det = np.prod(np.maximum(lam, 0.0), axis=1) * (2 * np.pi * np.e) ** 3
    good = det > 0
    h = 0.5 * np.log(det[good])
    return MapEntropy(float(np.mean(h)) if good.any() else float("nan"), float(np.mean(np.maximum(lam[:, 0], 0.0))),
                      radius_m, min_neighbors, max_neighbors, int(good.sum()), len(q))
