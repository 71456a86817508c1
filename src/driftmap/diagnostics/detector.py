"""The multi-scale double-wall detector: the two-layer test (:mod:`driftmap.diagnostics.layers`) at every
configured voxel size, then the flagged surface groups of all sizes merged into regions (adjacent, same
normal, compatible separations), each with the frames of its two layers ordered by time."""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from driftmap.diagnostics.layers import evaluate_scale
from driftmap.diagnostics.samples import PlacedCloud
from driftmap.diagnostics.wall_results import DoubleWallConfig, DoubleWallRegion, DoubleWallResult, ScaleResult
from driftmap.errors import ConfigError

logger = logging.getLogger(__name__)


def detect_double_walls(cloud: PlacedCloud, config: DoubleWallConfig | None = None) -> DoubleWallResult:
    """Evaluate every voxel at every configured size; flag double walls and merge them into regions."""
    cfg = config or DoubleWallConfig()
    if not cfg.voxel_sizes_m or min(cfg.voxel_sizes_m) <= 0:
        raise ConfigError(f"voxel_sizes_m must be positive, got {cfg.voxel_sizes_m}")
    scales = [evaluate_scale(cloud, float(s), cfg) for s in cfg.voxel_sizes_m]
    regions = merge_regions(scales, cloud, cfg)
    for s in scales:
        logger.info("double walls at %.2f m: %d of %d surface groups flagged; smearing %.4f m", s.voxel_size_m,
                    s.voxels_flagged, s.voxels_evaluated, s.score_m)
    return DoubleWallResult(scales, regions, cloud.frame_ids.copy(), cloud.stamps_ns.copy(), cfg)


def _layer_frames(scales: list[ScaleResult], items: list[tuple[int, int]],
                  stamps_ns: NDArray[np.int64]) -> tuple[list[tuple[NDArray[np.int64], NDArray[np.int64]]], NDArray[np.bool_]]:
    """Per flagged item (scale index, group index): the frame rows of its layers A and B with A the layer seen
    earlier (median stamp), and whether that swapped the detector's A (lower offset) and B."""
    stamps = stamps_ns.astype(np.float64)
    by_scale = {}
    for si, s in enumerate(scales):
        order = np.argsort(s.gf_group, kind="stable")
        starts = np.searchsorted(s.gf_group[order], np.arange(len(s.evaluated) + 1))
        by_scale[si] = (order, starts)
    frames_of: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []
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
    return frames_of, flip


def _merge_components(centers: NDArray[np.float64], normals: NDArray[np.float64], sizes: NDArray[np.float64],
                      signed: NDArray[np.float64], sigmas: NDArray[np.float64], merge_angle_deg: float) -> tuple[int, NDArray]:
    """Connected components of the flagged items: pairs whose voxels overlap, whose normals agree within
    ``merge_angle_deg`` and whose signed separations agree within their uncertainty (plus a quarter)."""
    tree = cKDTree(centers)
    pairs = tree.query_pairs(r=float(sizes.max()) * 1.8, output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        near = np.linalg.norm(centers[i] - centers[j], axis=1) <= 0.9 * (sizes[i] + sizes[j])
        same_n = np.einsum("ij,ij->i", normals[i], normals[j]) >= math.cos(math.radians(merge_angle_deg))
        tol = 3.0 * np.hypot(sigmas[i], sigmas[j]) + 0.25 * np.maximum(np.abs(signed[i]), np.abs(signed[j]))
        same_s = np.abs(signed[i] - signed[j]) <= tol
        keep = near & same_n & same_s
        i, j = i[keep], j[keep]
    else:
        i = j = np.zeros(0, np.int64)
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(len(centers), len(centers)))
    n_comp, label = connected_components(graph, directed=False)
    return n_comp, label


def merge_regions(scales: list[ScaleResult], cloud: PlacedCloud, cfg: DoubleWallConfig) -> list[DoubleWallRegion]:
    """Connected flagged groups (overlapping voxels, normals within ``merge_angle_deg``, compatible separations),
    largest region (by points) first."""
    items = [(si, int(gi)) for si, s in enumerate(scales) for gi in np.flatnonzero(s.flagged)]
    if not items:
        return []
    centers = np.array([scales[si].centers_m[gi] for si, gi in items])
    normals = np.array([scales[si].normals[gi] for si, gi in items])
    sizes = np.array([scales[si].voxel_size_m for si, _ in items])
    seps = np.array([scales[si].separation_m[gi] for si, gi in items])
    sigmas = np.array([scales[si].separation_sigma_m[gi] for si, gi in items])
    npts = np.array([scales[si].n_points[gi] for si, gi in items], dtype=np.float64)
    # orient the layers by time: A = the layer seen earlier
    frames_of, flip = _layer_frames(scales, items, cloud.stamps_ns)
    signed = np.where(flip, -seps, seps)
    n_comp, label = _merge_components(centers, normals, sizes, signed, sigmas, cfg.merge_angle_deg)
    regions = []
    ids, st = cloud.frame_ids, cloud.stamps_ns
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
        regions.append(DoubleWallRegion(
            center_m=center, normal=normal, separation_m=abs(off), separation_sigma_m=sig, offset_b_minus_a_m=off,
            frames_a=ids[fa], frames_b=ids[fb],
            stamp_ns_a=(int(st[fa].min()), int(st[fa].max())), stamp_ns_b=(int(st[fb].min()), int(st[fb].max())),
            n_voxels=len(members), voxel_sizes_m=tuple(sorted({float(sizes[m]) for m in members})), n_points=int(wts.sum()),
            rows_a=fa, rows_b=fb, members=tuple(items[m] for m in members),
        ))
    regions.sort(key=lambda r: -r.n_points)
    return regions
