"""The decisions' per-query kernels (driftmap.kernels.queries) give what the numpy expressions they replaced give, to
the bit, on random inputs (hypothesis): the footprint sweep's smallest signed distances, the unknown-voxel counts of
boxes and cylinders, the voxel means of a region. (The point index's box, ball and frames are checked against the
map view on the real 7-Scenes map in tests/test_decide_speed_invariants.py; the 1,000 benchmark decisions are
compared record for record by ``benchmarks/bench_decide.py --records / --compare``.)"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from driftmap.decisions import space
from driftmap.decisions.query_file import parse_queries
from driftmap.decisions.voxel_normals import DENSE_PER_POINT, voxel_cells
from driftmap.kernels import queries as kq
from driftmap.volume.queries import surface_voxel_reach_m

CASES = settings(max_examples=40, deadline=None, derandomize=True)


# ------------------------------------------------------------------------------------------- footprint sweep
def _reference_distances(q, samples, tree, surface, reach):
    """The sweep as it was written in numpy: per group of ``space.GROUP`` placements every surface point in the ball
    of the group (no pruning), the signed distances of ``space.footprint_signed_distances`` less the reach, the first
    smallest."""
    bound = float(np.linalg.norm(q.half_extent_m))
    r_max = float(reach.max())
    d_centre, nearest = tree.query(samples)
    signed = d_centre - bound - r_max
    nearest = nearest.astype(np.int64)
    need = np.flatnonzero(d_centre <= min(float(d_centre.min()), bound + space.MARGIN_CAP_M) + bound + r_max)
    for start in range(0, len(need), space.GROUP):
        rows = need[start:start + space.GROUP]
        centre = samples[rows].mean(axis=0)
        spread = float(np.linalg.norm(samples[rows] - centre, axis=1).max())
        within = spread + bound + r_max + min(float(d_centre[rows].max()), bound + space.MARGIN_CAP_M)
        cand = np.asarray(tree.query_ball_point(centre, within), dtype=np.int64)
        if len(cand) == 0:
            continue
        d = space.footprint_signed_distances(q, samples[rows], surface[cand])
        d -= reach[cand][None, :]
        j = np.argmin(d, axis=1)
        signed[rows] = d[np.arange(len(rows)), j]
        nearest[rows] = cand[j]
    return signed, nearest


@CASES
@given(seed=st.integers(0, 2**32 - 1), n_surface=st.integers(1, 3000), box=st.booleans(), segments=st.integers(1, 3))
def test_sweep_minima_equal_the_numpy_sweep(seed: int, n_surface: int, box: bool, segments: int) -> None:
    rng = np.random.default_rng(seed)
    voxel_m = 0.02
    # a surface of voxel means: points on a few planes, with noise, on a 2 cm lattice
    pts = rng.uniform(-1.0, 1.0, (n_surface, 3))
    pts[: n_surface // 2, 2] = np.round(rng.uniform(-0.2, 0.2)) + rng.normal(0, 0.003, n_surface // 2)
    surface = np.unique(np.floor(pts / voxel_m), axis=0) * voxel_m + rng.uniform(0.0, voxel_m, 3)
    reach = surface_voxel_reach_m(surface, voxel_m)
    tree = cKDTree(surface)
    path = np.cumsum(rng.uniform(-0.4, 0.4, (segments + 1, 3)), axis=0)
    fp = ({"box_m": rng.uniform(0.02, 0.4, 3).tolist()} if box
          else {"cylinder_m": [float(rng.uniform(0.01, 0.2)), float(rng.uniform(0.02, 0.5))]})
    q = parse_queries({"queries": [{"id": "c", "kind": "collision", "path_m": path.tolist(), "footprint": fp}]}).queries[0]
    samples, _ = space.path_samples(q.path_m, space.sweep_step(q, None, voxel_m))
    got = space._footprint_distances(q, samples, tree, surface, voxel_m, reach)
    want = _reference_distances(q, samples, tree, surface, reach)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


# ------------------------------------------------------------------------------------------- unknown voxels
def _sat(unknown: np.ndarray) -> np.ndarray:
    sat = np.zeros(tuple(n + 1 for n in unknown.shape), dtype=np.int32)
    sat[1:, 1:, 1:] = unknown.cumsum(0).cumsum(1).cumsum(2)
    return sat


def _brute_boxes(unknown: np.ndarray, origin: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Unknown voxels of each box counted voxel by voxel (outside the grid: unknown)."""
    out = []
    for a, b in zip(lo, hi):
        total = 0
        for i in range(a[0], b[0] + 1):
            for j in range(a[1], b[1] + 1):
                for k in range(a[2], b[2] + 1):
                    g = np.array([i, j, k]) - origin
                    total += 1 if np.any(g < 0) or np.any(g >= unknown.shape) else int(unknown[tuple(g)])
        out.append(total)
    return np.array(out, np.int64)


@CASES
@given(seed=st.integers(0, 2**32 - 1), n_boxes=st.integers(0, 30))
def test_unknown_in_boxes_counts_voxel_by_voxel(seed: int, n_boxes: int) -> None:
    rng = np.random.default_rng(seed)
    shape = rng.integers(1, 9, 3)
    unknown = rng.random(tuple(shape)) < rng.uniform(0.0, 1.0)
    origin = rng.integers(-5, 5, 3)
    lo = origin + rng.integers(-4, 12, (n_boxes, 3))
    hi = lo + rng.integers(-1, 6, (n_boxes, 3))  # -1: an empty box
    got = kq.unknown_in_boxes(_sat(unknown), origin, shape.astype(np.int64), lo, hi)
    np.testing.assert_array_equal(got, _brute_boxes(unknown, origin, lo, hi))


def _reference_cylinders(sat, origin, shape, samples, lo, hi, vs, radius_m):
    """The cylinder counts as they were written in numpy (candidate columns of each placement's box, the gap test,
    one summed-volume lookup per column)."""
    n = int((hi[:, :2] - lo[:, :2]).max()) + 1
    grid = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), axis=-1).reshape(-1, 2)
    cols = lo[:, None, :2] + grid[None]
    gap2 = space._gap(cols[..., 0], samples[:, None, 0], vs) ** 2 + space._gap(cols[..., 1], samples[:, None, 1], vs) ** 2
    inside = (gap2 <= radius_m ** 2) & np.all(cols <= hi[:, None, :2], axis=-1)
    which, k = np.nonzero(inside)
    boxes_lo = np.column_stack([cols[which, k], lo[which, 2]])
    boxes_hi = np.column_stack([cols[which, k], hi[which, 2]])
    counts = kq.unknown_in_boxes(sat, origin, shape, boxes_lo.astype(np.int64), boxes_hi.astype(np.int64))
    return np.bincount(which, weights=counts, minlength=len(samples)).astype(np.int64)


@CASES
@given(seed=st.integers(0, 2**32 - 1), n_samples=st.integers(1, 20))
def test_unknown_in_cylinders_equal_the_column_lookups(seed: int, n_samples: int) -> None:
    rng = np.random.default_rng(seed)
    vs = 0.02
    shape = rng.integers(2, 12, 3).astype(np.int64)
    unknown = rng.random(tuple(shape)) < rng.uniform(0.0, 1.0)
    origin = rng.integers(-5, 5, 3).astype(np.int64)
    radius, height = float(rng.uniform(0.005, 0.08)), float(rng.uniform(0.01, 0.2))
    half = np.array([radius, radius, 0.5 * height])
    samples = (origin + rng.uniform(-2, shape + 2, (n_samples, 3))) * vs
    lo = np.floor((samples - half) / vs).astype(np.int64)
    hi = np.floor((samples + half) / vs).astype(np.int64)
    sat = _sat(unknown)
    got = kq.unknown_in_cylinders(sat, origin, shape, samples, lo, hi, vs, radius ** 2)
    np.testing.assert_array_equal(got, _reference_cylinders(sat, origin, shape, samples, lo, hi, vs, radius))


# ------------------------------------------------------------------------------------------- voxel means
def _reference_voxel_cells(pts: np.ndarray, voxel_m: float):
    keys = np.floor(pts / voxel_m).astype(np.int64)
    base = keys.min(axis=0)
    keys -= base
    dims = keys.max(axis=0) + 1
    packed = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    uniq, inv = np.unique(packed, return_inverse=True)
    inv = inv.ravel()
    n = np.bincount(inv)
    means = np.stack([np.bincount(inv, weights=pts[:, k], minlength=len(n)) for k in range(3)], axis=1) / n[:, None]
    lattice = np.stack(np.unravel_index(uniq, tuple(int(d) for d in dims)), axis=1).astype(np.int64) + base
    return means, inv, lattice


@CASES
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 4000), spread=st.sampled_from([0.05, 0.5, 20.0]))
def test_voxel_cells_equal_bincount_means(seed: int, n: int, spread: float) -> None:
    """Both the dense table (a small box) and the sorted path (points spread far: more than DENSE_PER_POINT voxels
    per point) give np.unique's voxels and np.bincount's means."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(0.0, spread, (n, 3)) + rng.uniform(-100, 100, 3)
    got = voxel_cells(pts, 0.01)
    want = _reference_voxel_cells(pts, 0.01)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    assert DENSE_PER_POINT >= 1
