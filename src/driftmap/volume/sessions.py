"""Volumetric layers of a store of several sessions (a merged store, issue 26): per session, or the **latest state**
where the world changed -- voxel by voxel, the newest session that observed a voxel decides whether it is occupied
or free, so that a planner sees the door closed and the chair in its new place, not both (docs/volume.md).

Each session's layers are :meth:`VolumeLayers.on_one_grid` (OctoMap's rays of its own frames, one grid for all, so
they compare voxel for voxel). The latest-state layers take, for every voxel, the counts of the newest session with
at least ``min_observations`` (default 1) rays ending in or passing through it (hits + misses): its hits, misses,
TSDF sums and hit points; a voxel no session observed that often takes the newest session that observed it at all;
one nobody observed stays unknown. Sessions are ordered by their first stamp (ties: the merge's session order). A
voxel's state is then read exactly as in any layers (its clamped log-odds), so the clearance, swept checks, the mesh
and the exports work on them unchanged. They are read-only: a pose correction is applied by building them again
(:meth:`VolumeLayers.apply` refuses them).

Everything is vectorised over the grid; the only Python loops are over sessions and frames.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import ConfigError
from driftmap.volume.config import VolumeConfig
from driftmap.volume.layers import VolumeLayers, VoxelArrays

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)

READ_ONLY = "latest_state"
"""The key in :attr:`VolumeLayers.cache` that marks layers merged from sessions (:meth:`VolumeLayers.apply` refuses)."""


@dataclass
class LatestState:
    """The latest-state layers of a store's sessions and what decided each voxel."""

    layers: VolumeLayers
    """the merged layers (read-only): every query of :class:`VolumeLayers` works on them"""
    deciding_session: NDArray[np.int16]
    """(X, Y, Z) the session whose counts each voxel took; -1 where no session observed it"""
    order: list[int]
    """the sessions, oldest first (the last one's observations win)"""
    session_layers: dict[int, VolumeLayers] = field(default_factory=dict)
    """each session's own layers on the same grid"""
    seconds: float = 0.0

    def voxels_per_session(self) -> dict[int, int]:
        """How many voxels each session decided."""
        counts = np.bincount(self.deciding_session.ravel().astype(np.int64) + 1, minlength=max(self.order) + 2)
        return {s: int(counts[s + 1]) for s in self.order}

    def to_json(self) -> dict:
        return {"order": [int(s) for s in self.order],
                "voxels_per_session": {str(k): v for k, v in self.voxels_per_session().items()},
                "voxel_size_m": float(self.layers.grid.voxel_size_m), "seconds": round(self.seconds, 3)}


def session_order(store: FrameStore, sessions: dict[int, Sequence[int]]) -> list[int]:
    """The sessions oldest first: by the first stamp of their frames, ties by session number."""
    ids, stamps = store.frame_ids, store.ledger.stamps_ns
    first = {}
    for s, frames in sessions.items():
        rows = np.searchsorted(ids, np.asarray(frames, dtype=np.int64))
        if len(rows) == 0 or np.any(rows >= len(ids)) or np.any(ids[np.minimum(rows, len(ids) - 1)] != frames):
            raise ConfigError(f"{store.path}: session {s} names frames the store does not hold")
        first[s] = int(stamps[rows].min())
    return sorted(sessions, key=lambda s: (first[s], s))


def latest_state_layers(store: FrameStore, sessions: dict[int, Sequence[int]], revision: int | None = None,
                        config: VolumeConfig | None = None, *, min_observations: int = 1,
                        order: Sequence[int] | None = None) -> LatestState:
    """The latest-state layers of ``revision`` (default: the head) of ``store`` whose ``sessions`` are
    ``{session: [frame ids]}`` (e.g. :func:`driftmap.pipeline.merge.store_sessions`); see the module docstring.

    ``config``: the volumetric settings (unset ones take the store's sensor defaults,
    :func:`driftmap.volume.defaults.resolve_config`); ``min_observations``: the rays a session needs through a voxel
    to decide it over older sessions (1: the newest observation wins; measured on the synthetic room, 2 or 3 leave
    2-3 % of the closed door's voxels, seen by one ray of the newer session, free as the older session saw them);
    ``order``: the sessions oldest first (default: :func:`session_order`)."""
    from driftmap.volume.defaults import resolve_config

    t0 = time.perf_counter()
    rev = store.head if revision is None else int(revision)
    placed = store.members(rev)  # a session appended after the revision, or abandoned, is not in it (trial 18 B6)
    sessions = {k: kept for k, ids in sessions.items()
                if len(kept := np.intersect1d(np.asarray(ids, dtype=np.int64), placed))}
    if order is not None:
        order = [k for k in order if k in sessions]
    if len(sessions) < 1:
        raise ConfigError(f"{store.path}: latest-state layers need at least one session")
    if int(min_observations) < 1:
        raise ConfigError(f"latest-state layers: min_observations must be >= 1, got {min_observations!r}")
    seq = list(session_order(store, sessions) if order is None else order)
    if sorted(seq) != sorted(sessions):
        raise ConfigError(f"latest-state layers: order {seq} is not a permutation of the sessions {sorted(sessions)}")
    cfg = resolve_config(store, config or VolumeConfig())
    per = VolumeLayers.on_one_grid(store, rev, cfg, [list(sessions[s]) for s in seq])
    grid = per[0].grid
    decide = np.full(grid.n_voxels, -1, dtype=np.int16)
    strong = np.zeros(grid.n_voxels, dtype=bool)
    for s, layers in zip(seq, per):  # oldest first: a newer session overwrites where it observed
        seen = layers.arrays.hits.astype(np.int64) + layers.arrays.misses
        enough = seen >= int(min_observations)
        decide[enough] = s
        strong |= enough
        decide[(seen > 0) & ~strong] = s  # weak evidence decides only where no session has enough
    arrays = VoxelArrays.zeros(grid.n_voxels)
    for s, layers in zip(seq, per):
        mine = decide == s
        for name in ("hits", "misses", "tsdf_sum", "tsdf_count"):
            getattr(arrays, name)[mine] = getattr(layers.arrays, name)[mine]
    merged = VolumeLayers(cfg, grid, per[0].sensor_kind, rev, arrays, view=per[0].view,
                          store_uuid=per[0].store_uuid)
    for s, layers in zip(seq, per):
        _take_hits(merged, layers, decide == s)
    merged.cache[READ_ONLY] = True
    result = LatestState(merged, decide.reshape(grid.shape), seq, dict(zip(seq, per)), time.perf_counter() - t0)
    logger.info("latest-state layers of %d sessions (oldest first %s) at %.3g m: voxels decided per session %s in "
                "%.1f s", len(seq), seq, grid.voxel_size_m, result.voxels_per_session(), result.seconds)
    return result


def _take_hits(merged: VolumeLayers, layers: VolumeLayers, mine: NDArray[np.bool_]) -> None:
    """The frames' hit voxels (:meth:`VolumeLayers.observers`) and hit-point sums (the clearance's surface points)
    of ``layers`` in the voxels its session decided (``mine``, flat over the common grid)."""
    for fid, keys in layers.frame_hits.items():
        flats, inside = merged.grid_flat_of_keys(keys)
        keep = inside & mine[flats]
        if keep.any():
            merged.frame_hits[fid] = keys[keep]
    layers.hit_means()  # consolidates the hit-point batches into one: (lattice keys, fixed-point sums, counts)
    if not layers.hit_batches:
        return
    keys, sums, counts = layers.hit_batches[0]
    if len(keys) == 0:
        return
    flats, inside = merged.grid_flat_of_keys(keys)
    keep = inside & mine[flats]
    merged.hit_batches.append((keys[keep], sums[keep], counts[keep]))
