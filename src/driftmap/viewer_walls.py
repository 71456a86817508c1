"""The double walls in the viewer (:mod:`driftmap.viewer`, ``--color double-wall``): the detector of ``driftmap
diagnose`` run on the viewed revision, each shown point's separation, and why its count is no verdict."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.voxels import ABSOLUTE_GRID, voxel_keys

if TYPE_CHECKING:
    from driftmap.diagnostics.wall_results import DoubleWallResult
    from driftmap.store.frame_store import FrameStore


def double_wall_values(store: FrameStore, revision: int, points: NDArray[np.float32],
                        points_budget: int | None) -> tuple[NDArray[np.float64], DoubleWallResult, list[str]]:
    """|separation| of the finest flagged double-wall voxel containing each point (NaN: none), the detector's result
    and why its count is no verdict (:func:`~driftmap.diagnostics.coverage.detector_caveats`)."""
    from driftmap.diagnostics.coverage import detector_caveats
    from driftmap.diagnostics.detector import detect_double_walls
    from driftmap.diagnostics.diagnose_config import DiagnoseConfig
    from driftmap.diagnostics.samples import DiagnosticCloud

    cfg = DiagnoseConfig.for_store(store)
    sampling = cfg.sampling if points_budget is None else cfg.sampling.model_copy(update={"points_budget": points_budget})
    cloud = DiagnosticCloud.from_store(store, sampling, frame_ids=store.members(revision))  # the revision's frames
    poses = store.poses(revision)[np.searchsorted(store.frame_ids, cloud.frame_ids)]
    placed = cloud.place(poses)
    result = detect_double_walls(placed, cfg.double_wall)
    caveats = detector_caveats(placed, result, cfg.coverage)
    values = np.full(len(points), np.nan)
    done = np.zeros(len(points), bool)
    for scale in sorted(result.scales, key=lambda s: s.voxel_size_m):  # finest first: it localises best
        if not scale.flagged.any():
            continue
        size = scale.voxel_size_m
        flagged_keys = voxel_keys(scale.centers_m[scale.flagged], size, grid=ABSOLUTE_GRID, what="double-wall")
        seps = np.abs(scale.separation_m[scale.flagged])
        order = np.argsort(flagged_keys)
        flagged_keys, seps = flagged_keys[order], seps[order]
        # several groups (two surfaces, two sensor sides) can share a voxel: keep the largest separation
        uniq, start = np.unique(flagged_keys, return_index=True)
        sep_max = np.maximum.reduceat(seps, start)
        pk = voxel_keys(points, size, grid=ABSOLUTE_GRID, what="double-wall")  # looked up among the flagged keys
        pos = np.clip(np.searchsorted(uniq, pk), 0, len(uniq) - 1)
        hit = (uniq[pos] == pk) & ~done
        values[hit] = sep_max[pos[hit]]
        done |= hit
    return values, result, caveats
