"""The volumetric layers of a store's revision -- occupancy evidence (occupied / free / unknown), a TSDF and the
frames behind each occupied voxel -- kept true when a pose correction arrives.

:class:`VolumeLayers` integrates every frame of a revision (:mod:`driftmap.volume.kernels`). When a revision changes
poses, :meth:`VolumeLayers.apply` takes out the old contribution of exactly the frames whose points moved (the map
view's :class:`~driftmap.map.view.ChangeSet`, deskewed neighbours included) and puts in the new one; as every layer
is an integer sum, the result is bit for bit the layers a rebuild of that revision gives (tests/test_volume.py).
The distance field and the mesh are derived from these on demand (:mod:`driftmap.volume.distance`,
:mod:`driftmap.volume.mesh`); the queries a navigation stack asks live in :mod:`driftmap.volume.queries`.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d
import open3d.core as o3c
from numpy.typing import NDArray

from driftmap.errors import ConfigError, EmptyExportError, EmptyStoreError
from driftmap.frame import SensorKind
from driftmap.kernels import volume as kernels
from driftmap.volume.config import VolumeConfig
from driftmap.volume.grid import BLOCK_RESOLUTION, GridSpec, world_points
from driftmap.volume.observation import Observation, observe

if TYPE_CHECKING:
    from driftmap.map.view import MapView
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)

UNKNOWN, FREE, OCCUPIED = np.int8(-1), np.int8(0), np.int8(1)
"""Voxel states as :meth:`VolumeLayers.states` returns them."""
STATE_NAMES = {-1: "unknown", 0: "free", 1: "occupied"}
STATE_CHUNK_VOXELS = 1 << 20
"""Voxels :meth:`VolumeLayers.state_grid` classifies at a time (~40 MB of temporaries)."""

ProgressCallback = Callable[[str, int, int | None], None]


@dataclass
class VolumeChange:
    """What :meth:`VolumeLayers.apply` changed: the frames re-integrated, the region they cover before and after,
    and the voxels whose occupancy state changed (flat grid indices and their world centres)."""

    revision_from: int
    revision_to: int
    frame_ids: NDArray[np.int64]
    boxes_m: NDArray[np.float64]
    """(K, 2, 3) the boxes of the frames' old and new rays (min, max)"""
    changed_flats: NDArray[np.int64]
    changed_centers_m: NDArray[np.float64]
    seconds: float = 0.0
    rebuilt: bool = False
    """True when the update fell back to a rebuild (a frame changed that the update could not take out)"""

    @property
    def n_state_changed(self) -> int:
        return int(len(self.changed_flats))


@dataclass
class VolumeStats:
    """Counts of the voxel states and the memory of the layers."""

    occupied: int
    free: int
    unknown: int
    n_voxels: int
    nbytes: int
    """the dense grid's arrays (:attr:`GridSpec.nbytes`)"""
    cache_nbytes: int = 0
    """what the layers keep per frame besides the grid: its hit voxels (:attr:`VolumeLayers.frame_hits`), its missed
    voxels (:attr:`VolumeLayers.frame_misses`, with ``keep_frame_voxels``) and the hit-point sums; grows with the
    number of frames, not with the grid"""

    @property
    def observed(self) -> int:
        return self.occupied + self.free

    @property
    def total_nbytes(self) -> int:
        return self.nbytes + self.cache_nbytes

    @property
    def bytes_per_observed_voxel(self) -> float:
        """The grid's bytes per observed voxel (:attr:`total_nbytes` for everything the layers hold)."""
        return self.nbytes / max(self.observed, 1)


@dataclass
class VoxelArrays:
    """The per-voxel counts of :class:`VolumeLayers` (flat over the grid): hits, misses, the ray-mark scratch and the
    TSDF sums and counts."""

    hits: NDArray[np.int32]
    misses: NDArray[np.int32]
    mark: NDArray[np.int32]
    tsdf_sum: NDArray[np.int64]
    tsdf_count: NDArray[np.int32]

    @classmethod
    def zeros(cls, n: int) -> VoxelArrays:
        return cls(np.zeros(n, np.int32), np.zeros(n, np.int32), np.zeros(n, np.int32), np.zeros(n, np.int64),
                   np.zeros(n, np.int32))


@dataclass
class VolumeLayers:
    """Occupancy counts and TSDF sums of one revision on a dense grid, with the hit voxels of every frame."""

    config: VolumeConfig
    grid: GridSpec
    sensor_kind: SensorKind
    revision: int
    arrays: VoxelArrays
    frame_hits: dict[int, NDArray[np.int64]] = field(default_factory=dict)
    """per frame, the lattice keys (flat on the world lattice, see :meth:`_lattice_flat`) of its hit voxels"""
    view: MapView | None = None
    frame_misses: dict[int, tuple[GridSpec, NDArray[np.integer]]] = field(default_factory=dict)
    """per frame (``keep_frame_voxels``), the grid voxels its rays passed through, on the grid they were counted on:
    taking the frame out decrements them instead of tracing its rays again"""
    hit_batches: list[tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]] = field(default_factory=list)
    """(lattice keys, fixed-point coordinate sums (M, 3), point counts) of hit points, per integrated or removed frame
    (removed: negated), summed by :meth:`hit_means`"""
    version: int = 0
    """incremented by every frame integrated or taken out (derived layers are cached per version)"""
    store_uuid: str | None = None
    """the id of the store whose frames they integrate (:attr:`FrameStore.uuid`): ``decide`` refuses another
    store's layers (hostile trial 25 B4)"""
    cache: dict = field(default_factory=dict)
    _token: int = 0
    _observers: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None
    _kept_bytes: int = 0
    """bytes of :attr:`frame_misses` (bounded with the grid by ``memory_budget_mb``)"""
    _budget_logged: bool = False

    # --------------------------------------------------------------------------------------------- building
    @classmethod
    def from_store(cls, store: FrameStore, revision: int | None = None, config: VolumeConfig | None = None, *,
                   progress: ProgressCallback | None = None) -> VolumeLayers:
        """Integrate every frame of ``revision`` (default: the head) of ``store``: the rays of each frame from its
        sensor origin at that revision's pose (the map view's points: deskewed where frames carry point times)."""
        from driftmap.map.view import MapView
        from driftmap.volume.defaults import resolve_config

        rev = store.head if revision is None else revision
        if len(store) == 0:
            raise EmptyStoreError(f"store {store.path} has no frames in revision {rev}: no volumetric layers",
                                  store=store.path, revision=rev)
        store.ledger.revision(rev)  # a revision that does not exist: a StoreError naming it, before any work
        cfg = resolve_config(store, config or VolumeConfig())
        view = MapView.from_store(store, rev)
        return cls.from_view(view, store, cfg, progress=progress)

    @classmethod
    def on_one_grid(cls, store: FrameStore, revision: int, config: VolumeConfig,
                    frame_sets: Sequence[Sequence[int]]) -> list[VolumeLayers]:
        """Layers of each set of frames of ``revision`` (e.g. the sessions of a merged store; ``config`` resolved) on
        one grid sized for all of them, so that they compare voxel for voxel. Raises ConfigError when a set's rays
        leave that grid (deskewed points beyond the frames' boxes)."""
        from driftmap.map.view import MapView

        view = MapView.from_store(store, revision)
        grid = covering_grid(view, config)
        out = []
        for k, ids in enumerate(frame_sets):
            layers = cls.from_view(view, store, config, frame_ids=ids, grid=grid)
            if layers.grid != grid:
                raise ConfigError(f"{store.path}: the rays of frame set {k} left the grid sized for all the frames "
                                  f"(deskewed points beyond the frames' boxes): the sets' layers would not compare")
            out.append(layers)
        return out

    @classmethod
    def from_view(cls, view: MapView, store: FrameStore, config: VolumeConfig, *,
                  progress: ProgressCallback | None = None, frame_ids: Iterable[int] | None = None,
                  grid: GridSpec | None = None) -> VolumeLayers:
        """Layers of the frames of a map view (``config`` resolved), streamed: the grid is sized from the view's
        frame boxes (cut to the max range around each sensor), then each frame is observed and integrated in turn.

        ``frame_ids``: only these frames of the view (e.g. one session of a merged store); ``grid``: this grid
        instead of one sized from the frames (layers of several frame sets on one grid compare voxel for voxel;
        it grows where a frame's rays leave it)."""
        tick = progress or (lambda stage, done, total: None)
        ids = [int(f) for f in (view.frame_ids if frame_ids is None else frame_ids)]
        if not ids:
            raise EmptyStoreError(f"store {store.path}: no frames selected for volumetric layers",
                                  store=store.path, revision=view.revision)
        first = store.frame(ids[0])
        if grid is None:
            grid = covering_grid(view, config, ids)
        layers = cls(config, grid, first.sensor_kind, view.revision, VoxelArrays.zeros(grid.n_voxels), view=view,
                     store_uuid=store.uuid)
        return layers._integrate_all(store, ids, tick)

    def _integrate_all(self, store: FrameStore, ids: list[int], tick: ProgressCallback) -> VolumeLayers:
        logger.info("volume: %s for revision %d (%d frames)", self.grid.describe(), self.revision, len(ids))
        for n, fid in enumerate(ids):
            obs = self._observe(store, fid)
            self._grow_to(*obs.bounds_m)  # a no-op unless deskewing moved points beyond the frame's box
            self._integrate(obs, +1)
            tick("volume", n + 1, len(ids))
        return self

    # ------------------------------------------------------------------------------------------ integration
    def _next_token(self) -> int:
        self._token += 1
        if 2 * self._token + 1 >= 2**31 - 1:
            self.arrays.mark[:] = 0
            self._token = 1
        return self._token

    def _integrate(self, obs: Observation, sign: int) -> None:
        """Add (``sign`` 1) or take out (-1) one observation; the grid must hold it. Taking out a frame whose voxels
        were kept (:attr:`frame_misses`) decrements them instead of tracing its rays again."""
        a, g, c = self.arrays, self.grid, self.config
        origin_index = np.asarray(g.origin_index, dtype=np.int64)
        shape = np.asarray(g.shape, dtype=np.int64)
        ends = g.lattice_units(obs.ends_m)
        if sign < 0 and obs.frame_id in self.frame_misses and obs.frame_id in self.frame_hits:
            hit_flats, inside = self.grid_flat_of_keys(self.frame_hits.pop(obs.frame_id))
            a.hits[hit_flats[inside]] -= 1  # a frame's voxels are distinct: one decrement each
            a.misses[self._cached_misses(obs.frame_id)] -= 1
        else:
            hit_flats = np.empty(len(ends), dtype=np.int64)
            miss_flats = np.empty(MISS_CAPACITY_PER_RAY * len(ends) if sign > 0 and c.keep_frame_voxels else 0, np.int64)
            token = self._next_token()
            n_hit, n_miss = kernels.occupancy_update(g.lattice_units(obs.origin_m), ends, obs.is_hit, origin_index,
                                                     shape, a.hits, a.misses, a.mark, token, sign, hit_flats, miss_flats)
            if sign > 0:
                self.frame_hits[obs.frame_id] = self._lattice_flat(hit_flats[:n_hit])
                if c.keep_frame_voxels:
                    misses = (miss_flats[:n_miss] if n_miss <= len(miss_flats)
                              else np.flatnonzero(a.mark == 2 * token + 1))  # the buffer overflowed: this frame's marks
                    self._keep_misses(obs.frame_id, misses.astype(np.int32 if g.n_voxels < 2**31 else np.int64))
            else:
                self.frame_hits.pop(obs.frame_id, None)
        if sign < 0:
            dropped = self.frame_misses.pop(obs.frame_id, None)
            if dropped is not None:
                self._kept_bytes -= dropped[1].nbytes
        self.hit_batches.append(_hit_sums(ends[obs.is_hit], sign))
        self._observers = None
        self.version += 1
        if obs.depth_m is not None and obs.intrinsics is not None:
            fx, fy, cx, cy = obs.intrinsics
            blocks = tsdf_blocks(obs, g.voxel_size_m, float(c.truncation_m), c.max_range_m)
            kernels.tsdf_projective(obs.depth_m, fx, fy, cx, cy, np.linalg.inv(obs.T_world_sensor), blocks,
                                    BLOCK_RESOLUTION, origin_index, shape, g.voxel_size_m, float(c.truncation_m),
                                    float(c.max_range_m if c.max_range_m is not None else np.inf), a.tsdf_sum,
                                    a.tsdf_count, sign)
        else:
            hits = ends[obs.is_hit]
            kernels.tsdf_rays(g.lattice_units(obs.origin_m), hits, origin_index, shape,
                              float(c.truncation_m) / g.voxel_size_m, a.tsdf_sum, a.tsdf_count, sign)

    def _keep_misses(self, frame_id: int, flats: NDArray[np.integer]) -> None:
        """Keep a frame's missed voxels (:attr:`frame_misses`) while the grid and the kept voxels stay within
        ``memory_budget_mb``; beyond it the frame is kept out and taking it out traces its rays again (the same
        voxels: exact either way). The budget bounds what grows with the frames, not only the grid."""
        if self.grid.nbytes + self._kept_bytes + flats.nbytes > self.config.memory_budget_mb * 2**20:
            if not self._budget_logged:
                logger.info("volume: the frames' missed voxels reach volume.memory_budget_mb = %g MiB beside the "
                            "grid (%s): frames from %d on are not kept (a correction traces their rays again)",
                            self.config.memory_budget_mb, self.grid.describe(), frame_id)
                self._budget_logged = True
            return
        self.frame_misses[frame_id] = (self.grid, flats)
        self._kept_bytes += flats.nbytes

    def _cached_misses(self, frame_id: int) -> NDArray[np.int64]:
        """A frame's kept miss voxels as flat indices of the current grid (moved over if the grid grew since)."""
        grid, flats = self.frame_misses[frame_id]
        if grid == self.grid:
            return flats
        lattice = grid.unflat(flats.astype(np.int64)) + np.asarray(grid.origin_index)
        return self.grid.flat(lattice - np.asarray(self.grid.origin_index))

    def _lattice_flat(self, grid_flats: NDArray[np.int64]) -> NDArray[np.int64]:
        """Grid flat indices -> lattice keys that survive the grid growing (a 21-bit signed packing per axis)."""
        idx = self.grid.unflat(grid_flats) + np.asarray(self.grid.origin_index)
        return _pack(idx)

    def grid_flat_of_keys(self, keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """The flat grid index of each lattice key (:meth:`_lattice_flat`) and whether it lies inside the grid."""
        idx = _unpack(keys) - np.asarray(self.grid.origin_index)
        inside = np.all((idx >= 0) & (idx < np.asarray(self.grid.shape)), axis=1)
        return self.grid.flat(np.where(inside[:, None], idx, 0)), inside

    def _grow_to(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> None:
        """Reallocate the grid to also hold ``lo .. hi`` (counts copied to their lattice voxels)."""
        pad = self.config.padding_m + float(self.config.truncation_m or 0.0)
        g = self.grid
        need = g.lattice_index(np.stack([np.asarray(lo) - pad, np.asarray(hi) + pad]))
        first = np.asarray(g.origin_index, dtype=np.int64)
        if np.all(need[0] >= first) and np.all(need[1] < first + np.asarray(g.shape, dtype=np.int64)):
            return  # held already, by lattice index: GridSpec.union's min_m / voxel can floor one voxel low
        new = self.grid.union(lo - pad, hi + pad, budget_mb=self.config.memory_budget_mb)
        if new == self.grid:
            return
        old, arrays = self.grid, VoxelArrays.zeros(new.n_voxels)
        off = [a - b for a, b in zip(old.origin_index, new.origin_index)]
        sl = tuple(slice(o, o + n) for o, n in zip(off, old.shape))
        for name in ("hits", "misses", "tsdf_sum", "tsdf_count"):
            getattr(arrays, name).reshape(new.shape)[sl] = getattr(self.arrays, name).reshape(old.shape)
        logger.info("volume: grid grown from %s to %s", old.describe(), new.describe())
        self.grid, self.arrays, self._token = new, arrays, 0

    # ------------------------------------------------------------------------------------------- corrections
    def _check_store(self, store: FrameStore, what: str) -> None:
        """``store`` is the one the layers were built from (hostile trial 29 B1: another build of the same log was
        taken, and the layers then answered for the other map; another log's store ended in a raw numpy error)."""
        if self.store_uuid is not None and self.store_uuid != store.uuid:
            raise ConfigError(f"VolumeLayers.{what}: the layers are of another store (id {self.store_uuid}), not of "
                              f"{store.path} (id {store.uuid}): give the store they were built from")
        if self.store_uuid is None and self.view is not None:
            foreign = sorted(set(int(f) for f in self.view.frame_ids) - {int(f) for f in store.frame_ids})
            if foreign:
                raise ConfigError(f"VolumeLayers.{what}: the layers integrate frames {store.path} does not hold "
                                  f"({foreign[:5]}{' ...' if len(foreign) > 5 else ''}): another store's layers")

    def apply(self, revision: int, store: FrameStore | None = None) -> VolumeChange:
        """Update the layers to ``revision`` of the store they were built from: the old contribution of every frame
        whose points move is taken out and the new one put in (a rollback is a revision like any other). Returns the
        :class:`VolumeChange`; the layers then equal a rebuild of ``revision`` bit for bit."""
        if self.view is None or store is None:
            raise ConfigError("VolumeLayers.apply needs the layers' map view and store (build them with from_store)")
        if self.cache.get("latest_state"):
            raise ConfigError("latest-state layers (driftmap.volume.sessions) are read-only: build them again for "
                              "another revision")
        self._check_store(store, "apply")
        t0 = time.perf_counter()
        store.ledger.revision(revision)
        old_rev = self.revision
        self_ids = np.sort(self.view.frame_ids)
        if not np.array_equal(self_ids, store.members(revision)):
            # the revisions place different frames (one made before frames were appended, a rollback to it): the
            # layers of revision ``revision`` are those of its frames only, built again
            logger.info("volume: revision %d places other frames than revision %d; rebuilding the layers",
                        revision, old_rev)
            rebuilt = VolumeLayers.from_store(store, revision, self.config)
            self.__dict__.update(rebuilt.__dict__)
            return VolumeChange(old_rev, revision, np.setxor1d(self_ids, store.members(revision)), np.zeros((0, 2, 3)),
                                np.zeros(0, np.int64), np.zeros((0, 3)), time.perf_counter() - t0, rebuilt=True)
        before = {int(f): self.view.pose(int(f)) for f in self.view.frame_ids}
        after = store.poses(revision)
        moved = [int(f) for f, T in zip(store.frame_ids, after) if int(f) in before and not np.array_equal(before[int(f)], T)]
        # a deskewed scan moves with its neighbours' poses (LiDAR with point times); a depth frame only with its own
        candidates = (_with_neighbours(moved, [int(f) for f in self.view.frame_ids])
                      if self.sensor_kind is SensorKind.LIDAR else set(moved))
        old_obs = {fid: self._observe(store, fid) for fid in candidates}
        changes = self.view.apply(revision)
        changed = [int(f) for f in changes.frame_ids]
        kept = sorted(set(moved) - set(changed))
        if kept:
            # a pose change the map view did not apply (a view whose POSE_EPSILON is not 0), while a rebuild places
            # the frame at the exact pose (a loop closure moved an origin at 0 to 4e-20): take a view of the
            # revision as a rebuild does, and re-integrate every candidate (an unchanged frame's -1 / +1 cancel)
            from driftmap.map.view import MapView

            logger.info("volume: frames %s moved without the map view applying it; re-reading the view of "
                        "revision %d", kept[:5], revision)
            self.view = MapView.from_store(store, revision)
            changed += [f for f in sorted(candidates) if f not in changed]
        missing = [f for f in changed if f not in old_obs]
        if missing:
            logger.warning("volume: frames %s changed beyond the moved frames and their neighbours; rebuilding the "
                           "layers of revision %d", missing[:5], revision)
            rebuilt = VolumeLayers.from_view(self.view, store, self.config)
            self.__dict__.update(rebuilt.__dict__)
            return VolumeChange(old_rev, revision, np.asarray(changed, np.int64), np.zeros((0, 2, 3)),
                                np.zeros(0, np.int64), np.zeros((0, 3)), time.perf_counter() - t0, rebuilt=True)
        new_obs = {fid: self._observe(store, fid) for fid in changed}
        boxes = np.array([[*old_obs[f].bounds_m] for f in changed] + [[*new_obs[f].bounds_m] for f in changed]).reshape(-1, 2, 3)
        if len(changed):
            self._grow_to(boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0))
        region = _region(self.grid, boxes, float(self.config.truncation_m or 0.0))
        states_before = self.states_flat(region)
        for fid in changed:
            self._integrate(old_obs[fid], -1)
        for fid in changed:
            self._integrate(new_obs[fid], +1)
        self.revision = revision
        states_after = self.states_flat(region)
        flips = region[states_before != states_after]
        return VolumeChange(old_rev, revision, np.asarray(changed, np.int64), boxes, flips, self.grid.centers_m(flips),
                            time.perf_counter() - t0)

    def refresh(self, store: FrameStore) -> VolumeChange:
        """Integrate the frames stored since the layers last looked (a live robot appending frames), placed in the
        layers' revision: the map view takes them in (:meth:`MapView.refresh`), the grid grows to their rays, and a
        frame whose deskewed points moved with its new neighbour is taken out and put back. The result equals a
        rebuild bit for bit; returns the :class:`VolumeChange` (the new frames, their boxes, the flipped voxels)."""
        if self.view is None:
            raise ConfigError("VolumeLayers.refresh needs the layers' map view (build them with from_store)")
        self._check_store(store, "refresh")  # (hostile trial 30 W2: another store did nothing without a word)
        t0 = time.perf_counter()
        view, rev = self.view, self.revision
        last = int(view.frame_ids[-1]) if len(view.frame_ids) else None
        last_points = view.frame_points_world(last).copy() if last is not None else None
        new_ids = [int(f) for f in view.refresh()]
        if not new_ids:
            return VolumeChange(rev, rev, np.zeros(0, np.int64), np.zeros((0, 2, 3)), np.zeros(0, np.int64),
                                np.zeros((0, 3)), time.perf_counter() - t0)
        redo = [last] if last is not None and not np.array_equal(view.frame_points_world(last), last_points) else []
        old = [observe(store.frame(f), view.pose(f), last_points, self.config) for f in redo]
        new = [self._observe(store, f) for f in redo + new_ids]
        boxes = np.array([o.bounds_m for o in old + new], dtype=np.float64)
        self._grow_to(boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0))
        region = _region(self.grid, boxes, float(self.config.truncation_m or 0.0))
        before = self.states_flat(region)
        for obs in old:
            self._integrate(obs, -1)
        for obs in new:
            self._integrate(obs, +1)
        flips = region[before != self.states_flat(region)]
        return VolumeChange(rev, rev, np.asarray(redo + new_ids, np.int64), boxes, flips, self.grid.centers_m(flips),
                            time.perf_counter() - t0)

    def _observe(self, store: FrameStore, frame_id: int) -> Observation:
        assert self.view is not None
        return observe(store.frame(frame_id), self.view.pose(frame_id), self.view.frame_points_world(frame_id), self.config)

    # ------------------------------------------------------------------------------------------------ reading
    def log_odds_flat(self, flats: NDArray[np.int64]) -> NDArray[np.float64]:
        """The clamped log-odds of grid voxels (0 where unobserved)."""
        c = self.config
        L = self.arrays.hits[flats] * c.log_odds_hit + self.arrays.misses[flats] * c.log_odds_miss
        return np.clip(L, c.log_odds_min, c.log_odds_max)

    def states_flat(self, flats: NDArray[np.int64]) -> NDArray[np.int8]:
        """:data:`OCCUPIED` / :data:`FREE` / :data:`UNKNOWN` of grid voxels (flat indices)."""
        return self._states(self._flat_indices(flats, "states_flat"))

    def _states(self, flats: NDArray[np.int64]) -> NDArray[np.int8]:
        seen = (self.arrays.hits[flats] + self.arrays.misses[flats]) > 0
        occ = self.log_odds_flat(flats) >= self.config.log_odds_threshold
        out = np.full(len(flats), UNKNOWN, dtype=np.int8)
        out[seen] = FREE
        out[seen & occ] = OCCUPIED
        return out

    def _flat_indices(self, flats: NDArray[np.integer], what: str) -> NDArray[np.int64]:
        """Flat voxel indices, each within ``0 .. n_voxels - 1`` (numpy would read -1 as the last voxel; hostile trial
        27 W4); a :class:`ConfigError` naming ``what`` and the range otherwise."""
        flats = np.asarray(flats)
        if flats.size and (not np.issubdtype(flats.dtype, np.integer) or flats.min() < 0
                           or flats.max() >= self.grid.n_voxels):
            raise ConfigError(f"{what}: flat voxel indices must be integers in 0 .. {self.grid.n_voxels - 1}, got "
                              f"{flats.dtype} values in {flats.min()} .. {flats.max()}")
        return flats.astype(np.int64, copy=False)

    def states(self, points_m: NDArray[np.floating]) -> NDArray[np.int8]:
        """The state of the voxel holding each world point (outside the grid: unknown)."""
        idx, inside = self.grid.grid_index(world_points(points_m, "states"))
        out = np.full(len(idx), UNKNOWN, dtype=np.int8)
        out[inside] = self._states(self.grid.flat(idx[inside]))
        return out

    def state_grid(self) -> NDArray[np.int8]:
        """Every voxel's state, shaped as the grid (x, y, z), :data:`STATE_CHUNK_VOXELS` at a time (at once, ~40 bytes
        a voxel beside the grid's 24: an OctoMap export peaked at 2.4x the checked grid; hostile trial 24 W4)."""
        n = self.grid.n_voxels
        out = np.empty(n, dtype=np.int8)
        for start in range(0, n, STATE_CHUNK_VOXELS):
            out[start:start + STATE_CHUNK_VOXELS] = self._states(
                np.arange(start, min(n, start + STATE_CHUNK_VOXELS), dtype=np.int64))
        return out.reshape(self.grid.shape)

    def tsdf_flat(self, flats: NDArray[np.int64]) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """The TSDF (normalised, -1..1; NaN where unobserved) and its observation count at grid voxels."""
        flats = self._flat_indices(flats, "tsdf_flat")
        count = self.arrays.tsdf_count[flats]
        with np.errstate(invalid="ignore", divide="ignore"):
            tsdf = (self.arrays.tsdf_sum[flats] / kernels.TSDF_QUANTUM / count).astype(np.float32)
        return np.where(count > 0, tsdf, np.float32(np.nan)), count

    def stats(self) -> VolumeStats:
        s = self.state_grid().ravel()
        counts = np.bincount(s.astype(np.int64) + 1, minlength=3)
        return VolumeStats(int(counts[2]), int(counts[1]), int(counts[0]), self.grid.n_voxels, self.grid.nbytes,
                           self.cache_nbytes())

    def cache_nbytes(self) -> int:
        """Bytes of the per-frame records (hit keys, kept miss voxels, hit-point sums): see :class:`VolumeStats`."""
        hits = sum(k.nbytes for k in self.frame_hits.values())
        misses = sum(m.nbytes for _, m in self.frame_misses.values())
        sums = sum(k.nbytes + x.nbytes + n.nbytes for k, x, n in self.hit_batches)
        return int(hits + misses + sums)

    def observers(self, points_m: NDArray[np.floating]) -> list[NDArray[np.int64]]:
        """For each world point, the frames whose rays ended in its voxel (the frames behind an occupied voxel)."""
        if self._observers is None:
            fids = np.concatenate([np.full(len(k), f, np.int64) for f, k in self.frame_hits.items()] or [np.zeros(0, np.int64)])
            keys = np.concatenate(list(self.frame_hits.values()) or [np.zeros(0, np.int64)])
            order = np.lexsort((fids, keys))
            self._observers = (keys[order], fids[order])
        keys, fids = self._observers
        q = _pack(self.grid.lattice_index(world_points(points_m, "observers")))
        lo, hi = np.searchsorted(keys, q, "left"), np.searchsorted(keys, q, "right")
        return [fids[a:b] for a, b in zip(lo, hi)]

    def hit_means(self) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]:
        """Per voxel that a point ended in: its lattice key, the mean of those points (metres) and how many there
        were (integer sums over the frames, so equal after corrections to a rebuild)."""
        cached = self.cache.get("hit_means")
        if cached is not None and cached[0] == self.version:
            return cached[1]
        keys = np.concatenate([b[0] for b in self.hit_batches] or [np.zeros(0, np.int64)])
        sums = np.concatenate([b[1] for b in self.hit_batches] or [np.zeros((0, 3), np.int64)])
        counts = np.concatenate([b[2] for b in self.hit_batches] or [np.zeros(0, np.int64)])
        uniq, inv = np.unique(keys, return_inverse=True)
        total = np.zeros((len(uniq), 3), np.int64)
        np.add.at(total, inv, sums)
        n = np.bincount(inv, weights=counts, minlength=len(uniq)).astype(np.int64)
        keep = n > 0
        uniq, total, n = uniq[keep], total[keep], n[keep]
        self.hit_batches = [(uniq, total, n)]  # consolidated
        means = total / HIT_FIXED_POINT / n[:, None] * self.grid.voxel_size_m
        self.cache["hit_means"] = (self.version, (uniq, means, n))
        return uniq, means, n

    # --------------------------------------------------------------------------------- derived layers, queries
    def mesh(self, weight_threshold: float | None = None):  # noqa: ANN201 - an open3d.geometry.TriangleMesh
        """The TSDF's triangle mesh (:func:`driftmap.volume.mesh.triangle_mesh`)."""
        from driftmap.volume.mesh import DEFAULT_WEIGHT_THRESHOLD, triangle_mesh

        if weight_threshold is not None and not (isinstance(weight_threshold, (int, float, np.number))
                                                 and np.isfinite(weight_threshold) and weight_threshold >= 0):
            raise ConfigError(f"mesh: weight_threshold must be a finite number >= 0 (observations a voxel needs), got "
                              f"{weight_threshold!r}")  # NaN gave an empty mesh without a word (trial 27 W4)
        return triangle_mesh(self, DEFAULT_WEIGHT_THRESHOLD if weight_threshold is None else weight_threshold)

    def clearance_m(self, points_m: NDArray[np.floating], unknown_is: str | None = None,
                    max_m: float | None = None) -> NDArray[np.float64]:
        """Distance to the nearest obstacle at each point (:func:`driftmap.volume.queries.clearance_m`)."""
        from driftmap.volume.queries import clearance_m

        return clearance_m(self, points_m, unknown_is, max_m=max_m)

    def sweep(self, path_m: NDArray[np.floating], **footprint: object):  # noqa: ANN201 - a SweepResult
        """The first contact or unknown voxel of a footprint along a path (:func:`driftmap.volume.queries.sweep`)."""
        from driftmap.volume.queries import sweep

        return sweep(self, path_m, **footprint)  # type: ignore[arg-type]

    def equals(self, other: VolumeLayers) -> bool:
        """Bit-for-bit equal layers over the union of both grids (voxels outside a grid count as unobserved)."""
        if not isinstance(other, VolumeLayers):
            raise ConfigError(f"equals: compares VolumeLayers with VolumeLayers, got {type(other).__name__}")
        lo = np.minimum(self.grid.min_m, other.grid.min_m)
        hi = np.maximum(self.grid.max_m, other.grid.max_m) - 0.5 * self.grid.voxel_size_m
        common = GridSpec.covering(lo, hi, self.grid.voxel_size_m)
        return all(np.array_equal(_on(self, common, n), _on(other, common, n))
                   for n in ("hits", "misses", "tsdf_sum", "tsdf_count"))


# ---------------------------------------------------------------------------------------------------- helpers
def covering_grid(view: MapView, config: VolumeConfig, frame_ids: Iterable[int] | None = None) -> GridSpec:
    """The grid :meth:`VolumeLayers.from_view` sizes for these frames of ``view`` (default: all; ``config``
    resolved): their boxes cut to the max range around each sensor, plus the padding and the truncation."""
    ids = [int(f) for f in (view.frame_ids if frame_ids is None else frame_ids)]
    if ids and view.n_points == 0:  # not "a voxel larger than the map" (hostile trial 25 W6)
        raise EmptyExportError(f"the map of revision {view.revision} has no point ({len(ids)} frames, none with a "
                               f"point): no volumetric layers to build")
    lo, hi = _view_bounds(view, ids, config.max_range_m)
    extent = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
    if float(config.voxel_size_m) > float(np.max(extent)):
        raise ConfigError(f"volume.voxel_size_m = {float(config.voxel_size_m):g} m is larger than the map itself "
                          f"({extent[0]:.1f} x {extent[1]:.1f} x {extent[2]:.1f} m): the layers would hold it in "
                          f"one voxel; use a voxel of at most {float(np.max(extent)):.2g} m (the default: leave "
                          f"voxel_size_m unset)")
    pad = config.padding_m + float(config.truncation_m or 0.0)
    return GridSpec.covering(lo, hi, float(config.voxel_size_m), padding_m=pad, budget_mb=config.memory_budget_mb)


def _observations(view: MapView, store: FrameStore, ids: Iterable[int], config: VolumeConfig) -> list[Observation]:
    return [observe(store.frame(f), view.pose(f), view.frame_points_world(f), config) for f in ids]


def _view_bounds(view: MapView, ids: list[int], max_range_m: float | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The box of every frame's points and sensor origin, each frame's cut to its max range around the origin."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for fid in ids:
        origin = view.pose(fid)[:3, 3]
        box = np.asarray(view.frame_box_m(fid), dtype=np.float64).reshape(2, 3)
        if max_range_m is not None:
            box = np.clip(box, origin - max_range_m, origin + max_range_m)
        lo = np.minimum(lo, np.minimum(box[0], origin))
        hi = np.maximum(hi, np.maximum(box[1], origin))
    return lo, hi


def tsdf_blocks(obs: Observation, voxel_size_m: float, truncation_m: float, max_range_m: float | None) -> NDArray[np.int32]:
    """The lattice blocks a depth image's TSDF touches: Open3D's ``compute_unique_block_coordinates`` of the image
    (every block within ``truncation_m`` of a measured depth along its ray), so that the samples updated are
    Open3D's."""
    assert obs.depth_m is not None and obs.intrinsics is not None
    fx, fy, cx, cy = obs.intrinsics
    K = o3c.Tensor(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))
    E = o3c.Tensor(np.linalg.inv(obs.T_world_sensor))
    depth = obs.depth_m
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():  # a frame with no depth left (all dropped out, all beyond range): no block to touch
        return np.zeros((0, 3), dtype=np.int32)
    depth_max = float(max_range_m) if max_range_m is not None else float(np.max(depth[valid])) + 1.0
    try:
        blocks = _block_finder(voxel_size_m).compute_unique_block_coordinates(
            o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth))), K, E, 1.0, depth_max,
            truncation_m / voxel_size_m)
    except RuntimeError as exc:  # Open3D aborts when no depth lies within depth_max
        if "No block is touched" not in str(exc):
            raise
        return np.zeros((0, 3), dtype=np.int32)
    return blocks.numpy()  # int32 (N, 3), as Open3D gives them


@functools.lru_cache(maxsize=8)
def _block_finder(voxel_size_m: float) -> o3d.t.geometry.VoxelBlockGrid:
    """An empty Open3D grid of this voxel size, used only for its block selection."""
    return o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
                                         attr_channels=((1), (1)), voxel_size=voxel_size_m,
                                         block_resolution=BLOCK_RESOLUTION, block_count=1, device=o3c.Device("CPU:0"))


def _with_neighbours(moved: list[int], order: list[int]) -> set[int]:
    """The moved frames and their neighbours in frame order (a deskewed frame moves with its neighbour's pose)."""
    pos = {f: k for k, f in enumerate(order)}
    out = set(moved)
    for f in moved:
        k = pos.get(f)
        if k is not None:
            out.update(order[max(0, k - 1):k + 2])
    return out


def _region(grid: GridSpec, boxes: NDArray[np.float64], margin_m: float) -> NDArray[np.int64]:
    """Flat indices of the grid voxels inside any of ``boxes`` (grown by ``margin_m``)."""
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    mask = np.zeros(grid.shape, dtype=bool)
    for lo, hi in boxes:
        a, _ = grid.grid_index((lo - margin_m)[None])
        b, _ = grid.grid_index((hi + margin_m)[None])
        a, b = np.clip(a[0], 0, np.asarray(grid.shape) - 1), np.clip(b[0], 0, np.asarray(grid.shape) - 1)
        mask[a[0]:b[0] + 1, a[1]:b[1] + 1, a[2]:b[2] + 1] = True
    return np.flatnonzero(mask.ravel())


MISS_CAPACITY_PER_RAY = 8
"""Room for this many missed voxels per ray when a frame's misses are kept (its rays cross more: found by ``mark``)."""
HIT_FIXED_POINT = float(2**16)
"""Hit coordinates are summed in lattice units times this, as int64 (exact, order-free sums)."""


def _hit_sums(ends_lattice: NDArray[np.float64], sign: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Per lattice voxel of the hit points (lattice units): key, fixed-point coordinate sum, count (times ``sign``)."""
    if len(ends_lattice) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    keys = _pack(np.floor(ends_lattice).astype(np.int64))
    fixed = np.rint(ends_lattice * HIT_FIXED_POINT).astype(np.int64)
    uniq, inv = np.unique(keys, return_inverse=True)
    sums = np.zeros((len(uniq), 3), np.int64)
    np.add.at(sums, inv, fixed)
    return uniq, sign * sums, sign * np.bincount(inv, minlength=len(uniq)).astype(np.int64)


_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def _pack(idx: NDArray[np.int64]) -> NDArray[np.int64]:
    """(N, 3) lattice voxels -> one int64 each (21 bits per axis, +-2^20 voxels)."""
    u = np.asarray(idx, dtype=np.int64) + _KEY_OFFSET
    if len(u) and (u.min() < 0 or u.max() >= (1 << _KEY_BITS)):
        raise ConfigError("volume: lattice index beyond +-2^20 voxels (voxel_size_m too small for the map extent)")
    return (u[:, 0] << (2 * _KEY_BITS)) | (u[:, 1] << _KEY_BITS) | u[:, 2]


def _unpack(keys: NDArray[np.int64]) -> NDArray[np.int64]:
    mask = (1 << _KEY_BITS) - 1
    k = np.asarray(keys, dtype=np.int64)
    return np.stack([(k >> (2 * _KEY_BITS)) & mask, (k >> _KEY_BITS) & mask, k & mask], axis=-1) - _KEY_OFFSET


def _on(layers: VolumeLayers, grid: GridSpec, name: str) -> NDArray:
    """One array of ``layers`` placed on ``grid`` (zeros outside its own grid)."""
    src = getattr(layers.arrays, name).reshape(layers.grid.shape)
    out = np.zeros(grid.shape, dtype=src.dtype)
    off = [a - b for a, b in zip(layers.grid.origin_index, grid.origin_index)]
    out[tuple(slice(o, o + n) for o, n in zip(off, layers.grid.shape))] = src
    return out
