"""One voxel-key implementation (driftmap.voxels): the map, the viewer and the diagnostics give the same voxels
and ids on the same real points, keys round-trip, sort like (x, y, z), and a grid that cannot hold the
coordinates raises instead of wrapping."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from driftmap import viewer
from driftmap.diagnostics.surfaces import voxel_ids
from driftmap.errors import ConfigError, GeometryError
from driftmap.map.view import MapView
from driftmap.sources.sevenscenes import SevenScenes
from driftmap.store.frame_store import FrameStore
from driftmap.voxels import (
    ABSOLUTE_GRID,
    ABSOLUTE_HALF_RANGE,
    VoxelGrid,
    dense_ids,
    first_per_key,
    first_point_per_voxel,
    random_per_key,
    voxel_coords,
    voxel_keys,
    voxel_means,
)

VOXEL_M = 0.05


@pytest.fixture(scope="module")
def few_frames(tmp_path_factory: pytest.TempPathFactory, sevenscenes_dir: Path) -> FrameStore:
    """Five real 7-Scenes frames (160x120 pixels) with the data set's poses."""
    path = tmp_path_factory.mktemp("voxels") / "store"
    source = SevenScenes(sevenscenes_dir, pixel_stride=4, poses_from_ground_truth=True, frames="0:250:50")
    with FrameStore.create(path) as store:
        for frame in source:
            store.append(frame)
    return FrameStore.open(path)


def _reference_ids(points: np.ndarray, size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Independent of driftmap.voxels: numpy's row-wise unique of the float voxel coordinates."""
    coords, inverse = np.unique(np.floor(points / size_m).astype(np.int64), axis=0, return_inverse=True)
    return coords, inverse.ravel()


def test_map_viewer_and_diagnostics_give_the_same_voxels_and_ids_on_real_points(few_frames: FrameStore) -> None:
    view = MapView.from_store(few_frames, 0)
    pts = view.points_world
    pts = pts[np.isfinite(pts).all(axis=1)]
    ref_coords, ref_ids = _reference_ids(pts, VOXEL_M)
    assert 1000 < len(ref_coords) < len(pts)

    # the three callers' keys on the same (float32) points: the map's bounding grid, the viewer's absolute grid,
    # the diagnostics' (3, N) columns; all give numpy's lexicographic ids
    map_ids, map_keys = dense_ids(voxel_keys(pts, VOXEL_M))
    abs_ids, abs_keys = dense_ids(voxel_keys(pts, VOXEL_M, grid=ABSOLUTE_GRID))
    diag_ids, diag_keys, grid = voxel_ids(np.ascontiguousarray(pts.T), VOXEL_M)
    for ids in (map_ids, abs_ids, diag_ids):
        np.testing.assert_array_equal(ids, ref_ids)
    np.testing.assert_array_equal(grid.unpack(diag_keys), ref_coords)
    np.testing.assert_array_equal(ABSOLUTE_GRID.unpack(abs_keys), ref_coords)
    assert len(map_keys) == len(ref_coords)

    # the map's per-frame voxel sets (change sets) are the distinct voxels of each frame, in key order
    for row, fid in enumerate(view.frame_ids):
        p = view.frame_points_world(int(fid))
        p = p[np.isfinite(p).all(axis=1)]
        np.testing.assert_array_equal(view._voxels(row, VOXEL_M), _reference_ids(p, VOXEL_M)[0])

    # the map's fused export: one centroid per voxel, the mean of exactly that voxel's points
    fused = view.fused(VOXEL_M)
    means = voxel_means(pts, VOXEL_M)
    assert len(fused.points_world) == len(ref_coords)
    np.testing.assert_array_equal(fused.points_world, means.centroids_m.astype(np.float32))
    np.testing.assert_array_equal(means.mean_of(pts), means.centroids_m)
    assert means.counts.sum() == len(pts) and np.array_equal(means.point_voxel, ref_ids)
    np.testing.assert_array_equal(np.diff(fused.provenance_offsets) >= 1, np.ones(len(ref_coords), bool))

    # the viewer: one real point per occupied voxel, every voxel exactly once
    shown, frame_ids, n_map = viewer._downsample(few_frames, 0, VOXEL_M, max_points=10**9, seed=0)
    assert n_map == view.n_points and len(shown) == len(ref_coords)
    np.testing.assert_array_equal(np.unique(voxel_coords(shown, VOXEL_M), axis=0), ref_coords)
    assert set(np.unique(frame_ids)) <= set(view.frame_ids.tolist())


def test_keys_round_trip_and_sort_like_coordinates_with_negative_coordinates() -> None:
    rng = np.random.default_rng(0)
    coords = rng.integers(-5000, 5000, size=(20_000, 3)).astype(np.int64)
    coords[:3] = [[-1, -1, -1], [0, 0, 0], [-5000, 4999, -1]]
    bounding = VoxelGrid.around(coords)
    assert bounding.lo == (-5000, -5000, -5000) and bounding.hi == tuple(int(v) for v in coords.max(axis=0))
    for grid in (bounding, ABSOLUTE_GRID):
        keys = grid.pack(coords)
        np.testing.assert_array_equal(grid.unpack(keys), coords)
        lexical = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0]))
        np.testing.assert_array_equal(np.sort(keys), keys[lexical])
    # the absolute grid is the documented 21-bit layout, so keys compare across calls and chunks
    k = coords + ABSOLUTE_HALF_RANGE
    np.testing.assert_array_equal(ABSOLUTE_GRID.pack(coords), (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2])
    # the bounding grid numbers its voxels from 0 at the lower corner: the keys are small and non-negative
    assert bounding.pack(np.array([bounding.lo])).tolist() == [0] and voxel_keys(coords).min() >= 0


def test_voxel_coordinates_floor_negative_points_and_keep_the_points_dtype() -> None:
    p = np.array([[-0.01, -1e-9, 0.0], [0.0999, 0.1, -0.1]], np.float64)
    np.testing.assert_array_equal(voxel_coords(p, 0.1), [[-1, -1, 0], [0, 1, -1]])
    # float32 points are divided in float32 (what the map and the viewer always did): 0.7f / 0.1 is 7 in float32
    # and 6.99.. in float64; the map's change sets and the viewer must agree with the map's own float32 voxels
    p32 = np.array([[0.7, 1.4, 0.0]], np.float32)
    np.testing.assert_array_equal(voxel_coords(p32, 0.1), [[7, 14, 0]])
    np.testing.assert_array_equal(voxel_coords(p32.astype(np.float64), 0.1), [[6, 13, 0]])
    with pytest.raises(ConfigError):
        voxel_coords(p, 0.0)
    with pytest.raises(ConfigError):
        voxel_coords(p, float("inf"))


def test_coordinates_outside_the_key_range_raise_instead_of_wrapping() -> None:
    h = ABSOLUTE_HALF_RANGE
    inside = np.array([[-h, h - 1, 0], [h - 1, -h, 7]], np.int64)
    np.testing.assert_array_equal(ABSOLUTE_GRID.unpack(ABSOLUTE_GRID.pack(inside)), inside)
    for outside in ([h, 0, 0], [0, -h - 1, 0], [0, 0, 2 * h]):
        with pytest.raises(ConfigError, match="leave the key grid"):
            ABSOLUTE_GRID.pack(np.array([outside, [0, 0, 0]], np.int64))
    # far points on the absolute grid (the viewer's): a typed error naming the caller, not a wrapped key
    far = np.array([[0.0, 0.0, 0.0], [0.1 * h + 1.0, 0.0, 0.0]])
    with pytest.raises(ConfigError, match="view"):
        voxel_keys(far, 0.1, grid=ABSOLUTE_GRID, what="view")
    # a bounding grid of 2**62 voxels or more (the map's and the diagnostics'): refused as well
    huge = np.array([[0.0, 0.0, 0.0], [1e6, 1e6, 1e6]])
    with pytest.raises(ConfigError, match="too large"):
        voxel_keys(huge, 1e-3)
    with pytest.raises(ConfigError, match="too large"):
        voxel_keys(huge, 1e-3)
    # a non-finite point has no voxel (the cast would give an arbitrary integer on some platforms)
    for bad in (np.nan, np.inf):
        with pytest.raises(GeometryError, match="1 points are not finite"):
            voxel_keys(np.array([[0.0, 0.0, 0.0], [bad, 0.0, 0.0]]), 0.1, grid=ABSOLUTE_GRID)
        with pytest.raises(GeometryError, match="not finite"):
            voxel_ids(np.array([[0.0, bad], [0.0, 0.0], [0.0, 0.0]]), 0.1)


@pytest.mark.parametrize("span", [50, 1 << 40], ids=["bitmap", "sort"])
def test_dense_ids_and_first_per_key_equal_numpy_unique(span: int) -> None:
    rng = np.random.default_rng(1)
    keys = rng.integers(0, span, 5000).astype(np.int64)
    ids, uniq = dense_ids(keys)
    ref_uniq, ref_first, ref_inverse = np.unique(keys, return_index=True, return_inverse=True)
    np.testing.assert_array_equal(uniq, ref_uniq)
    np.testing.assert_array_equal(ids, ref_inverse)
    np.testing.assert_array_equal(first_per_key(keys), ref_first)
    # negative keys take the sorting path (a bitmap cannot index them)
    ids_neg, uniq_neg = dense_ids(keys - span // 2)
    np.testing.assert_array_equal(ids_neg, ref_inverse)
    np.testing.assert_array_equal(uniq_neg, ref_uniq - span // 2)
    pick = random_per_key(keys, np.random.default_rng(2))
    np.testing.assert_array_equal(np.sort(keys[pick]), ref_uniq)
    assert dense_ids(np.zeros(0, np.int64))[0].size == 0 and first_per_key(np.zeros(0, np.int64)).size == 0


def test_first_point_per_voxel_keeps_the_first_real_point_of_every_voxel(few_frames: FrameStore) -> None:
    pts = MapView.from_store(few_frames, 0).points_world
    pts = pts[np.isfinite(pts).all(axis=1)]
    first = first_point_per_voxel(pts, VOXEL_M)
    _, ref_first = np.unique(np.floor(pts / VOXEL_M).astype(np.int64), axis=0, return_index=True)
    np.testing.assert_array_equal(first, np.sort(ref_first))
    assert first_point_per_voxel(np.zeros((0, 3), np.float32), VOXEL_M).size == 0
