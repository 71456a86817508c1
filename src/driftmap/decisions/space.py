"""Decisions about space: ``clearance`` (a robot sphere at points), ``collision`` (a box or cylinder footprint swept
along a path) and ``explore`` (how much of a region nobody saw).

Obstacles are the layers' *observed surface*: the mean point of every occupied voxel at least ``surface_min_hits``
points ended in (:func:`driftmap.volume.queries.surface_tree`), so one stray point of depth noise is no wall.
Unknown space is a voxel no ray ended in or passed through. The policy for it (``unknown_is``, per query or the
volume setting; default ``occupied``): a sphere or footprint that reaches unknown space before any surface is
``unknown`` -- a planner must not go there without looking -- and with ``free`` unknown space is ignored. Anything
outside the layers' grid is unknown.
"""

from __future__ import annotations

import itertools
import logging
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.decisions.errors import QueryError
from driftmap.decisions.query_file import ClearanceQuery, CollisionQuery, ExploreQuery
from driftmap.kernels import queries as kq
from driftmap.volume.queries import surface_box_distances, surface_tree, surface_voxel_reach_m

logger = logging.getLogger(__name__)

if TYPE_CHECKING:
    from driftmap.decisions.evidence import DecisionContext
    from driftmap.volume.layers import VolumeLayers

UNKNOWN = -1
MARGIN_CAP_M = 0.25
"""collision: the footprint's clearance is exact up to this far beyond its bounding sphere (a lower bound beyond)"""


def _policy(ctx: DecisionContext, value: str | None) -> str:
    return value if value is not None else ctx.layers.config.unknown_is.value


def _surface(ctx: DecisionContext) -> tuple[object | None, NDArray[np.float64]]:
    tree = surface_tree(ctx.layers)
    return tree, (np.zeros((0, 3)) if tree is None else np.asarray(tree.data))


# ------------------------------------------------------------------------------------------------ clearance
def clearance(ctx: DecisionContext, q: ClearanceQuery) -> dict:
    """``blocked`` when an observed surface is within the radius of any point (the distance to its voxel's cube:
    no point measured in the voxel is nearer, so a coarse map does not call free what a point 0.1 m away blocks);
    else ``unknown`` when an
    unknown voxel is (its cube within the radius; the voxel holding a point always), with policy ``occupied``; else
    ``free``. Margin: the smallest clearance to a surface minus the radius. A point inside
    an observed surface voxel's cube has clearance 0: ``blocked`` whatever the radius (0 included), margin ``-radius``."""
    tree, surface = _surface(ctx)
    d_surf, idx = surface_box_distances(ctx.layers, q.points_m)
    k = int(np.argmin(d_surf))
    margin = float(d_surf[k]) - q.radius_m
    policy = _policy(ctx, q.unknown_is)
    n_unknown = unknown_in_balls(ctx.layers, q.points_m, q.radius_m) if policy == "occupied" else 0
    if margin <= 0 and np.isfinite(margin):  # touching counts: a point inside a surface voxel is never free
        decision, failure = "blocked", "collision"
    elif n_unknown:
        decision, failure = "unknown", "unknown_space"
    else:
        decision, failure = "free", None
    evidence = surface[int(idx[k])] if np.isfinite(d_surf[k]) else None
    frames = ctx.layers.observers(evidence[None])[0] if evidence is not None else np.zeros(0, np.int64)
    lo, hi = q.extent_m()
    out = ctx.finish(decision, failure, lo, hi, evidence, frames)
    out["margin"] = margin if np.isfinite(margin) else None
    out["details"].update(clearance_m=float(d_surf[k]), unknown_voxels_in_reach=int(n_unknown),
                          nearest_point_index=k, unknown_is=policy)
    return out


def unknown_in_ball(layers: VolumeLayers, point: NDArray[np.float64], radius_m: float) -> int:
    """How many unknown voxels (or voxels outside the grid) have their cube within ``radius_m`` of ``point`` (the
    voxel holding the point always: a point inside unknown space is never free, whatever the radius)."""
    return unknown_in_columns(layers, *_ball_columns(layers, point, radius_m))


MAX_BALL_COLUMNS = 50_000_000
"""clearance: a query whose balls span more voxel columns than this (summed over its points, at the layers' voxel
size) is refused, not counted (~0.3 us per column: 40M columns took 11 s on this 2-core machine)."""
BALL_COLUMN_CHUNK = 1 << 20
"""clearance: the columns of at most this many (and at least one point's) are enumerated at once, so a query's
memory stays bounded (~150 MB) whatever its point count."""


def _ball_cells(pts: NDArray[np.float64], radius_m: float, vs: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    return np.floor((pts - radius_m) / vs).astype(np.int64), np.floor((pts + radius_m) / vs).astype(np.int64)


def n_ball_columns(points: NDArray[np.float64], radius_m: float, voxel_m: float) -> int:
    """The lattice columns :func:`unknown_in_balls` enumerates for ``points`` (their balls' bounding squares)."""
    lo, hi = _ball_cells(np.asarray(points, dtype=np.float64).reshape(-1, 3), radius_m, voxel_m)
    return int(((hi[:, 0] - lo[:, 0] + 1).astype(np.float64) * (hi[:, 1] - lo[:, 1] + 1)).sum())


def check_ball_columns(q: ClearanceQuery, voxel_m: float) -> None:
    """A :class:`QueryError` naming the query when its balls span more than :data:`MAX_BALL_COLUMNS` columns."""
    n = n_ball_columns(q.points_m, q.radius_m, voxel_m)
    if n > MAX_BALL_COLUMNS:
        raise QueryError(f"query {q.id!r}: {len(q.points_m):,} points of radius_m {q.radius_m:g} span {n:,.0f} "
                         f"voxel columns at the layers' {voxel_m:g} m voxels, more than {MAX_BALL_COLUMNS:,}: split "
                         "it, use fewer points or a smaller radius", query_id=q.id, field="radius_m")


def unknown_in_balls(layers: VolumeLayers, points: NDArray[np.float64], radius_m: float) -> int:
    """:func:`unknown_in_ball` summed over ``points`` (one summed-volume lookup for the columns of many points, found
    for them at once: the same columns and z ranges as :func:`_ball_columns` per point), in chunks of at most
    :data:`BALL_COLUMN_CHUNK` columns (or one point's)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return 0
    vs = layers.grid.voxel_size_m
    lo, hi = _ball_cells(pts, radius_m, vs)
    counts = (hi[:, 0] - lo[:, 0] + 1) * (hi[:, 1] - lo[:, 1] + 1)
    ends = np.cumsum(counts)
    total, start = 0, 0
    while start < len(pts):  # each chunk: the points whose columns end within BALL_COLUMN_CHUNK of its first's start
        base = ends[start] - counts[start]
        stop = max(start + 1, int(np.searchsorted(ends, base + BALL_COLUMN_CHUNK, side="right")))
        total += _unknown_in_ball_chunk(layers, pts[start:stop], lo[start:stop], hi[start:stop], radius_m)
        start = stop
    return total


def _unknown_in_ball_chunk(layers: VolumeLayers, pts: NDArray[np.float64], lo: NDArray[np.int64],
                           hi: NDArray[np.int64], radius_m: float) -> int:
    vs = layers.grid.voxel_size_m
    ny = hi[:, 1] - lo[:, 1] + 1
    counts = (hi[:, 0] - lo[:, 0] + 1) * ny
    which = np.repeat(np.arange(len(pts)), counts)  # per column, its point
    local = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    n_y = ny[which]
    gx, gy = lo[which, 0] + local // n_y, lo[which, 1] + local % n_y
    px, py, pz = pts[which, 0], pts[which, 1], pts[which, 2]
    rho2 = _gap(gx, px, vs) ** 2 + _gap(gy, py, vs) ** 2  # to each column's square
    keep = rho2 <= radius_m * radius_m
    gx, gy, pz = gx[keep], gy[keep], pz[keep]
    dz = np.sqrt(np.maximum(radius_m * radius_m - rho2[keep], 0.0))
    z0 = np.floor((pz - dz) / vs).astype(np.int64)
    z1 = np.floor((pz + dz) / vs).astype(np.int64)
    return unknown_in_columns(layers, gx, gy, z0, z1)


def _ball_columns(layers: VolumeLayers, point: NDArray[np.float64], radius_m: float) -> tuple[NDArray[np.int64], ...]:
    """The lattice columns ``(gx, gy)`` whose square comes within ``radius_m`` of ``point`` and per column the z
    range ``z0 .. z1`` of the voxels whose cube does."""
    vs = layers.grid.voxel_size_m
    lo, hi = _ball_cells(point, radius_m, vs)
    gx, gy = (a.ravel() for a in np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij"))
    rho2 = _gap(gx, point[0], vs) ** 2 + _gap(gy, point[1], vs) ** 2  # to each column's square
    keep = rho2 <= radius_m * radius_m
    gx, gy = gx[keep], gy[keep]
    dz = np.sqrt(np.maximum(radius_m * radius_m - rho2[keep], 0.0))
    z0 = np.floor((point[2] - dz) / vs).astype(np.int64)
    z1 = np.floor((point[2] + dz) / vs).astype(np.int64)
    return gx, gy, z0, z1


def _gap(cells: NDArray[np.int64], x: float | NDArray[np.float64], vs: float) -> NDArray[np.float64]:
    """Distance along one axis from ``x`` to the cells ``[k vs, (k + 1) vs]`` (0 inside)."""
    return np.maximum(np.maximum(cells * vs - x, x - (cells + 1) * vs), 0.0)


# ------------------------------------------------------------------------------------------------ collision
def collision(ctx: DecisionContext, q: CollisionQuery) -> dict:
    """Sweep the footprint (centred on the path) along the path every ``sweep_step_m``; the first place where an
    observed surface point lies inside it is a contact (``blocked``), the first where it overlaps an unknown voxel
    (policy ``occupied``) is ``unknown``, whichever comes first (a contact wins a tie); else ``free``.
    Margin: the smallest distance between the footprint and a surface point along the whole path (negative: how
    deep the surface reaches into it)."""
    step = sweep_step(q, ctx.config.sweep_step_m, ctx.voxel_m)
    check_path_samples(q, step)
    samples, along = path_samples(q.path_m, step)
    tree, surface = _surface(ctx)
    signed, nearest = _footprint_distances(q, samples, tree, surface, ctx.voxel_m, surface_reach(ctx.layers))
    contact = np.flatnonzero(signed < 0)
    unknown = (np.flatnonzero(_unknown_counts(ctx.layers, q, samples) > 0) if _policy(ctx, q.unknown_is) == "occupied"
               else np.zeros(0, np.int64))
    first_c = int(contact[0]) if len(contact) else None
    first_u = int(unknown[0]) if len(unknown) else None
    k_min = int(np.argmin(signed))
    if first_c is not None and (first_u is None or first_c <= first_u):
        decision, failure, at = "blocked", "collision", first_c
        evidence = surface[int(nearest[first_c])]
    elif first_u is not None:
        decision, failure, at = "unknown", "unknown_space", first_u
        evidence = surface[int(nearest[k_min])] if nearest[k_min] >= 0 else None
    else:
        decision, failure, at = "free", None, None
        evidence = surface[int(nearest[k_min])] if nearest[k_min] >= 0 else None
    frames = ctx.layers.observers(evidence[None])[0] if evidence is not None else np.zeros(0, np.int64)
    lo, hi = q.extent_m()
    out = ctx.finish(decision, failure, lo, hi, evidence, frames)
    margin = float(signed[k_min])
    out["margin"] = margin if np.isfinite(margin) else None
    out["details"].update(
        outcome={"blocked": "contact", "unknown": "unknown", "free": "clear"}[decision],
        contact_distance_m=None if at is None else float(along[at]),
        stop_point_m=None if at is None else samples[at].tolist(),
        path_length_m=float(along[-1]), footprint=q.footprint, footprint_m=list(q.size_m),
        unknown_is=_policy(ctx, q.unknown_is), n_samples=len(samples), sweep_step_m=step)
    return out


def sweep_step(q: CollisionQuery, step_m: float | None, voxel_m: float, *, warn: bool = True) -> float:
    """The distance between footprint placements: ``step_m`` (``[decide] sweep_step_m``; default half a voxel), at
    most the footprint's smallest extent plus half a voxel, so that no surface voxel (a cube of one voxel) lies
    between two placements unseen -- a 30 cm step with a 2 cm footprint would sweep through a board."""
    smallest = float(min(q.size_m)) if q.footprint == "box" else float(min(2.0 * q.size_m[0], q.size_m[1]))
    cap = smallest + 0.5 * voxel_m
    if step_m is None:
        return min(0.5 * voxel_m, cap)
    if step_m > cap:
        if warn:
            logger.warning("query %r: sweep_step_m %g m is longer than the footprint's smallest extent (%g m) plus half "
                           "a voxel: swept every %g m instead, so that no obstacle lies between two placements",
                           q.id, step_m, smallest, cap)
        return cap
    return float(step_m)


MAX_PATH_SAMPLES = 1_000_000
"""collision: a path needing more footprint placements than this (at the sweep step) is refused, not swept."""


def n_path_samples(path: NDArray[np.float64], step_m: float) -> int:
    """How many points :func:`path_samples` would return (without making them)."""
    seg = np.linalg.norm(np.diff(np.asarray(path, dtype=np.float64), axis=0), axis=1)
    seg = seg[seg > 0]
    return 1 + int(np.maximum(1.0, np.ceil(seg / step_m)).sum())


def check_path_samples(q: CollisionQuery, step_m: float) -> None:
    """A :class:`QueryError` naming the query when its path needs more than :data:`MAX_PATH_SAMPLES` placements."""
    n = n_path_samples(q.path_m, step_m)
    if n > MAX_PATH_SAMPLES:
        raise QueryError(f"query {q.id!r}: path_m ({q.length_m:.6g} m) needs {n:,} footprint placements at the "
                         f"sweep step of {step_m:g} m, more than {MAX_PATH_SAMPLES:,}: split it or check its units",
                         query_id=q.id, field="path_m")


def path_samples(path: NDArray[np.float64], step_m: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Points every ``step_m`` (at most) along a polyline, its vertices included, and their distance along it."""
    pts, dist, travelled = [path[:1]], [np.zeros(1)], 0.0
    for a, b in itertools.pairwise(path):
        seg = float(np.linalg.norm(b - a))
        if seg == 0:
            continue
        n = max(1, int(np.ceil(seg / step_m)))
        t = np.arange(1, n + 1) / n
        pts.append(a + (b - a) * t[:, None])
        dist.append(travelled + seg * t)
        travelled += seg
    return np.concatenate(pts), np.concatenate(dist)


def footprint_signed_distance(q: CollisionQuery, offsets: NDArray[np.float64]) -> NDArray[np.float64]:
    """Signed distance (m) of points (given relative to the footprint's centre) to the footprint: negative inside."""
    return footprint_signed_distances(q, np.zeros((1, 3)), offsets)[0]


def footprint_signed_distances(q: CollisionQuery, centres: NDArray[np.float64], points: NDArray[np.float64]
                               ) -> NDArray[np.float64]:
    """(S, M) signed distances of ``points`` to the footprint placed at each of ``centres`` (negative inside)."""
    # per axis (S, M) arrays, no reduction over a last axis of 2 or 3 (the same sums and maxima, in the same order),
    # computed in place where the value is the same
    if q.footprint == "box":
        half = 0.5 * np.asarray(q.size_m, dtype=np.float64)
        d = []
        for k in range(3):
            t = np.subtract(points[None, :, k], centres[:, None, k])
            np.abs(t, out=t)
            t -= half[k]
            d.append(t)
    else:
        r, h = q.size_m
        ox, oy, oz = (points[None, :, k] - centres[:, None, k] for k in range(3))
        d = [np.hypot(ox, oy) - r, np.abs(oz) - 0.5 * h]
    deepest = d[0].copy()
    for c in d[1:]:
        np.maximum(deepest, c, out=deepest)
    out = np.maximum(d[0], 0.0)
    out *= out  # x ** 2 is x * x
    tmp = np.empty_like(out)
    for c in d[1:]:
        np.maximum(c, 0.0, out=tmp)
        tmp *= tmp
        out += tmp
    np.sqrt(out, out=out)
    return np.where(deepest <= 0, deepest, out)


GROUP = 8
"""collision: consecutive path samples whose surface candidates are gathered together"""


def surface_reach(layers: VolumeLayers) -> NDArray[np.float64] | None:
    """:func:`surface_voxel_reach_m` of every observed-surface point, cached on the layers until they change."""
    key = "decisions_surface_reach"
    hit = layers.cache.get(key)
    if hit is not None and hit[0] == layers.version:
        return hit[1]
    tree = surface_tree(layers)
    reach = None if tree is None else surface_voxel_reach_m(np.asarray(tree.data), layers.grid.voxel_size_m)
    layers.cache[key] = (layers.version, reach)
    return reach


def _footprint_distances(q: CollisionQuery, samples: NDArray[np.float64], tree: object | None,
                         surface: NDArray[np.float64], voxel_size_m: float,
                         reach: NDArray[np.float64] | None = None) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Per sample: the smallest signed distance from the footprint to a surface point, less how far a point measured
    in that point's voxel may lie from it (:func:`surface_voxel_reach_m`), and that point's index. Exact
    wherever it can be the path's smallest or a contact (the samples whose centre lies within the footprint's
    bounding radius of the nearest centre distance) up to :data:`MARGIN_CAP_M` beyond the footprint; elsewhere the
    lower bound ``nearest surface - bounding radius`` (with the nearest point's index)."""
    n = len(samples)
    if tree is None:
        return np.full(n, np.inf), np.full(n, -1, np.int64)
    bound = float(np.linalg.norm(q.half_extent_m))
    if reach is None:  # a measured point may lie this far from its voxel's mean
        reach = surface_voxel_reach_m(surface, voxel_size_m)
    r_max = float(reach.max())
    d_centre, nearest = tree.query(samples)
    signed = d_centre - bound - r_max
    nearest = nearest.astype(np.int64)
    need = np.flatnonzero(d_centre <= min(float(d_centre.min()), bound + MARGIN_CAP_M) + bound + r_max)
    if len(need) == 0:
        return signed, nearest
    if q.footprint == "box":
        s0, s1, s2 = (float(x) for x in 0.5 * np.asarray(q.size_m, dtype=np.float64))
    else:
        s0, s1, s2 = float(q.size_m[0]), 0.5 * float(q.size_m[1]), 0.0
    centres, radius = kq.group_balls(samples, need, GROUP, bound, r_max, d_centre, bound + MARGIN_CAP_M, surface,
                                     reach, nearest, q.footprint == "box", s0, s1, s2)
    found = tree.query_ball_point(centres, radius, return_sorted=False)  # per group, in the tree's order (as one query)
    counts = np.fromiter((len(c) for c in found), np.int64, len(found))
    cand = np.fromiter(itertools.chain.from_iterable(found), np.int64, int(counts.sum()))
    kq.group_minima(samples, need, GROUP, surface, reach, cand, np.concatenate([[0], np.cumsum(counts)]),
                    q.footprint == "box", s0, s1, s2, signed, nearest)
    return signed, nearest


def _unknown_counts(layers: VolumeLayers, q: CollisionQuery, samples: NDArray[np.float64]) -> NDArray[np.int64]:
    """Per sample, how many unknown voxels (or voxels outside the grid) the footprint overlaps (their cubes, not only
    their centres: a footprint smaller than a voxel inside unknown space is never clear): one summed-volume lookup
    per sample for a box, one per column of its cross-section for a cylinder (compiled)."""
    vs, half = layers.grid.voxel_size_m, q.half_extent_m
    lo = np.floor((samples - half) / vs).astype(np.int64)
    hi = np.floor((samples + half) / vs).astype(np.int64)
    if q.footprint == "box":
        return unknown_in_boxes(layers, lo, hi)
    o, shape = _grid_index(layers)
    return kq.unknown_in_cylinders(unknown_sat(layers), o, shape, samples, lo, hi, float(vs),
                                   float(q.size_m[0] ** 2))


def _grid_index(layers: VolumeLayers) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    return (np.asarray(layers.grid.origin_index, dtype=np.int64).reshape(3),
            np.asarray(layers.grid.shape, dtype=np.int64).reshape(3))


def unknown_in_boxes(layers: VolumeLayers, lo: NDArray[np.int64], hi: NDArray[np.int64]) -> NDArray[np.int64]:
    """Unknown voxels in lattice boxes ``lo .. hi`` (inclusive, (K, 3) each; voxels outside the grid count as
    unknown), from the summed-volume table of the unknown voxels: eight lookups per box (compiled)."""
    o, shape = _grid_index(layers)
    return kq.unknown_in_boxes(unknown_sat(layers), o, shape, np.ascontiguousarray(lo, dtype=np.int64),
                               np.ascontiguousarray(hi, dtype=np.int64))


def unknown_in_columns(layers: VolumeLayers, gx: NDArray[np.int64], gy: NDArray[np.int64],
                       z0: int | NDArray[np.int64], z1: int | NDArray[np.int64]) -> int:
    """Unknown voxels in the lattice columns ``(gx, gy)`` between lattice z ``z0 .. z1`` (inclusive; one range for
    all columns or one per column); voxels outside the grid count as unknown."""
    if len(gx) == 0:
        return 0
    z0 = np.broadcast_to(np.asarray(z0, dtype=np.int64), gx.shape)
    z1 = np.broadcast_to(np.asarray(z1, dtype=np.int64), gx.shape)
    keep = z1 >= z0
    lo = np.stack([gx, gy, z0], axis=1)[keep]
    hi = np.stack([gx, gy, z1], axis=1)[keep]
    return int(unknown_in_boxes(layers, lo, hi).sum()) if len(lo) else 0


def unknown_sat(layers: VolumeLayers) -> NDArray[np.int32]:
    """The summed-volume table of the unknown voxels (a leading zero plane on each axis): ``sat[i, j, k]`` counts
    the unknown voxels below grid index (i, j, k). Cached on the layers until they change."""
    key = "decisions_unknown_sat"
    hit = layers.cache.get(key)
    if hit is not None and hit[0] == layers.version:
        return hit[1]
    unknown = layers.state_grid() == UNKNOWN
    sat = np.zeros(tuple(n + 1 for n in unknown.shape), dtype=np.int32)
    np.cumsum(unknown, axis=0, dtype=np.int32, out=sat[1:, 1:, 1:])
    np.cumsum(sat[1:, 1:, 1:], axis=1, out=sat[1:, 1:, 1:])
    np.cumsum(sat[1:, 1:, 1:], axis=2, out=sat[1:, 1:, 1:])
    layers.cache[key] = (layers.version, sat)
    return sat


# ------------------------------------------------------------------------------------------------ explore
def explore(ctx: DecisionContext, q: ExploreQuery) -> dict:
    """The fraction of the region's voxels (centres inside it; at least the one holding its centre) that are
    unknown: ``go_look`` above ``max_unknown_fraction``, else ``known``. Margin: the threshold minus the fraction."""
    layers = ctx.layers
    vs = layers.grid.voxel_size_m
    lo = np.ceil(q.min_m / vs - 0.5).astype(np.int64)
    hi = np.floor(q.max_m / vs - 0.5).astype(np.int64)
    centre = np.floor(0.5 * (q.min_m + q.max_m) / vs).astype(np.int64)
    lo, hi = np.where(hi < lo, centre, lo), np.where(hi < lo, centre, hi)
    total = int(np.prod(hi - lo + 1))
    fraction = int(unknown_in_boxes(layers, lo[None], hi[None])[0]) / total
    margin = q.max_unknown_fraction - fraction
    decision, failure = ("go_look", "unknown_space") if margin < 0 else ("known", None)
    out = ctx.finish(decision, failure, q.min_m, q.max_m, None, ctx.frames_in_box(q.min_m, q.max_m))
    out["evidence_m"] = 0.5 * (q.min_m + q.max_m)
    out["margin"] = float(margin)
    out["details"].update(unknown_fraction=float(fraction), n_voxels=int(total))
    return out
