"""Mean Map Entropy and Mean Plane Variance (Razlaw et al. 2015; Kornilova & Ferrer 2021): the literature's
crispness measures of a point cloud, reported beside the smearing score for comparison."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from driftmap.errors import GeometryError


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
