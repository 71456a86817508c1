"""The per-group kernels of the double-wall detector (driftmap.kernels.groups) equal, bit for bit, the numpy
expressions they replaced (np.bincount, np.minimum.at / np.maximum.at, gathers of small per-group tables), on random
groups (hypothesis); on the real 7-Scenes samples see tests/test_diagnostics.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from driftmap.kernels.groups import (
    cell_residuals,
    dot_gathered,
    group_min_max,
    group_outer_sums,
    group_row_sums,
    group_sums,
    layer_purity_counts,
    pack_coords,
    plane_cells,
    voxel_coords_bounds,
)
from driftmap.voxels import keys_on_bounding_grid, voxel_coord_columns

CASES = settings(max_examples=60, deadline=None, derandomize=True)


def _case(seed: int, n_points: int, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ids = rng.integers(0, n_groups, n_points)
    values = rng.standard_normal((3, n_points)) * rng.choice([1e-3, 1.0, 1e3], size=(3, 1))
    return ids, values


@CASES
@given(seed=st.integers(0, 2**32 - 1), n_points=st.integers(0, 3000), n_groups=st.integers(1, 400))
def test_sums_equal_bincount(seed: int, n_points: int, n_groups: int) -> None:
    ids, values = _case(seed, n_points, n_groups)
    expected = np.stack([np.bincount(ids, weights=values[k], minlength=n_groups) for k in range(3)])
    assert np.array_equal(group_row_sums(ids, n_groups, values), expected)
    assert np.array_equal(group_sums(ids, n_groups, values[1]), expected[1])
    counts = np.bincount(ids, minlength=n_groups).astype(np.float64)
    assert np.array_equal(group_sums(ids, n_groups), counts)
    outer = group_outer_sums(ids, n_groups, values)
    for a in range(3):
        for b in range(3):
            assert np.array_equal(outer[:, a, b], np.bincount(ids, weights=values[a] * values[b], minlength=n_groups))


@CASES
@given(seed=st.integers(0, 2**32 - 1), n_points=st.integers(0, 3000), n_groups=st.integers(1, 400))
def test_min_max_equal_ufunc_at(seed: int, n_points: int, n_groups: int) -> None:
    ids, values = _case(seed, n_points, n_groups)
    lo, hi = np.full(n_groups, np.inf), np.full(n_groups, -np.inf)
    np.minimum.at(lo, ids, values[0])
    np.maximum.at(hi, ids, values[0])
    got_lo, got_hi = group_min_max(ids, n_groups, values[0])
    assert np.array_equal(got_lo, lo) and np.array_equal(got_hi, hi)


@CASES
@given(seed=st.integers(0, 2**32 - 1), n_points=st.integers(0, 3000), n_groups=st.integers(1, 200),
       cell_m=st.sampled_from([0.0125, 0.025, 0.05, 0.1]))
def test_gathered_dots_and_cells_equal_numpy(seed: int, n_points: int, n_groups: int, cell_m: float) -> None:
    ids, points = _case(seed, n_points, n_groups)
    rng = np.random.default_rng(seed + 1)
    normal = rng.standard_normal((n_groups, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    u = np.cross(normal, [0.0, 0.0, 1.0])
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    v = np.cross(normal, u)
    center = rng.standard_normal((n_groups, 3))
    t = np.ascontiguousarray(normal.T)

    def from_center(axes: np.ndarray) -> np.ndarray:  # the numpy expression the kernels replaced
        ta = np.ascontiguousarray(axes.T)
        dots = points[0] * ta[0].take(ids) + points[1] * ta[1].take(ids) + points[2] * ta[2].take(ids)
        return dots - np.einsum("ij,ij->i", center, axes).take(ids)

    assert np.array_equal(dot_gathered(points, normal, ids),
                          points[0] * t[0].take(ids) + points[1] * t[1].take(ids) + points[2] * t[2].take(ids))
    k = int(math.ceil(2.0 * math.sqrt(6.0) * 0.1 / cell_m)) + 2
    along, keys = plane_cells(points, ids, normal, u, v, center, cell_m, k)
    cu = np.clip(np.floor(from_center(u) / cell_m).astype(np.int64) + k // 2, 0, k - 1)
    cv = np.clip(np.floor(from_center(v) / cell_m).astype(np.int64) + k // 2, 0, k - 1)
    assert np.array_equal(along, from_center(normal))
    assert np.array_equal(keys, (ids * k + cu) * k + cv)


@CASES
@given(seed=st.integers(0, 2**32 - 1), n_points=st.integers(0, 3000), n_cells=st.integers(1, 300),
       n_frames=st.integers(1, 40))
def test_cell_residuals_and_purity_counts_equal_numpy(seed: int, n_points: int, n_cells: int, n_frames: int) -> None:
    rng = np.random.default_rng(seed)
    c = rng.integers(0, n_cells, n_points)
    o = rng.standard_normal(n_points) * 0.01
    f = rng.integers(0, n_frames, n_points)
    # the numpy expressions of the detector before the kernels (layers._cell_residuals, layers._purity)
    c_n = np.bincount(c, minlength=n_cells).astype(np.float64)
    c_f1 = np.bincount(c, f.astype(np.float64), minlength=n_cells)
    c_f2 = np.bincount(c, f.astype(np.float64) ** 2, minlength=n_cells)
    multi = (c_f2 / np.maximum(c_n, 1) - (c_f1 / np.maximum(c_n, 1)) ** 2) > 1e-9
    r = o - np.bincount(c, o, minlength=n_cells)[c] / np.maximum(c_n[c], 1)
    got_r, got_valid = cell_residuals(c, n_cells, o, f)
    assert np.array_equal(got_r, r) and np.array_equal(got_valid, multi[c])

    n_groups = max(1, n_cells // 3)
    cell_group = rng.integers(0, n_groups, n_cells)
    g = cell_group[c]
    layer = rng.integers(-1, 2, n_points).astype(np.int8)
    shared = rng.random(n_cells) < 0.7
    mid = np.where(shared, rng.standard_normal(n_cells) * 0.01, 0.0)
    sign_sep = np.sign(rng.standard_normal(n_groups))
    expect = rng.random(n_groups)
    on_shared = shared[c] & (layer >= 0)
    sgn = np.where(layer == 1, 1.0, -1.0)
    correct = ((o - mid[c]) * sgn * sign_sep[g] > 0) & on_shared
    expected = (np.bincount(g, on_shared.astype(np.float64), minlength=n_groups),
                np.bincount(g, correct.astype(np.float64), minlength=n_groups),
                np.bincount(g, expect[g] * on_shared, minlength=n_groups))
    got = layer_purity_counts(c, g, n_groups, o, layer, shared, mid, sign_sep, expect)
    for a, b in zip(got, expected):
        assert np.array_equal(a, b)


@CASES
@given(seed=st.integers(0, 2**32 - 1), n_points=st.integers(1, 3000), size_m=st.sampled_from([0.013, 0.1, 0.2, 0.4, 1.7]))
def test_voxel_coords_and_keys_equal_numpy(seed: int, n_points: int, size_m: float) -> None:
    rng = np.random.default_rng(seed)
    columns = rng.standard_normal((3, n_points)) * rng.choice([0.01, 1.0, 50.0]) + rng.uniform(-100, 100, (3, 1))
    coords, lo, hi = voxel_coords_bounds(columns, size_m)
    expected = voxel_coord_columns(columns, size_m)
    assert all(np.array_equal(coords[a], expected[a]) for a in range(3))
    keys, grid = keys_on_bounding_grid(expected)
    assert grid.lo == tuple(lo) and grid.hi == tuple(hi)
    assert np.array_equal(pack_coords(coords, grid.lo, grid.span), keys)
    single = columns.astype(np.float32)  # divided in float32, as numpy does
    coords, lo, hi = voxel_coords_bounds(single, size_m)
    expected = voxel_coord_columns(single, size_m)
    assert all(np.array_equal(coords[a], expected[a]) for a in range(3))
    columns[1, n_points // 2] = np.nan
    assert voxel_coords_bounds(columns, size_m) is None


def test_bad_ids_and_shapes_raise() -> None:
    ids = np.array([0, 3, 1])
    with pytest.raises(IndexError):
        group_sums(ids, 3, np.ones(3))
    with pytest.raises(IndexError):
        group_row_sums(np.array([-1, 0, 1]), 3, np.ones((2, 3)))
    with pytest.raises(IndexError):
        group_sums(ids, 2)
    with pytest.raises(ValueError, match="weights must be"):
        group_row_sums(ids, 4, np.ones((2, 4)))
    with pytest.raises(ValueError, match="finite"):
        group_min_max(ids, 4, np.array([0.0, np.nan, 1.0]))

