"""Change vs misalignment between the sessions of a merged store (issue 26): where one session holds a surface and
another saw free space through the same place, the world changed (a chair moved, a door closed); a surface of one
session a few centimetres off another's is a misalignment (a double wall), never a change.

Each session gets its own occupancy counts on one grid (:class:`~driftmap.volume.VolumeLayers` of its frames only:
OctoMap's rays from every frame's sensor origin through its points). For sessions ``i < j`` (merge order):

- ``added``: voxels that are a surface of ``j`` (occupied, at least ``min_surface_hits`` points) where ``i``
  confidently saw free space;
- ``removed``: surfaces of ``i`` where ``j`` confidently saw free space.

"Confidently free" is free in the session's own layers with at least ``min_free_misses`` rays through the voxel and
**farther than** ``margin_m`` **from any voxel that session's own rays ended in**: a surface of one session displaced
by less than the margin from the other's (a misalignment, the double-wall detector's business) lies where the other
session's free space touches its own surface, so it never reads as a change. The changed voxels are grouped into
regions (connected after a dilation by ``link_voxels``, so a chair's seat and legs are one region), each with its
centre, box, voxel count, the sessions and the stamps of the frames that saw the surface. The voxels that could be
judged (a surface of one session observed by the other) are counted, so the changed fraction has a denominator.

Everything here is vectorised over the grid (numpy / scipy.ndimage); nothing writes a file.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from driftmap.diagnostics.diagnose_config import DiagnoseConfig
from driftmap.errors import ConfigError
from driftmap.frame import SensorKind
from driftmap.volume import VolumeConfig, VolumeLayers
from driftmap.volume.defaults import resolve_config
from driftmap.volume.grid import GridSpec

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)

DEPTH_CHANGE_VOXEL_SIZE_M = 0.04
"""A depth camera's change voxel: twice the volumetric layers' 2 cm (a quarter of the memory per session; a chair's
2.4 cm leg still lands in one voxel). Its max range follows the layers' rule (the depth noise within 0.4 voxel:
about 3.1 m at 4 cm). LiDAR stores take the layers' own voxel."""


@dataclass(frozen=True)
class ChangeConfig:
    """Lengths and counts of the change test (:func:`session_changes`)."""

    voxel_size_m: float | None = None
    """None: :data:`DEPTH_CHANGE_VOXEL_SIZE_M` for a depth camera, the volumetric layers' default for a LiDAR"""
    margin_m: float | None = None
    """free space within this of a session's own surface is not evidence; None: the largest separation the double-wall
    detector reports for the store's scene (``DiagnoseConfig.for_store(store).revisits.max_detectable_m``: 20 cm
    indoors), so a misalignment the detector measures never reads as a change (trial 13: at a fixed 10 cm, a session
    misaligned by 15 cm read as 19 change regions, whole walls added and removed)"""
    min_free_misses: int = 2
    """rays that must have passed through a voxel for it to count as seen free"""
    min_surface_hits: int = 2
    """points that must have ended in a voxel for it to count as a surface"""
    link_voxels: int = 2
    """changed voxels up to twice this many voxels apart belong to one region (a chair's legs and its seat)"""
    min_region_voxels: int = 4
    """smaller groups are counted as changed voxels but reported as no region"""

    def __post_init__(self) -> None:
        if self.margin_m is not None and not (math.isfinite(self.margin_m) and self.margin_m >= 0):
            raise ConfigError(f"session changes: margin_m must be a finite length >= 0, got {self.margin_m!r}")
        if self.voxel_size_m is not None and not (math.isfinite(self.voxel_size_m) and self.voxel_size_m > 0):
            raise ConfigError(f"session changes: voxel_size_m must be > 0, got {self.voxel_size_m!r}")
        for name in ("min_free_misses", "min_surface_hits", "min_region_voxels"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"session changes: {name} must be >= 1, got {getattr(self, name)!r}")
        if int(self.link_voxels) < 0:
            raise ConfigError(f"session changes: link_voxels must be >= 0, got {self.link_voxels!r}")


@dataclass(frozen=True)
class ChangeRegion:
    """Connected changed voxels of one kind between two sessions."""

    kind: str
    """``added`` (a surface of the later session where the earlier saw free space) or ``removed`` (the reverse)"""
    session_surface: int
    """the session that holds the surface"""
    session_free: int
    """the session that saw free space there"""
    center_m: NDArray[np.float64]
    min_m: NDArray[np.float64]
    max_m: NDArray[np.float64]
    n_voxels: int
    surface_frames: NDArray[np.int64]
    """frames of ``session_surface`` whose points ended in the region"""
    surface_stamps_ns: tuple[int, int]
    free_stamps_ns: tuple[int, int]
    """the stamp span of ``session_free``'s frames"""

    @property
    def sessions(self) -> tuple[int, int]:
        """(earlier, later) session of the pair."""
        return (min(self.session_surface, self.session_free), max(self.session_surface, self.session_free))

    def contains_m(self, point_m: NDArray[np.floating], pad_m: float = 0.0) -> bool:
        p = np.asarray(point_m, dtype=np.float64)
        return bool(np.all(p >= self.min_m - pad_m) and np.all(p <= self.max_m + pad_m))

    def to_json(self) -> dict:
        return {
            "kind": self.kind,
            "sessions": list(self.sessions),
            "session_surface": int(self.session_surface),
            "session_free": int(self.session_free),
            "center_m": [float(v) for v in self.center_m],
            "min_m": [float(v) for v in self.min_m],
            "max_m": [float(v) for v in self.max_m],
            "extent_m": [float(v) for v in self.max_m - self.min_m],
            "n_voxels": int(self.n_voxels),
            "surface_frames": [int(f) for f in self.surface_frames],
            "surface_stamp_ns": [int(self.surface_stamps_ns[0]), int(self.surface_stamps_ns[1])],
            "free_stamp_ns": [int(self.free_stamps_ns[0]), int(self.free_stamps_ns[1])],
        }


@dataclass
class SessionChanges:
    """What :func:`session_changes` found for a merged store's revision."""

    revision: int
    sessions: list[int]
    regions: list[ChangeRegion]
    evaluated_voxels: int
    """voxels that could be judged: a surface of one session that another session observed (hit or passed)"""
    changed_voxels: int
    """voxels flagged added or removed (in regions or not)"""
    voxel_size_m: float
    max_range_m: float | None
    config: ChangeConfig
    voxels_per_session: dict[int, dict[str, int]] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def changed_fraction(self) -> float:
        return self.changed_voxels / self.evaluated_voxels if self.evaluated_voxels else 0.0

    def region_at(self, point_m: NDArray[np.floating], pad_m: float | None = None) -> int | None:
        """The index of the first region whose box (grown by ``pad_m``, default the margin) holds ``point_m``."""
        pad = float(self.config.margin_m or 0.0) if pad_m is None else pad_m
        for k, r in enumerate(self.regions):
            if r.contains_m(point_m, pad):
                return k
        return None

    def to_json(self) -> dict:
        c = self.config
        return {
            "revision": int(self.revision),
            "sessions": [int(s) for s in self.sessions],
            "regions": [r.to_json() for r in self.regions],
            "n_regions": len(self.regions),
            "kinds": {k: sum(r.kind == k for r in self.regions) for k in ("added", "removed")},
            "evaluated_voxels": int(self.evaluated_voxels),
            "changed_voxels": int(self.changed_voxels),
            "changed_fraction": float(self.changed_fraction),
            "changed_voxels_in_regions": int(sum(r.n_voxels for r in self.regions)),
            "voxel_size_m": float(self.voxel_size_m),
            "max_range_m": None if self.max_range_m is None else float(self.max_range_m),
            "voxels_per_session": {str(k): v for k, v in self.voxels_per_session.items()},
            "config": {"margin_m": c.margin_m, "min_free_misses": c.min_free_misses,
                       "min_surface_hits": c.min_surface_hits, "link_voxels": c.link_voxels,
                       "min_region_voxels": c.min_region_voxels},
            "seconds": round(self.seconds, 3),
        }


@dataclass
class _Session:
    layers: VolumeLayers
    surface: NDArray[np.bool_]
    """(X, Y, Z) occupied with at least min_surface_hits points"""
    trusted_free: NDArray[np.bool_]
    observed: NDArray[np.bool_]
    stamps_ns: tuple[int, int]


def session_changes(store: FrameStore, sessions: dict[int, list[int]], revision: int | None = None,
                    config: ChangeConfig | None = None) -> SessionChanges:
    """Changed regions between every pair of sessions (``{session: [frame ids]}``, e.g. from
    :func:`driftmap.pipeline.merge.store_sessions`) of ``store`` in ``revision`` (default: the head)."""
    t0 = time.perf_counter()
    cfg = config or ChangeConfig()
    if cfg.margin_m is None:
        cfg = dataclasses.replace(cfg, margin_m=DiagnoseConfig.for_store(store).revisits.max_detectable_m)
    rev = store.head if revision is None else int(revision)
    placed = set(store.members(rev).tolist())  # a session appended after the revision is not in it
    sessions = {k: kept for k, ids in sessions.items() if (kept := [f for f in ids if int(f) in placed])}
    if len(sessions) < 2:
        raise ConfigError(f"{store.path}: session changes need at least two sessions in revision {rev}, got "
                          f"{len(sessions)}")
    first = store.frame(int(store.frame_ids[0]))
    voxel = cfg.voxel_size_m
    if voxel is None and first.sensor_kind is not SensorKind.LIDAR:
        voxel = DEPTH_CHANGE_VOXEL_SIZE_M
    vcfg = resolve_config(store, VolumeConfig(voxel_size_m=voxel, keep_frame_voxels=False))
    ids_all, stamps_all = store.frame_ids, store.ledger.stamps_ns
    order = sorted(sessions)
    all_layers = VolumeLayers.on_one_grid(store, rev, vcfg, [sessions[s] for s in order])
    grid = all_layers[0].grid
    built: dict[int, _Session] = {}
    margin = int(math.ceil(cfg.margin_m / grid.voxel_size_m - 1e-9))
    ball = _ball(margin)
    for s, layers in zip(order, all_layers):
        hits = layers.arrays.hits.reshape(grid.shape)
        misses = layers.arrays.misses.reshape(grid.shape)
        state = layers.state_grid()
        surface = (state == 1) & (hits >= cfg.min_surface_hits)
        any_hit = hits > 0
        near = ndimage.binary_dilation(any_hit, structure=ball) if margin > 0 else any_hit
        trusted_free = (state == 0) & (misses >= cfg.min_free_misses) & ~near
        rows = np.searchsorted(ids_all, np.asarray(sessions[s], dtype=np.int64))
        st = stamps_all[rows]
        built[s] = _Session(layers, surface, trusted_free, (hits + misses) > 0, (int(st.min()), int(st.max())))
    evaluated = np.zeros(grid.shape, dtype=bool)
    changed = np.zeros(grid.shape, dtype=bool)
    regions: list[ChangeRegion] = []
    for a_i, a in enumerate(order):
        for b in order[a_i + 1:]:
            A, B = built[a], built[b]
            evaluated |= (A.surface & B.observed) | (B.surface & A.observed)
            for kind, surf, free in (("added", b, a), ("removed", a, b)):
                mask = built[surf].surface & built[free].trusted_free
                changed |= mask
                regions += _regions(mask, kind, surf, free, built, grid, cfg)
    regions.sort(key=lambda r: -r.n_voxels)
    per_session = {s: {"surface": int(built[s].surface.sum()), "trusted_free": int(built[s].trusted_free.sum()),
                       "observed": int(built[s].observed.sum())} for s in order}
    result = SessionChanges(rev, order, regions, int(evaluated.sum()), int(changed.sum()), float(grid.voxel_size_m),
                            vcfg.max_range_m, cfg, per_session, time.perf_counter() - t0)
    logger.info("session changes: %d regions, %d of %d evaluated voxels changed (%.2f %%) at %.3g m in %.1f s",
                len(regions), result.changed_voxels, result.evaluated_voxels, 100 * result.changed_fraction,
                grid.voxel_size_m, result.seconds)
    return result


def _ball(radius: int) -> NDArray[np.bool_]:
    r = max(int(radius), 0)
    g = np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1]
    return (g ** 2).sum(axis=0) <= r * r + 1e-9


def _regions(mask: NDArray[np.bool_], kind: str, surf: int, free: int, built: dict[int, _Session], grid: GridSpec,
             cfg: ChangeConfig) -> list[ChangeRegion]:
    """Connected groups of ``mask`` (linked across ``link_voxels``) with at least ``min_region_voxels`` voxels; a
    Python loop over the regions only (the voxels are grouped by ``ndimage.label``)."""
    if not mask.any():
        return []
    linked = ndimage.binary_dilation(mask, structure=np.ones((3, 3, 3), bool), iterations=cfg.link_voxels) \
        if cfg.link_voxels > 0 else mask
    labels, n = ndimage.label(linked, structure=np.ones((3, 3, 3), bool))
    lab = labels[mask]
    counts = np.bincount(lab, minlength=n + 1)
    flats = np.flatnonzero(mask.ravel())
    centers = grid.centers_m(flats)
    observers = built[surf].layers.observers(centers)
    out = []
    for k in np.flatnonzero(counts >= cfg.min_region_voxels):
        if k == 0:
            continue
        sel = lab == k
        c = centers[sel]
        half = 0.5 * grid.voxel_size_m
        frames = np.unique(np.concatenate([observers[i] for i in np.flatnonzero(sel)] or [np.zeros(0, np.int64)]))
        stamps = _stamp_span(built[surf].layers, frames, built[surf].stamps_ns)
        out.append(ChangeRegion(kind, int(surf), int(free), c.mean(axis=0), c.min(axis=0) - half, c.max(axis=0) + half,
                                int(sel.sum()), frames.astype(np.int64), stamps, built[free].stamps_ns))
    return out


def _stamp_span(layers: VolumeLayers, frames: NDArray[np.int64], default: tuple[int, int]) -> tuple[int, int]:
    """The first and last stamp of ``frames`` (of the layers' map view); ``default`` without any."""
    view = layers.view
    if view is None or len(frames) == 0:
        return default
    ids = np.asarray(view.frame_ids, dtype=np.int64)
    order = np.argsort(ids)
    pos = np.clip(np.searchsorted(ids[order], frames), 0, len(ids) - 1)
    rows = order[pos][ids[order][pos] == frames]
    if len(rows) == 0:
        return default
    stamps = np.asarray(view.stamps_ns, dtype=np.int64)[rows]
    return int(stamps.min()), int(stamps.max())
