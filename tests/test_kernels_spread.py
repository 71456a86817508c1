"""The frame spread's compiled pass (driftmap.kernels.spread) equals the numpy expression
(driftmap.decisions.evidence.frame_spread_numpy) to a few units of rounding, on layered surfaces (frames placing a
plane at different offsets, so the spread is their separation), with a normal given or fitted; and the gather with
voxel rows (driftmap.kernels.regions) equals the map-order gather plus a lookup, exactly."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from driftmap.decisions.evidence import frame_spread_numpy
from driftmap.kernels.queries import gather_in_map_order
from driftmap.kernels.regions import gather_with_voxels
from driftmap.kernels.spread import frame_spread

CASES = settings(max_examples=40, deadline=None, derandomize=True)


def _layers(seed: int, n_frames: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points of a tilted plane, each frame's shifted along its normal by a few mm, float32 as the index holds them."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    rows = rng.integers(0, n_frames, n).astype(np.int32)
    shift = rng.uniform(-0.02, 0.02, n_frames)
    ab = rng.uniform(-0.05, 0.05, (n, 2))
    centre = rng.uniform(-3.0, 3.0, 3)
    pts = centre + ab[:, :1] * u + ab[:, 1:] * v + (shift[rows] + rng.normal(0.0, 0.001, n))[:, None] * normal
    return pts.astype(np.float32), rows, centre, normal


@CASES
@given(seed=st.integers(0, 2**32 - 1), n_frames=st.integers(1, 12), n=st.integers(0, 3000),
       min_count=st.integers(1, 40), fit=st.booleans())
def test_frame_spread_is_the_numpy_expression(seed: int, n_frames: int, n: int, min_count: int, fit: bool) -> None:
    pts32, rows, centre, normal = _layers(seed, n_frames, n)
    positions = np.random.default_rng(seed + 1).permutation(n).astype(np.int64)  # any order: the cell order
    got = frame_spread(pts32, rows, n_frames, positions, centre, np.zeros(3) if fit else normal, fit, min_count)
    frame_ids = np.arange(100, 100 + n_frames, dtype=np.int64)  # ids, not rows: the grouping is the same
    want = frame_spread_numpy(pts32.astype(np.float64), frame_ids[rows], centre, None if fit else normal, min_count)
    if want is None:
        assert np.isnan(got)
    else:
        assert abs(got - want) <= 1e-12, (got, want)
        if n_frames > 1 and min(np.bincount(rows, minlength=n_frames)) >= min_count:
            assert want > 0.0  # layered frames: the test measures a spread, not zeros


@CASES
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 2000), m=st.integers(0, 2000))
def test_gather_with_voxels_is_the_gather_and_a_lookup(seed: int, n: int, m: int) -> None:
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3)).astype(np.float32)
    order = rng.permutation(n).astype(np.int32)
    rows = rng.integers(0, 7, n).astype(np.int32)
    frame_ids = np.arange(7, dtype=np.int64) * 10
    voxel_rows = rng.integers(0, 50, n).astype(np.int32)
    positions = rng.choice(n, min(m, n), replace=False).astype(np.int64) if n else np.zeros(0, np.int64)
    pts, fids, vox = gather_with_voxels(points, order, rows, frame_ids, voxel_rows, positions)
    want_pts, want_fids = gather_in_map_order(points, order, rows, frame_ids, positions)
    assert pts.tobytes() == want_pts.tobytes() and np.array_equal(fids, want_fids)
    at = positions[np.argsort(order[positions], kind="stable")]
    assert np.array_equal(vox, voxel_rows[at])
