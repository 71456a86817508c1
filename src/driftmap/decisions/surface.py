"""Decisions about surfaces, from the full-resolution map points of the revision (the map view; with
``range_limited_points`` only those within the volume's max range of their sensor): ``grasp`` (a region of
interest: contact point, normal, approach direction and how stable the normal is) and ``foothold`` (a patch: slope
and flatness).

Normals are :func:`driftmap.preprocess.cloud.estimate_normals` (Open3D's covariance normals) over at most
``normal_max_neighbors`` neighbours within ``normal_radius_m``, fitted on the region's points averaged per
``normal_voxel_m`` voxel (world lattice; each point takes its voxel's normal), so that on a map where many frames
overlap the neighbours span the intended radius rather than millimetres of depth noise -- the neighbours are the
map's voxels, inside the region or not, so a region's border does not tilt its normals
(:mod:`driftmap.decisions.voxel_normals`) -- each oriented towards the sensor of the frame that measured the point.
Point counts (``too_few_points``), the dominant normal's weights, the spread's percentile, the plane's offset and the
flatness use every full-resolution point. The *dominant normal* is the principal direction of the points' normals
(the eigenvector of the largest eigenvalue of ``sum n n^T``), pointing the way most of them do; the *normal spread* is the 90th percentile of the angles between
the points' normals and it (deg): a few degrees on a plane, tens of degrees across an edge or a corner.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.decisions.evidence import id_ranks, unique_ids
from driftmap.decisions.query_file import FootholdQuery, GraspQuery
from driftmap.decisions.voxel_normals import (  # noqa: F401 - re-export
    DENSE_PER_POINT,
    fit_normals,
    voxel_cells,
    voxel_normals,
)
from driftmap.kernels.queries import oriented_point_normals
from driftmap.kernels.regions import select_box, select_cylinder
from driftmap.preprocess.cloud import estimate_normals

if TYPE_CHECKING:
    from driftmap.decisions.evidence import DecisionContext


def voxel_means(pts: NDArray[np.float64], voxel_m: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The mean point of every occupied ``voxel_m`` voxel of the world lattice (in the order of their keys) and each
    point's voxel (an index into the means)."""
    means, inv, _ = voxel_cells(pts, voxel_m)
    return means, inv


def _oriented(ctx: DecisionContext, normals: NDArray[np.floating], voxel_of: NDArray[np.int64],
              p_in: NDArray[np.float64], f_in: NDArray[np.int64], frames: NDArray[np.int64]
              ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Per point of ``p_in``, ``normals[voxel_of]`` turned towards the sensor origin of its frame (``f_in``;
    ``frames``: their sorted set), and which are finite (compiled:
    :func:`driftmap.kernels.queries.oriented_point_normals`)."""
    if len(p_in) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.bool_)
    origins = np.stack([ctx.origin(int(x)) for x in frames])
    return oriented_point_normals(normals, voxel_of, p_in, origins, id_ranks(f_in, frames))


def _region_normals(ctx: DecisionContext, lo: NDArray[np.float64], hi: NDArray[np.float64],
                    select: Callable[[NDArray[np.float64], NDArray[np.int64]], tuple]
                    ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]]:
    """The region's points (``select(pts, fids) -> (mask, p_in, f_in)`` of the map points in the box ``lo .. hi``,
    map order), their frames, and each one's normal (oriented, NaN where too few neighbours) and whether it is
    finite: its ``normal_voxel_m`` voxel's normal among the map's voxel means (module docstring).

    With the map's normals prepared (:mod:`driftmap.decisions.voxel_normals`, ``decide.prepare``) each point takes
    its voxel's row. Otherwise they are fitted here on the voxel means of the region grown by ``normal_radius_m``
    plus three voxels, among the voxels that box holds whole (by their lattice cells, one voxel in from its faces):
    every voxel whose mean lies within the radius of a region voxel's mean is one of them, with the same points in
    the same (map) order as in the map, so the same mean, neighbours and normal
    (:func:`~driftmap.decisions.voxel_normals.fit_normals`; with ``normal_voxel_m`` None: Open3D's normal of every
    point of the grown box)."""
    c = ctx.config
    shared = voxel_normals(ctx.layers, c, build=False)  # as prepared for the run (decide.prepare)
    if shared is not None:
        pts, fids, vox = ctx.point_index.box_with_voxels(lo, hi, shared.index_rows)
        mask, p_in, f_in = select(pts, fids)
        frames = unique_ids(f_in)
        normals, ok = _oriented(ctx, shared.normals, np.compress(mask, vox), p_in, f_in, frames)
        return p_in, f_in, normals, ok
    v = c.normal_voxel_m
    grow = c.normal_radius_m + 3.0 * (v if v is not None else 0.0)
    g_lo, g_hi = lo - grow, hi + grow
    pts, fids = ctx.points_in_box(g_lo, g_hi)
    inside = (pts >= lo).all(axis=1) & (pts <= hi).all(axis=1)
    mask, p_in, f_in = select(np.compress(inside, pts, axis=0), np.compress(inside, fids))
    which = np.flatnonzero(inside)[mask]
    frames = unique_ids(f_in)
    if v is None:  # every point's own normal (Open3D over the grown box)
        normals = estimate_normals(pts, k=c.normal_max_neighbors, radius_m=c.normal_radius_m, at=which).normals
        return p_in, f_in, *_oriented(ctx, normals, np.arange(len(which)), p_in, f_in, frames)
    means, inv, cells = voxel_cells(pts, v)
    whole = np.flatnonzero(np.all((cells > np.floor(g_lo / v)) & (cells < np.floor(g_hi / v)), axis=1))
    rank = np.full(len(means), -1, np.int64)
    rank[whole] = np.arange(len(whole))
    inv_in = inv.take(which)
    held = np.flatnonzero(np.bincount(inv_in, minlength=len(means)))  # the voxels of the region's points
    assert np.all(rank[held] >= 0), "a region voxel not held whole by a box grown by 3 voxels"  # floor is monotonic
    fitted = fit_normals(means[whole], rank[held], c.normal_max_neighbors, c.normal_radius_m)
    row = np.full(len(means), -1, np.int64)
    row[held] = np.arange(len(held))
    return p_in, f_in, *_oriented(ctx, fitted, row.take(inv_in), p_in, f_in, frames)


CYLINDER_SLACK_M = 1e-6
"""foothold: the cylinder's points are tested among those of its bounding box widened by this much"""


def _finite_rows(normals: NDArray[np.float64], ok: NDArray[np.bool_]) -> NDArray[np.float64]:
    return normals if ok.all() else np.compress(ok, normals, axis=0)


def _sum_along_negative(normals: NDArray[np.float64], e: NDArray[np.float64]) -> bool:
    """``float(normals.sum(axis=0) @ e) < 0`` for unit normals: from the per-row dot products (a fraction of the
    column sums' time), whose sum differs from it by less than ``8 n^2`` units of rounding, the exact expression
    evaluated only when the sum is that close to 0."""
    n = len(normals)
    fast = float((normals @ e).sum())
    if abs(fast) > 8.0 * n * n * np.finfo(np.float64).eps + 1e-300:
        return fast < 0
    return float(normals.sum(axis=0) @ e) < 0


def dominant_normal(normals: NDArray[np.float64], angles: bool = True
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The principal direction of unit normals (oriented as most of them) and each normal's angle to it (deg; None
    with ``angles=False``)."""
    m = normals.T @ normals
    e = np.linalg.eigh(m)[1][:, -1]
    if _sum_along_negative(normals, e):
        e = -e
    if not angles:
        return e, None
    return e, np.degrees(np.arccos(np.clip(normals @ e, -1.0, 1.0)))


# ------------------------------------------------------------------------------------------------ grasp
def grasp(ctx: DecisionContext, q: GraspQuery) -> dict:
    """``too_few_points`` with fewer than ``min_points`` map points in the ROI; ``unstable_normal`` when the normal
    spread exceeds ``max_normal_spread_deg``; else ``graspable``. The contact point is the centroid of the ROI's
    points moved onto their plane (normal: the dominant normal, offset: the median of the points along it); the
    approach is against the normal. Margin (deg): the allowed spread minus the spread."""
    c = ctx.config
    min_points = q.min_points or c.grasp_min_points
    max_spread = q.max_normal_spread_deg if q.max_normal_spread_deg is not None else c.grasp_max_normal_spread_deg
    lo, hi = q.roi_min_m, q.roi_max_m

    lo64, hi64 = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    p_in, f_in, normals, ok = _region_normals(ctx, lo64, hi64, lambda pts, fids: select_box(pts, fids, lo64, hi64))
    n_in = len(p_in)
    frames = unique_ids(f_in)
    if n_in < min_points:
        out = ctx.finish("too_few_points", "too_few_points", q.roi_min_m, q.roi_max_m, None, frames)
        out["margin"] = None
        out["evidence_m"] = 0.5 * (q.roi_min_m + q.roi_max_m)
        out["details"].update(n_points=n_in, min_points=min_points)
        return out
    e, angles = dominant_normal(_finite_rows(normals, ok))
    spread = float(np.percentile(angles, 90))
    offset = float(np.median(p_in @ e))
    centroid = p_in.mean(axis=0)
    contact = centroid - (float(centroid @ e) - offset) * e
    margin = max_spread - spread
    decision, failure = ("unstable_normal", "unstable_normal") if margin < 0 else ("graspable", None)
    out = ctx.finish(decision, failure, q.roi_min_m, q.roi_max_m, contact, frames, normal=e)
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

    lo, hi = q.extent_m()
    c64 = np.asarray(centre, np.float64)
    # inside: np.linalg.norm(p[:, :2] - centre[:2], axis=1) <= r and |z - centre_z| <= r, of the points of the
    # cylinder's box widened by CYLINDER_SLACK_M (so that rounding of centre -+ r cuts none of them)
    p_in, f_in, normals, ok = _region_normals(ctx, np.asarray(lo, np.float64) - CYLINDER_SLACK_M,
                                              np.asarray(hi, np.float64) + CYLINDER_SLACK_M,
                                              lambda pts, fids: select_cylinder(pts, fids, c64, float(r)))
    n_in = len(p_in)
    frames = unique_ids(f_in)
    if n_in < min_points:
        out = ctx.finish("too_few_points", "too_few_points", lo, hi, None, frames)
        out.update(margin=None, evidence_m=centre)
        out["details"].update(n_points=n_in, min_points=min_points)
        return out
    e, _ = dominant_normal(_finite_rows(normals, ok), angles=False)
    if e[2] < 0:
        e = -e
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
    out = ctx.finish(decision, failure, lo, hi, on_plane, frames, normal=e)
    out["margin"] = q.max_slope_deg - slope
    out["details"].update(n_points=n_in, slope_deg=slope, flatness_m=flatness, max_flatness_m=max_flat, normal=e,
                          surface_point_m=on_plane)
    return out
