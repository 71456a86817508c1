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


def _oriented_normals(ctx: DecisionContext, pts: NDArray[np.float64], which: NDArray[np.bool_],
                      box: tuple[NDArray[np.float64], NDArray[np.float64]], p_in: NDArray[np.float64],
                      f_in: NDArray[np.int64], frames: NDArray[np.int64]
                      ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Normals of ``p_in = pts[which]`` (NaN where too few neighbours) and which are finite, each towards the sensor
    origin of its frame (``f_in``; ``frames``: their sorted set): fitted on the voxel means of all of ``pts``
    (``normal_voxel_m``; None: on every point), the points in the world box ``box``. A voxel whose whole
    neighbourhood lies inside the box takes the map's normal of that voxel (:mod:`driftmap.decisions.voxel_normals`:
    the same value); the others are fitted here (:func:`~driftmap.decisions.voxel_normals.fit_normals`). Each point
    then takes its voxel's normal, turned towards its sensor (compiled:
    :func:`driftmap.kernels.queries.oriented_point_normals`)."""
    c = ctx.config
    origins = np.stack([ctx.origin(int(x)) for x in frames])
    sensor_of = id_ranks(f_in, frames)
    if c.normal_voxel_m is None:  # every point's own normal (Open3D over the whole region)
        normals = estimate_normals(pts, k=c.normal_max_neighbors, radius_m=c.normal_radius_m).normals[which]
        return oriented_point_normals(normals, np.arange(len(normals)), p_in, origins, sensor_of)
    fit, inv, cells = voxel_cells(pts, c.normal_voxel_m)
    inv_in = np.compress(which, inv)
    held = np.bincount(inv_in, minlength=len(fit)) > 0  # only the voxels holding a point inside
    at = np.flatnonzero(held)
    normals = np.empty((len(at), 3), np.float32)
    shared = voxel_normals(ctx.layers, c, build=False)  # as prepared for the run (decide.prepare)
    rows = np.full(len(at), -1, np.int64)
    if shared is not None and len(fit) >= c.normal_max_neighbors:  # fewer: the fit sums fewer columns
        inner = shared.interior(fit[at], *box)
        rows[inner] = shared.lookup(cells[at[inner]])
        normals[rows >= 0] = shared.normals[rows[rows >= 0]]
    own = rows < 0
    if own.any():
        normals[own] = fit_normals(fit, at[own], c.normal_max_neighbors, c.normal_radius_m)
    rank = (np.cumsum(held) - 1).take(inv_in)  # each inside point: its voxel's rank in ``at``
    return oriented_point_normals(normals, rank, p_in, origins, sensor_of)


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


def _region_points(ctx: DecisionContext, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> tuple:
    """Points of the region grown by ``normal_margin_m`` (float64, map order), their frames and the grown box."""
    m = ctx.config.normal_margin_m
    box = (lo - m, hi + m)
    pts, fids = ctx.points_in_box(*box)
    return pts, fids, box


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

    pts, fids, box = _region_points(ctx, lo, hi)
    inside, p_in, f_in = select_box(pts, fids, np.asarray(lo, np.float64), np.asarray(hi, np.float64))
    n_in = len(p_in)
    frames = unique_ids(f_in)
    if n_in < min_points:
        out = ctx.finish("too_few_points", "too_few_points", q.roi_min_m, q.roi_max_m, None, frames)
        out["margin"] = None
        out["evidence_m"] = 0.5 * (q.roi_min_m + q.roi_max_m)
        out["details"].update(n_points=n_in, min_points=min_points)
        return out
    normals, ok = _oriented_normals(ctx, pts, inside, box, p_in, f_in, frames)
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
    pts, fids, box = _region_points(ctx, lo, hi)
    # inside: np.linalg.norm(p[:, :2] - centre[:2], axis=1) <= r and |z - centre_z| <= r
    mask, p_in, f_in = select_cylinder(pts, fids, np.asarray(centre, np.float64), float(r))
    n_in = len(p_in)
    frames = unique_ids(f_in)
    if n_in < min_points:
        out = ctx.finish("too_few_points", "too_few_points", lo, hi, None, frames)
        out.update(margin=None, evidence_m=centre)
        out["details"].update(n_points=n_in, min_points=min_points)
        return out
    normals, ok = _oriented_normals(ctx, pts, mask, box, p_in, f_in, frames)
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
