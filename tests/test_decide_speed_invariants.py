"""What the decisions' speed-ups (issue 25) must not change: the capped neighbour count masks exactly as counting every
neighbour, the subset normals are Open3D's, the cell index returns exactly what the map view's box / ball queries
and the range cut return (the same points, in the same order), the explore frames are the frames of those points,
the per-frame medians are ``np.median``'s, and the voxel-fitted normals leave the point counts of grasp and foothold
as they were."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from driftmap.decisions import DecideConfig, decide, load_queries
from driftmap.decisions.evidence import DecisionContext, group_medians, id_ranks
from driftmap.decisions.point_index import PointIndex, in_range_mask
from driftmap.decisions.query_file import QuerySet
from driftmap.decisions.surface import _sum_along_negative, voxel_means
from driftmap.map.view import MapView
from driftmap.pipeline.build import build
from driftmap.preprocess.cloud import estimate_normals
from driftmap.sources.sevenscenes import SevenScenes
from driftmap.store.frame_store import FrameStore
from driftmap.volume import VolumeLayers

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "datasets" / "synthetic-loop"
QUERY_FILE = ROOT / "datasets" / "synthetic-loop-queries.json"
MAX_RANGE_M = 2.29


@pytest.fixture(scope="module")
def kitchen_view(sevenscenes_dir: Path) -> MapView:
    """12 overlapping 7-Scenes frames (every 80th, 160x120 pixels) with the data set's poses: real, dense points."""
    source = SevenScenes(sevenscenes_dir, pixel_stride=4, poses_from_ground_truth=True, frames="0:960:80")
    return MapView.from_frames(list(source))


def _region(view: MapView, side_m: float, seed: int) -> np.ndarray:
    pts = np.asarray(view.points_world, dtype=np.float64)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    c = pts[np.random.default_rng(seed).integers(len(pts))]
    return pts[np.all(np.abs(pts - c) <= 0.5 * side_m, axis=1)]


# ------------------------------------------------------------------------------------------------ normals
def test_the_capped_count_masks_as_the_full_count_on_real_points(kitchen_view: MapView) -> None:
    for seed in range(3):
        pts = _region(kitchen_view, 0.3, seed)
        assert len(pts) > 500
        for radius in (0.01, 0.03):
            full = cKDTree(pts).query_ball_point(pts, radius, return_length=True)
            result = estimate_normals(pts, k=64, radius_m=radius)
            np.testing.assert_array_equal(result.n_neighbors, np.minimum(full, 5))
            np.testing.assert_array_equal(np.isnan(result.normals[:, 0]), full < 5)
            some = np.arange(0, len(pts), 7)
            sub = estimate_normals(pts, k=64, radius_m=radius, at=some)
            np.testing.assert_array_equal(np.isnan(sub.normals[:, 0]), full[some] < 5)


@pytest.mark.parametrize("radius_m", [None, 0.03])
def test_normals_at_a_subset_are_open3ds(kitchen_view: MapView, radius_m: float | None) -> None:
    """``at=``: the same k nearest within the radius and the same covariance as Open3D's ``estimate_covariances``
    over the whole cloud, for the chosen points only."""
    pts = _region(kitchen_view, 0.3, 5)
    pts = np.vstack([pts, [[9.0, 9.0, 9.0]], [[9.0, 9.0, 9.001]]])  # a pair far from the rest: fewer than 3
    at = np.concatenate([np.arange(0, len(pts) - 2, 3), [len(pts) - 1]])
    whole = estimate_normals(pts, k=64, radius_m=radius_m, viewpoint=np.array([0.0, 0.0, 0.0]))
    sub = estimate_normals(pts, k=64, radius_m=radius_m, at=at)
    ok = np.isfinite(whole.normals[at, 0])
    np.testing.assert_array_equal(ok, np.isfinite(sub.normals[:, 0]))
    dots = np.einsum("ij,ij->i", whole.normals[at][ok].astype(np.float64), sub.normals[ok].astype(np.float64))
    assert np.all(dots > 1 - 1e-4)  # the same orientation (towards the origin) and direction
    np.testing.assert_allclose(sub.curvature[ok], whole.curvature[at][ok], atol=1e-4)
    assert len(estimate_normals(pts, k=64, radius_m=radius_m, at=np.zeros(0, np.int64)).normals) == 0


def test_voxel_means_hold_their_points() -> None:
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(5000, 3)) * 0.1 + [1.0, -2.0, 0.5]
    means, inv = voxel_means(pts, 0.01)
    assert inv.shape == (len(pts),) and len(means) == len(np.unique(np.floor(pts / 0.01), axis=0))
    np.testing.assert_array_equal(np.floor(means[inv] / 0.01), np.floor(pts / 0.01))  # the mean is in the voxel
    for v in rng.integers(len(means), size=20):
        np.testing.assert_allclose(means[v], pts[inv == v].mean(axis=0), atol=1e-12)


# ------------------------------------------------------------------------------------------------ the point index
def _view_box(view: MapView, lo, hi, max_range_m):
    found = view.query_box(lo, hi)
    return _cut(view, found.points_world.astype(np.float64), found.frame_ids, max_range_m)


def _cut(view: MapView, pts, fids, max_range_m):
    """The range cut ``DecisionContext`` made before the index."""
    if max_range_m is None or len(pts) == 0:
        return pts, fids
    uniq, inv = np.unique(fids, return_inverse=True)
    origins = np.stack([view.pose(int(f))[:3, 3] for f in uniq])
    keep = np.linalg.norm(pts - origins[inv], axis=1) <= max_range_m
    return pts[keep], fids[keep]


@pytest.mark.parametrize("max_range_m", [MAX_RANGE_M, None])
def test_the_index_answers_as_the_view_and_the_range_cut(kitchen_view: MapView, max_range_m: float | None) -> None:
    view = kitchen_view
    index = PointIndex.build(view, max_range_m)
    pts = np.asarray(view.points_world, dtype=np.float64)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    rng = np.random.default_rng(2)
    for n in range(60):
        c = pts[rng.integers(len(pts))]
        half = rng.uniform(0.005, 0.8, 3)
        lo, hi = c - half, c + half
        if n % 3 == 0:  # corners on cell boundaries and on points themselves (inclusive comparisons)
            lo = np.floor(lo / index.cell_m) * index.cell_m
            hi = pts[rng.integers(len(pts))].copy() if n % 2 else np.ceil(hi / index.cell_m) * index.cell_m
            lo = np.minimum(lo, hi)
        want_p, want_f = _view_box(view, lo, hi, max_range_m)
        got_p, got_f = index.box(lo, hi)
        np.testing.assert_array_equal(got_p, want_p)
        np.testing.assert_array_equal(got_f, want_f)
        np.testing.assert_array_equal(np.unique(index.frames_in_box(lo, hi)), np.unique(want_f))
        r = float(rng.uniform(0.005, 0.3))
        found = view.query_radius(c, r)
        want_p, want_f = _cut(view, found.points_world.astype(np.float64), found.frame_ids, max_range_m)
        got_p, got_f = index.ball(c, r)
        np.testing.assert_array_equal(got_p, want_p)
        np.testing.assert_array_equal(got_f, want_f)


def test_the_range_mask_is_the_norm_test() -> None:
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(10000, 3))
    rows = rng.integers(0, 4, len(pts))
    origins = rng.normal(size=(4, 3))
    want = np.linalg.norm(pts - origins[rows], axis=1) <= 1.5
    np.testing.assert_array_equal(in_range_mask(pts, rows, origins, 1.5), want)


def test_group_medians_are_np_median() -> None:
    rng = np.random.default_rng(4)
    values = np.round(rng.normal(size=3000), 2)  # ties
    groups = rng.integers(0, 40, len(values)) * 3
    got = group_medians(values, groups, 5)
    uniq, counts = np.unique(groups, return_counts=True)
    want = [np.median(values[groups == g]) for g, c in zip(uniq, counts) if c >= 5]
    np.testing.assert_array_equal(got, want)
    assert len(group_medians(values[:0], groups[:0], 5)) == 0


def test_id_ranks_are_searchsorted() -> None:
    rng = np.random.default_rng(6)
    for ids in (rng.integers(0, 50, 2000) * 7 + 3, rng.integers(0, 10**9, 300), np.array([5, 5, 5]), np.zeros(0, int)):
        uniq = np.unique(ids)
        np.testing.assert_array_equal(id_ranks(ids, uniq), np.searchsorted(uniq, ids))


def test_sum_along_negative_is_the_column_sums_sign() -> None:
    rng = np.random.default_rng(7)
    for n in (1, 2, 7, 500, 20000):
        normals = rng.normal(size=(n, 3))
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        for e in (rng.normal(size=3), normals.sum(axis=0), -normals.sum(axis=0)):
            e = e / np.linalg.norm(e)
            assert _sum_along_negative(normals, e) == (float(normals.sum(axis=0) @ e) < 0)
    pair = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])  # a sum of exactly 0: the exact expression decides
    assert not _sum_along_negative(pair, np.array([1.0, 0.0, 0.0]))


# ------------------------------------------------------------------------------------------------ decisions
@pytest.fixture(scope="module")
def gt_store(tmp_path_factory: pytest.TempPathFactory) -> FrameStore:
    out = tmp_path_factory.mktemp("speed") / "gt"
    build(LOG, out, poses_file=LOG / "groundtruth.txt", loop_closure=False)
    return FrameStore.open(out)


def test_fitting_normals_on_voxels_keeps_the_point_counts(gt_store: FrameStore) -> None:
    """Grasp and foothold count (and take their frames from) every full-resolution point whatever the normals are
    fitted on; explore's frames are those of the region's points."""
    qs = load_queries(QUERY_FILE)
    picked = QuerySet([q for q in qs if q.kind in ("grasp", "foothold")])
    layers = VolumeLayers.from_store(gt_store, gt_store.head)
    voxels = decide(gt_store, picked, layers=layers)
    every = decide(gt_store, picked, layers=layers, decide_config=DecideConfig(normal_voxel_m=None))
    assert DecideConfig().normal_voxel_m is not None
    for a, b in zip(voxels.decisions, every.decisions):
        assert a.details["n_points"] == b.details["n_points"] and a.frames == b.frames, a.id
        assert (a.decision == "too_few_points") == (b.decision == "too_few_points"), a.id
    ctx = DecisionContext(gt_store, layers.revision, layers, DecideConfig())
    for q in (q for q in qs if q.kind == "explore"):
        _, fids = ctx.points_in_box(q.min_m, q.max_m)
        np.testing.assert_array_equal(np.unique(ctx.frames_in_box(q.min_m, q.max_m)), np.unique(fids))
