"""Free-space conflict between two clouds: how much of one cloud lies where the other's sensor saw through.

A sensor that measured a surface at range ``r`` in some direction saw free space along that ray up to ``r``. A
second cloud, placed in the first sensor's frame, whose points lie on such rays clearly in front of the measured
surface contradicts it: either the world changed there (a door closed, a chair moved in) or the second cloud is
placed wrongly. A wrong placement of a cloud of another place contradicts a large share of what both sensors saw; one
place seen twice contradicts only where something changed. ``merge`` uses the share to refuse a session that two
registrations agree on but that sits in the other session's free space (docs/merge.md, hostile trial 14 F4).

The viewer's rays are binned by direction on a cube map (six faces of ``n x n`` cells, ``bin_deg`` wide at a face's
centre), which has no pole: a depth camera looks along its z axis, a LiDAR around it, and both bin alike. Per cell
the **nearest** of the viewer's points is taken as the free-space bound (the least free space the cell's rays saw:
a cell straddling a depth edge never counts the far side's free space). A point of the other cloud in a cell that
holds a viewer point is **conflicting** when it lies more than ``max(margin_m, margin_fraction * r)`` in front of
that bound (the margin takes the residual misalignment and the range noise), **agreeing** within the margin of it,
and **occluded** behind it (the viewer could not have seen it: no evidence either way). The share is conflicting over
conflicting + agreeing: the occluded points are left out, since how much of a cloud hides behind the other's
surfaces depends on the two viewpoints, not on the placement. Measured (docs/merge.md): one place seen twice 0.6-1.6 %
(7-Scenes, synthetic room, real Livox-like scans), 3.9 % with a door closed in the LiDAR's view; the 7-Scenes kitchen
on the synthetic room 15-24 %, the synthetic LiDAR room turned by half a turn 9 %.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import ConfigError

__all__ = ["FreeSpaceConflict", "direction_cells", "free_space_conflict"]


@dataclass(frozen=True)
class FreeSpaceConflict:
    """Of the other cloud's points on a viewer's ray: how many lie clearly in front of the surface that ray ended on
    (conflicting), on it (agreeing) and behind it (occluded)."""

    conflicting: int
    agreeing: int
    occluded: int

    @property
    def share(self) -> float:
        """conflicting / (conflicting + agreeing) (0 when neither)."""
        judged = self.conflicting + self.agreeing
        return self.conflicting / judged if judged else 0.0

    def __add__(self, other: FreeSpaceConflict) -> FreeSpaceConflict:
        return FreeSpaceConflict(self.conflicting + other.conflicting, self.agreeing + other.agreeing,
                                 self.occluded + other.occluded)


def direction_cells(points_m: NDArray[np.floating], bin_deg: float) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Each point's cube-map direction cell (an integer key) and its range (m). Points at the origin get key -1."""
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    r = np.linalg.norm(p, axis=1)
    n = int(math.ceil(2.0 / math.tan(math.radians(bin_deg))))
    keys = np.full(len(p), -1, dtype=np.int64)
    ok = r > 0.0
    if not ok.any():
        return keys, r
    d = p[ok] / r[ok, None]
    rows = np.arange(len(d))
    axis = np.argmax(np.abs(d), axis=1)
    dominant = d[rows, axis]
    face = axis * 2 + (dominant < 0)
    u = d[rows, (axis + 1) % 3] / np.abs(dominant)
    v = d[rows, (axis + 2) % 3] / np.abs(dominant)
    iu = np.clip(((u + 1.0) * 0.5 * n).astype(np.int64), 0, n - 1)
    iv = np.clip(((v + 1.0) * 0.5 * n).astype(np.int64), 0, n - 1)
    keys[ok] = (face * n + iu) * n + iv
    return keys, r


def free_space_conflict(viewer_points_m: NDArray[np.floating], other_points_m: NDArray[np.floating], *,
                        margin_m: float, margin_fraction: float = 0.05, bin_deg: float = 1.0) -> FreeSpaceConflict:
    """How many of ``other_points_m`` (given in the viewer's sensor frame) lie clearly in front of, on and behind the
    surface the viewer measured in their direction (module docstring)."""
    if not (margin_m >= 0.0 and margin_fraction >= 0.0 and 0.0 < bin_deg < 45.0):
        raise ConfigError(f"free_space_conflict: margin_m {margin_m}, margin_fraction {margin_fraction} must be >= 0 "
                          f"and bin_deg {bin_deg} in (0, 45)")
    viewer_keys, viewer_r = direction_cells(viewer_points_m, bin_deg)
    other_keys, other_r = direction_cells(other_points_m, bin_deg)
    keep = viewer_keys >= 0
    cells, inverse = np.unique(viewer_keys[keep], return_inverse=True)
    if len(cells) == 0:
        return FreeSpaceConflict(0, 0, 0)
    nearest = np.full(len(cells), np.inf)
    np.minimum.at(nearest, inverse, viewer_r[keep])
    pos = np.clip(np.searchsorted(cells, other_keys), 0, len(cells) - 1)
    on_ray = (cells[pos] == other_keys) & (other_keys >= 0)
    bound = nearest[pos[on_ray]]
    margin = np.maximum(margin_m, margin_fraction * bound)
    r = other_r[on_ray]
    conflicting = int(np.count_nonzero(r < bound - margin))
    occluded = int(np.count_nonzero(r > bound + margin))
    return FreeSpaceConflict(conflicting, len(r) - conflicting - occluded, occluded)
