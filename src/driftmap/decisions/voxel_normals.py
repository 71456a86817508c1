"""The normals of the map's ``normal_voxel_m`` voxels, fitted once per revision and read by every grasp and foothold.

A point's normal (:mod:`driftmap.decisions.surface`) is its voxel's: the covariance of the ``normal_max_neighbors``
nearest voxel means within ``normal_radius_m`` among all the map's voxel means (the means of the points of each
voxel, summed in map order), its eigenvector of the smallest eigenvalue. It depends on the map, not on the query's
box: a region's border does not tilt its normals. :func:`voxel_normals` fits them for every voxel of the map and
records each indexed point's voxel, so a region only reads rows; a run of few grasps and footholds fits its regions'
own (:func:`fit_normals`, the same neighbours and sums, hence the same floats; ``tests/test_decide_batch.py``).

Built by :func:`voxel_normals` in ``decide.prepare`` when a run asks at least
:data:`~driftmap.decisions.decide.SHARED_NORMALS_MIN_QUERIES` grasps and footholds (3-9 s on the shared 2-core machine
for the 385,000 voxels of the 4.2M in-range points of the benchmark map; a region fits its own in milliseconds) and
cached on the layers until they change.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.decisions.point_index import point_index
from driftmap.kernels.queries import knn_covariances
from driftmap.kernels.queries import voxel_cells as _voxel_cells
from driftmap.preprocess.cloud import estimate_normals

if TYPE_CHECKING:
    from driftmap.decisions.settings import DecideConfig
    from driftmap.volume.layers import VolumeLayers

logger = logging.getLogger(__name__)

DENSE_PER_POINT = 8
"""voxel_means: a region whose box spans at most this many voxels per point ranks them from a dense table"""
CHUNK_VOXELS = 1 << 16
"""the map's normals are fitted this many voxels at a time (bounds the (chunk, k, 3) neighbour offsets)"""
MIN_NEIGHBORS = 5
"""a normal fitted on fewer neighbours within the radius is NaN (``estimate_normals``' ``min_neighbors``)"""


def fit_normals(means: NDArray[np.float64], at: NDArray[np.int64], k: int, radius_m: float) -> NDArray[np.float32]:
    """``estimate_normals(means, k=k, radius_m=radius_m, at=at).normals`` (the same floats): the covariance of each
    ``means[at]``'s ``k`` nearest means within ``radius_m`` from the compiled search
    (:func:`driftmap.kernels.queries.knn_covariances`, the same neighbours and sums as the ``cKDTree`` one), its
    eigenvector of the smallest eigenvalue (numpy's batched ``eigh``) oriented towards the origin; NaN with fewer
    than :data:`MIN_NEIGHBORS` neighbours."""
    at = np.asarray(at, dtype=np.int64)
    if len(at) == 0 or not 3 <= k <= 1000 or k < MIN_NEIGHBORS:  # estimate_normals' own checks and count search
        return estimate_normals(means, k=k, radius_m=radius_m, at=at).normals
    pts = np.ascontiguousarray(means, dtype=np.float64)
    bound_m = float(np.nextafter(radius_m, np.inf))  # cKDTree's distance_upper_bound, squared as it squares it
    cov, counts = knn_covariances(pts, at, int(k), float(radius_m), bound_m * bound_m)
    normals = np.linalg.eigh(cov)[1][:, :, 0]
    flip = np.einsum("ij,ij->i", normals, np.zeros(3) - pts[at]) < 0
    normals[flip] *= -1.0
    normals[counts < MIN_NEIGHBORS] = np.nan
    return normals.astype(np.float32)


def voxel_cells(pts: NDArray[np.float64], voxel_m: float
                ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
    """The mean point of every occupied ``voxel_m`` voxel of the world lattice (in the order of their keys), each
    point's voxel (an index into the means) and each voxel's lattice cell (M, 3): the points' sums per voxel in
    point order, divided by the count (compiled; a region whose box spans at most :data:`DENSE_PER_POINT` voxels per
    point ranks them from a dense table, a larger one by sorting)."""
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3), np.int64)
    return _voxel_cells(np.ascontiguousarray(pts, dtype=np.float64), float(voxel_m), DENSE_PER_POINT)


@dataclass
class VoxelNormals:
    """The map's voxel normals (module docstring), with each indexed point's voxel."""

    voxel_m: float
    radius_m: float
    k: int
    normals: NDArray[np.float32]
    """per voxel (in the order of their lattice cells), ``estimate_normals(...).normals`` of its mean among all the
    map's means (NaN: too few neighbours)"""
    index_rows: NDArray[np.int32]
    """per point of the decisions' point index (its cell order), its voxel's row in :attr:`normals`"""


def voxel_normals(layers: VolumeLayers, config: DecideConfig, *, build: bool = True) -> VoxelNormals | None:
    """The map's :class:`VoxelNormals` for ``config``'s normal settings (None with ``normal_voxel_m`` None: normals
    per point), cached on the layers until they change; ``build`` False: only when cached already (None otherwise:
    a few queries fit their own normals faster than the whole map's are fitted)."""
    if config.normal_voxel_m is None:
        return None
    max_range = layers.config.max_range_m if config.range_limited_points else None
    settings = (float(config.normal_voxel_m), float(config.normal_radius_m), int(config.normal_max_neighbors),
                max_range)
    key = f"decisions_voxel_normals_{settings}"
    hit = layers.cache.get(key)
    if hit is not None and hit[0] == layers.version:
        return hit[1]
    if not build:
        return None
    index = point_index(layers, config.range_limited_points)
    by_map = np.argsort(index.order)  # the index's points in map order
    pts = np.asarray(index.world[index.order[by_map]], dtype=np.float64)  # the map's points in map order
    voxel_m, radius_m, k = settings[:3]
    if len(pts) == 0:
        result = None
    else:
        means, inv, _ = voxel_cells(pts, voxel_m)
        index_rows = np.empty(len(pts), np.int32)
        index_rows[by_map] = inv
        normals = np.empty((len(means), 3), np.float32)
        for start in range(0, len(means), CHUNK_VOXELS):
            at = np.arange(start, min(start + CHUNK_VOXELS, len(means)))
            normals[at] = estimate_normals(means, k=k, radius_m=radius_m, at=at).normals
        result = VoxelNormals(voxel_m, radius_m, k, normals, index_rows)
        logger.debug("voxel normals: %d voxels of %d points", len(means), len(pts))
    for old in [c for c in layers.cache if c.startswith("decisions_voxel_normals_")]:
        del layers.cache[old]  # one set at a time
    layers.cache[key] = (layers.version, result)
    return result
