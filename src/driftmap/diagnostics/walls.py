"""A simple, transparent double-wall measure on a known planar wall.

Points near a wall are cut into strips along the wall; in each strip the spread of the points' offsets
along the wall normal is measured (robustly, as half the 5..95 % range). On a consistent map the spread
is the sensor noise; where the same wall was placed twice by drifting poses, the strip holds two layers
and the spread grows to about half their separation. The full detector (any surface, separation with
uncertainty, frame attribution) is :mod:`driftmap.diagnostics.double_wall`'s job; this one needs the
wall's plane and serves as a ground-truth-free sanity measure on synthetic data and tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import ConfigError


@dataclass(frozen=True, slots=True)
class WallSpread:
    """Per-strip spread of the points' offsets along a wall's normal (metres)."""

    strip_centers_m: NDArray[np.float64]
    spread_m: NDArray[np.float64]
    n_points: NDArray[np.int64]

    @property
    def median_m(self) -> float:
        return float(np.median(self.spread_m)) if self.spread_m.size else float("nan")

    @property
    def max_m(self) -> float:
        return float(np.max(self.spread_m)) if self.spread_m.size else float("nan")


def wall_spread(
    points_world: NDArray[np.floating],
    *,
    normal: tuple[float, float, float],
    offset_m: float,
    tangent: tuple[float, float, float],
    band_m: float = 0.3,
    strip_m: float = 0.25,
    z_range_m: tuple[float, float] | None = None,
    tangent_range_m: tuple[float, float] | None = None,
    min_points: int = 30,
) -> WallSpread:
    """Spread of points within ``band_m`` of the plane ``normal . p = offset_m``, per strip along ``tangent``."""
    n = np.asarray(normal, dtype=np.float64)
    t = np.asarray(tangent, dtype=np.float64)
    if abs(np.linalg.norm(n) - 1) > 1e-6 or abs(np.linalg.norm(t) - 1) > 1e-6 or abs(n @ t) > 1e-6:
        raise ConfigError("wall_spread: normal and tangent must be orthogonal unit vectors")
    p = np.asarray(points_world, dtype=np.float64)
    d = p @ n - offset_m
    s = p @ t
    keep = np.abs(d) < band_m
    if z_range_m is not None:
        keep &= (p[:, 2] >= z_range_m[0]) & (p[:, 2] <= z_range_m[1])
    if tangent_range_m is not None:
        keep &= (s >= tangent_range_m[0]) & (s <= tangent_range_m[1])
    d, s = d[keep], s[keep]
    if d.size == 0:
        return WallSpread(np.zeros(0), np.zeros(0), np.zeros(0, np.int64))
    strip = np.floor(s / strip_m).astype(np.int64)
    order = np.argsort(strip, kind="stable")
    strip, d = strip[order], d[order]
    uniq, start, counts = np.unique(strip, return_index=True, return_counts=True)
    centers, spreads, ns = [], [], []
    for key, a, c in zip(uniq, start, counts, strict=True):
        if c < min_points:
            continue
        lo, hi = np.percentile(d[a : a + c], [5.0, 95.0])
        centers.append((key + 0.5) * strip_m)
        spreads.append(0.5 * (hi - lo))
        ns.append(c)
    return WallSpread(np.asarray(centers), np.asarray(spreads), np.asarray(ns, dtype=np.int64))
