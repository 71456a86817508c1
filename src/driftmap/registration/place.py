"""LiDAR place recognition: Scan Context (Kim & Kim, "Scan Context: Egocentric Spatial Descriptor for Place
Recognition within 3D Point Cloud Map", IROS 2018).

A scan (or a keyframe cloud, in its sensor frame, z up) is binned on a polar grid around the sensor: ``n_rings``
rings out to ``max_radius_m`` by ``n_sectors`` azimuth sectors; each bin holds the highest point above the scan's
ground (0: empty). A place seen again with the sensor turned by a yaw angle gives the same matrix with its columns
rolled, so the distance between two scans is the best over column shifts of one minus the mean cosine similarity
of the columns both saw, and the best shift is a yaw estimate that starts the registration. The ring key (the
share of occupied bins per ring) does not depend on the yaw and picks the few older scans worth the full
comparison.

Unlike a proximity search this does not trust the odometry: it finds a revisit however far the drift has put it
(docs/build.md measures both on the synthetic street).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import ConfigError

logger = logging.getLogger(__name__)

GROUND_PERCENTILE = 1.0
"""Heights are measured from this percentile of the cloud's z (the ground under a car- or robot-mounted LiDAR),
so two scans of one place agree whatever the sensor's mounting height."""


@dataclass(frozen=True)
class ScanContext:
    """One cloud's descriptor."""

    matrix: NDArray[np.float64]
    """(n_rings, n_sectors): highest point above the ground per polar bin (m); 0 where the bin is empty."""
    ring_key: NDArray[np.float64]
    """(n_rings,): share of occupied sectors per ring (invariant to yaw)."""
    max_radius_m: float

    @property
    def n_sectors(self) -> int:
        return int(self.matrix.shape[1])

    @property
    def is_empty(self) -> bool:
        return not np.any(self.matrix)


def scan_context(points_m: NDArray[np.floating], *, n_rings: int = 20, n_sectors: int = 60,
                 max_radius_m: float = 80.0) -> ScanContext:
    """The Scan Context of a cloud given in a z-up sensor frame (a LiDAR's). Points beyond ``max_radius_m`` (in
    the horizontal plane) are ignored; fewer than 10 points give an empty descriptor, which matches nothing."""
    if n_rings < 1 or n_sectors < 1 or not max_radius_m > 0.0:
        raise ConfigError(f"scan_context: n_rings, n_sectors and max_radius_m must be positive, got "
                         f"{n_rings}, {n_sectors}, {max_radius_m}")
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    matrix = np.zeros((n_rings, n_sectors))
    r = np.hypot(pts[:, 0], pts[:, 1])
    keep = (r < max_radius_m) & np.isfinite(r)
    if np.count_nonzero(keep) >= 10:
        pts, r = pts[keep], r[keep]
        height = pts[:, 2] - np.percentile(pts[:, 2], GROUND_PERCENTILE)
        ring = np.minimum((r / max_radius_m * n_rings).astype(np.int64), n_rings - 1)
        azimuth = np.mod(np.arctan2(pts[:, 1], pts[:, 0]), 2.0 * math.pi)
        sector = np.minimum((azimuth / (2.0 * math.pi) * n_sectors).astype(np.int64), n_sectors - 1)
        np.maximum.at(matrix.reshape(-1), ring * n_sectors + sector, np.maximum(height, 0.0))
    ring_key = np.count_nonzero(matrix > 0.0, axis=1) / n_sectors
    return ScanContext(matrix, ring_key.astype(np.float64), float(max_radius_m))


def scan_context_distance(a: ScanContext, b: ScanContext) -> tuple[float, float]:
    """``(distance, yaw_rad)``: the best over column shifts of ``1 - mean cosine similarity`` of the sector
    columns that both descriptors saw (0: identical, 1: nothing in common or nothing seen), and the yaw of ``b``'s
    sensor relative to ``a``'s at that shift (a multiple of the sector width)."""
    if a.matrix.shape != b.matrix.shape:
        raise ConfigError(f"scan_context_distance: descriptors of shapes {a.matrix.shape} and {b.matrix.shape}")
    n = a.n_sectors
    shifts = np.arange(n)
    # rolled[k][:, c] = b[:, (c - k) mod n]: b turned by +k sectors
    rolled = b.matrix[:, (np.arange(n)[None, :] - shifts[:, None]) % n].transpose(1, 0, 2)  # (shift, ring, sector)
    norm_a = np.linalg.norm(a.matrix, axis=0)  # (sector,)
    norm_b = np.linalg.norm(rolled, axis=1)  # (shift, sector)
    dots = np.einsum("rc,krc->kc", a.matrix, rolled)
    valid = (norm_a[None, :] > 0.0) & (norm_b > 0.0)
    sim = np.where(valid, dots / np.where(valid, norm_a[None, :] * norm_b, 1.0), 0.0)
    counts = valid.sum(axis=1)
    distance = np.where(counts > 0, 1.0 - sim.sum(axis=1) / np.maximum(counts, 1), 1.0)
    best = int(np.argmin(distance))
    yaw = best * 2.0 * math.pi / n
    return float(distance[best]), float(math.atan2(math.sin(yaw), math.cos(yaw)))


def yaw_guess(yaw_rad: float) -> NDArray[np.float64]:
    """``T_a_b`` for a yaw estimate: ``b``'s sensor turned by ``yaw_rad`` about ``a``'s z axis, no translation."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return geometry.make_transform(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), None)
