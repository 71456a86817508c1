"""The surface decisions' compiled selection (driftmap.kernels.regions) equals the numpy expressions it replaces, bit
for bit: the same points in the same order, the same frames."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from driftmap.kernels.regions import select_box, select_cylinder

CASES = settings(max_examples=40, deadline=None, derandomize=True)


def _points(seed: int, n: int, n_nan: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pts = rng.normal(0.0, 0.3, (n, 3))
    pts[rng.integers(0, max(n, 1), n_nan if n else 0), rng.integers(0, 3, n_nan if n else 0)] = np.nan
    return pts, rng.integers(0, 100, n).astype(np.int64)


@CASES
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 3000), n_nan=st.integers(0, 5),
       half=st.floats(0.0, 0.6))
def test_select_box_equals_the_numpy_mask(seed: int, n: int, n_nan: int, half: float) -> None:
    pts, fids = _points(seed, n, n_nan)
    centre = np.random.default_rng(seed + 1).normal(0.0, 0.2, 3)
    lo, hi = centre - half, centre + half
    if n:  # a point exactly on a face is inside (inclusive bounds)
        pts[0] = np.array([lo[0], hi[1], centre[2]])
    mask, p_in, f_in = select_box(pts, fids, lo, hi)
    want = (pts[:, 0] >= lo[0]) & (pts[:, 0] <= hi[0]) & (pts[:, 1] >= lo[1]) & (pts[:, 1] <= hi[1])
    want &= (pts[:, 2] >= lo[2]) & (pts[:, 2] <= hi[2])
    assert np.array_equal(mask, want)
    assert p_in.tobytes() == pts[want].tobytes() and np.array_equal(f_in, fids[want]) and p_in.dtype == np.float64
    assert p_in.shape == (int(want.sum()), 3) and p_in.flags.c_contiguous


@CASES
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 3000), n_nan=st.integers(0, 5), r=st.floats(0.0, 0.6))
def test_select_cylinder_equals_the_numpy_mask(seed: int, n: int, n_nan: int, r: float) -> None:
    pts, fids = _points(seed, n, n_nan)
    centre = np.random.default_rng(seed + 2).normal(0.0, 0.2, 3)
    if n:  # on the rim and on the top face: inside
        pts[0] = centre + np.array([r, 0.0, 0.0])
        if n > 1:
            pts[1] = centre + np.array([0.0, 0.0, r])
    mask, p_in, f_in = select_cylinder(pts, fids, centre, r)
    want = (np.linalg.norm(pts[:, :2] - centre[:2], axis=1) <= r) & (np.abs(pts[:, 2] - centre[2]) <= r)
    assert np.array_equal(mask, want)
    assert p_in.tobytes() == pts[want].tobytes() and np.array_equal(f_in, fids[want])
