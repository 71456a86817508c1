"""Decisions about surfaces, from the full-resolution map points of the revision (the map view; with
``range_limited_points`` only those within the volume's max range of their sensor): ``grasp`` (a region of
interest: contact point, normal, approach direction and how stable the normal is) and ``foothold`` (a patch: slope
and flatness).

Normals are :func:`driftmap.preprocess.cloud.estimate_normals` (Open3D's covariance normals) over at most
``normal_max_neighbors`` neighbours within ``normal_radius_m``, fitted on the region's points averaged per
``normal_voxel_m`` voxel (world lattice; each point takes its voxel's normal), so that on a map where many frames
overlap the neighbours span the intended radius rather than millimetres of depth noise -- points up to
``normal_margin_m`` outside the region lend their neighbourhood, so a region's border does not tilt its normals --
each oriented towards the sensor of the frame that measured the point. Point counts (``too_few_points``), the
dominant normal's weights, the spread's percentile, the plane's offset and the flatness use every full-resolution
point. The
*dominant normal* is the principal direction of the points' normals (the eigenvector of the largest eigenvalue of
``sum n n^T``), pointing the way most of them do; the *normal spread* is the 90th percentile of the angles between
the points' normals and it (deg): a few degrees on a plane, tens of degrees across an edge or a corner.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.decisions.query_file import FootholdQuery, GraspQuery
from driftmap.preprocess.cloud import estimate_normals

if TYPE_CHECKING:
    from driftmap.decisions.evidence import DecisionContext


DENSE_PER_POINT = 8
"""voxel_means: a region whose box spans at most this many voxels per point ranks them from a dense table"""


def voxel_means(pts: NDArray[np.float64], voxel_m: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The mean point of every occupied ``voxel_m`` voxel of the world lattice (in the order of their keys) and each
    point's voxel (an index into the means)."""
    keys = np.floor(pts / voxel_m).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    packed = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    cells = int(np.prod(dims))
    if cells <= DENSE_PER_POINT * len(pts):  # each point's rank among the occupied voxels, from a dense table
        occupied = np.bincount(packed, minlength=cells) > 0
        inv = (np.cumsum(occupied) - 1)[packed]  # the same as np.unique's inverse, without sorting every point
    else:
        _, inv = np.unique(packed, return_inverse=True)
        inv = inv.ravel()
    n = np.bincount(inv)
    means = np.stack([np.bincount(inv, weights=pts[:, k], minlength=len(n)) for k in range(3)], axis=1) / n[:, None]
    return means, inv


def _oriented_normals(ctx: DecisionContext, pts: NDArray[np.float64], fids: NDArray[np.int64],
                      which: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Normals of ``pts[which]`` (NaN where too few neighbours), each towards its frame's sensor origin: fitted on
    the voxel means of all of ``pts`` (``normal_voxel_m``; None: on every point)."""
    c = ctx.config
    if c.normal_voxel_m is None:  # every point's own normal (Open3D over the whole region)
        normals = estimate_normals(pts, k=c.normal_max_neighbors, radius_m=c.normal_radius_m).normals[which]
    else:
        fit, inv = voxel_means(pts, c.normal_voxel_m)
        held = np.bincount(inv[which], minlength=len(fit)) > 0  # only the voxels holding a point inside
        at = np.flatnonzero(held)
        normals = estimate_normals(fit, k=c.normal_max_neighbors, radius_m=c.normal_radius_m, at=at).normals
        normals = normals[(np.cumsum(held) - 1)[inv[which]]]  # each inside point: its voxel's rank in ``at``
    normals = normals.astype(np.float64)
    p, f = pts[which], fids[which]
    uniq = np.sort(np.unique_values(f))  # a few frames: each point's found by a search, not a sort of every point
    origins = np.stack([ctx.origin(int(x)) for x in uniq])
    flip = np.einsum("ij,ij->i", normals, origins[np.searchsorted(uniq, f)] - p) < 0
    normals[flip] *= -1.0
    return normals


def dominant_normal(normals: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The principal direction of unit normals (oriented as most of them) and each normal's angle to it (deg)."""
    m = normals.T @ normals
    e = np.linalg.eigh(m)[1][:, -1]
    if float(normals.sum(axis=0) @ e) < 0:
        e = -e
    angles = np.degrees(np.arccos(np.clip(normals @ e, -1.0, 1.0)))
    return e, angles


def _region_points(ctx: DecisionContext, lo: NDArray[np.float64], hi: NDArray[np.float64], inside) -> tuple:
    """Points of the region grown by ``normal_margin_m``, which of them are inside (``inside(pts)``), their
    oriented normals (only computed when enough points are inside) and frames."""
    m = ctx.config.normal_margin_m
    pts, fids = ctx.points_in_box(lo - m, hi + m)
    mask = inside(pts) if len(pts) else np.zeros(0, bool)
    return pts, fids, mask


# ------------------------------------------------------------------------------------------------ grasp
def grasp(ctx: DecisionContext, q: GraspQuery) -> dict:
    """``too_few_points`` with fewer than ``min_points`` map points in the ROI; ``unstable_normal`` when the normal
    spread exceeds ``max_normal_spread_deg``; else ``graspable``. The contact point is the centroid of the ROI's
    points moved onto their plane (normal: the dominant normal, offset: the median of the points along it); the
    approach is against the normal. Margin (deg): the allowed spread minus the spread."""
    c = ctx.config
    min_points = q.min_points or c.grasp_min_points
    max_spread = q.max_normal_spread_deg if q.max_normal_spread_deg is not None else c.grasp_max_normal_spread_deg
    pts, fids, inside = _region_points(ctx, q.roi_min_m, q.roi_max_m,
                                       lambda p: np.all((p >= q.roi_min_m) & (p <= q.roi_max_m), axis=1))
    n_in = int(inside.sum())
    if n_in < min_points:
        out = ctx.finish("too_few_points", "too_few_points", q.roi_min_m, q.roi_max_m, None, fids[inside])
        out["margin"] = None
        out["evidence_m"] = 0.5 * (q.roi_min_m + q.roi_max_m)
        out["details"].update(n_points=n_in, min_points=min_points)
        return out
    normals = _oriented_normals(ctx, pts, fids, inside)
    p_in = pts[inside]
    ok = np.all(np.isfinite(normals), axis=1)
    e, angles = dominant_normal(normals[ok])
    spread = float(np.percentile(angles, 90))
    offset = float(np.median(p_in @ e))
    centroid = p_in.mean(axis=0)
    contact = centroid - (float(centroid @ e) - offset) * e
    margin = max_spread - spread
    decision, failure = ("unstable_normal", "unstable_normal") if margin < 0 else ("graspable", None)
    out = ctx.finish(decision, failure, q.roi_min_m, q.roi_max_m, contact, fids[inside], normal=e)
    out["margin"] = margin
    out["details"].update(n_points=n_in, contact_point_m=contact, normal=e, approach=-e, normal_spread_deg=spread,
                          max_normal_spread_deg=max_spread, n_normals=int(ok.sum()))
    return out


# ------------------------------------------------------------------------------------------------ foothold
def foothold(ctx: DecisionContext, q: FootholdQuery) -> dict:
    """The patch: map points within ``radius_m`` of the centre horizontally and vertically (a vertical cylinder of
    radius r and height 2r). ``too_few_points`` below ``min_points``; ``uneven`` when their RMS distance from the
    plane (dominant normal, through their median offset) exceeds ``max_flatness_m``; ``too_steep`` when the slope
    (the dominant normal's angle to the vertical) exceeds ``max_slope_deg``; else ``stable``. Margin (deg): the
    allowed slope minus the slope."""
    c = ctx.config
    min_points = q.min_points or c.foothold_min_points
    max_flat = q.max_flatness_m if q.max_flatness_m is not None else c.foothold_max_flatness_m
    r, centre = q.radius_m, q.center_m

    def inside(p: NDArray[np.float64]) -> NDArray[np.bool_]:
        return (np.linalg.norm(p[:, :2] - centre[:2], axis=1) <= r) & (np.abs(p[:, 2] - centre[2]) <= r)

    lo, hi = q.extent_m()
    pts, fids, mask = _region_points(ctx, lo, hi, inside)
    n_in = int(mask.sum())
    if n_in < min_points:
        out = ctx.finish("too_few_points", "too_few_points", lo, hi, None, fids[mask])
        out.update(margin=None, evidence_m=centre)
        out["details"].update(n_points=n_in, min_points=min_points)
        return out
    normals = _oriented_normals(ctx, pts, fids, mask)
    ok = np.all(np.isfinite(normals), axis=1)
    e, _ = dominant_normal(normals[ok])
    if e[2] < 0:
        e = -e
    p_in = pts[mask]
    along = p_in @ e
    offset = float(np.median(along))
    flatness = float(np.sqrt(np.mean((along - offset) ** 2)))
    slope = float(np.degrees(np.arccos(np.clip(abs(e[2]), 0.0, 1.0))))
    if flatness > max_flat:
        decision, failure = "uneven", "uneven"
    elif slope > q.max_slope_deg:
        decision, failure = "too_steep", "too_steep"
    else:
        decision, failure = "stable", None
    on_plane = centre - (float(centre @ e) - offset) * e
    out = ctx.finish(decision, failure, lo, hi, on_plane, fids[mask], normal=e)
    out["margin"] = q.max_slope_deg - slope
    out["details"].update(n_points=n_in, slope_deg=slope, flatness_m=flatness, max_flatness_m=max_flat, normal=e,
                          surface_point_m=on_plane)
    return out
