"""Depth validation and back-projection: real 7-Scenes frames against Open3D, worked examples, invalid-pixel
accounting, the depth-scale unit mistake, intrinsics errors, the invalid-fraction monitor and depth_frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import driftmap
from driftmap import (
    BackprojectionResult,
    DepthScaleError,
    Frame,
    IntrinsicsError,
    InvalidFractionMonitor,
    InvalidReason,
    PinholeIntrinsics,
    PoseEstimate,
    PoseSource,
    Provenance,
    SensorKind,
    backproject,
    depth_frame,
)

# 7-Scenes (Kinect v1) depth camera
FX = FY = 585.0
CX, CY = 320.0, 240.0
W, H = 640, 480
SEVENSCENES_INTR = PinholeIntrinsics(fx=FX, fy=FY, cx=CX, cy=CY, width=W, height=H)
TINY_MIN_M = 1e-6  # Open3D has no lower bound: every code > 0 is kept

# frames 0, 250, 640, 999 are the spread of the sequence; 33 and 850 carry 65535 "no reading" pixels
REAL_FRAMES = (0, 250, 640, 999, 33, 850)
ALL_REASONS = {r.value for r in InvalidReason}


def read_depth(sevenscenes_dir: Path, index: int) -> np.ndarray:
    depth = np.asarray(o3d.io.read_image(str(sevenscenes_dir / f"frame-{index:06d}.depth.png")))
    assert depth.dtype == np.uint16 and depth.shape == (H, W)
    return depth


def counts_of(result: BackprojectionResult) -> dict[str, int]:
    """Counts for every reason (missing keys mean 0); all keys must be InvalidReason values."""
    assert set(result.invalid_counts) <= ALL_REASONS, result.invalid_counts
    return {reason: int(result.invalid_counts.get(reason, 0)) for reason in ALL_REASONS}


def expected(**counts: int) -> dict[str, int]:
    out = {reason: 0 for reason in ALL_REASONS}
    for key, value in counts.items():
        out[InvalidReason[key].value] = value
    return out


def open3d_points(depth: np.ndarray, intr: PinholeIntrinsics, depth_scale: float, depth_trunc: float) -> np.ndarray:
    o3d_intr = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
    pcd = o3d.geometry.PointCloud.create_from_depth_image(
        o3d.geometry.Image(np.ascontiguousarray(depth)), o3d_intr, depth_scale=depth_scale, depth_trunc=depth_trunc
    )
    return np.asarray(pcd.points)


# --------------------------------------------------------------------------------------------------------------
# 1. real frames against Open3D, and per-reason counts against numpy
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("index", REAL_FRAMES)
@pytest.mark.parametrize("max_depth_m", [2.0, 2.2, 3.0, 10.0])
def test_real_frame_matches_open3d_point_for_point(sevenscenes_dir: Path, index: int, max_depth_m: float) -> None:
    depth = read_depth(sevenscenes_dir, index)
    result = backproject(depth, SEVENSCENES_INTR, depth_scale=1000, min_depth_m=TINY_MIN_M, max_depth_m=max_depth_m)
    reference = open3d_points(depth, SEVENSCENES_INTR, 1000.0, max_depth_m)

    assert result.points.dtype == np.float32 and result.points.ndim == 2 and result.points.shape[1] == 3
    assert result.n_valid == len(reference) > 0
    # same order, same points
    np.testing.assert_allclose(result.points.astype(np.float64), reference, rtol=0, atol=1e-6)
    # invalid pixels excluded identically: the kept pixels are exactly those Open3D keeps (0 < z < trunc)
    z = depth.astype(np.float32).ravel() / np.float32(1000.0)
    o3d_kept = np.flatnonzero((z > 0) & (z.astype(np.float64) < max_depth_m))
    np.testing.assert_array_equal(result.pixel_index, o3d_kept)
    assert result.depth_scale == 1000.0


@pytest.mark.parametrize("index", REAL_FRAMES)
@pytest.mark.parametrize("max_depth_m", [2.0, 3.0])
def test_real_frame_counts_per_reason_match_numpy(sevenscenes_dir: Path, index: int, max_depth_m: float) -> None:
    depth = read_depth(sevenscenes_dir, index)
    result = backproject(depth, SEVENSCENES_INTR, depth_scale=1000, min_depth_m=TINY_MIN_M, max_depth_m=max_depth_m)
    n_zero = int(np.count_nonzero(depth == 0))
    n_65535 = int(np.count_nonzero(depth == 65535))
    n_beyond = int(np.count_nonzero((depth >= round(max_depth_m * 1000)) & (depth != 65535)))
    assert counts_of(result) == expected(ZERO=n_zero, NO_READING_65535=n_65535, BEYOND_MAX=n_beyond)
    assert n_zero > 0
    if max_depth_m == 2.0:
        assert n_beyond > 0  # every frame here sees something beyond 2 m
    if index in (33, 850):
        assert n_65535 > 0
    assert result.n_pixels == W * H
    assert sum(result.invalid_counts.values()) + result.n_valid == W * H
    assert result.invalid_fraction == pytest.approx((n_zero + n_65535 + n_beyond) / (W * H))


@pytest.mark.parametrize("max_depth_m", [0.5, 2.2, 3.3, 4.1, 10.0])
def test_every_uint16_code_truncates_like_open3d(max_depth_m: float) -> None:
    """All 65536 codes in one image: the kept set and points agree with Open3D's depth_trunc exactly.

    3.3 and 4.1 are not representable in float32 (they round down), which is where a float32 comparison
    against ``float32(max_depth_m)`` and Open3D's float-vs-double comparison can part ways.
    """
    depth = np.arange(65536, dtype=np.uint16).reshape(256, 256)
    intr = PinholeIntrinsics(fx=300.0, fy=310.0, cx=127.5, cy=120.0, width=256, height=256)
    result = backproject(depth, intr, depth_scale=1000, min_depth_m=TINY_MIN_M, max_depth_m=max_depth_m,
                         check_scale=False)
    reference = open3d_points(depth, intr, 1000.0, max_depth_m)
    kept_codes = depth.ravel()[result.pixel_index]
    o3d_codes = np.rint(reference[:, 2] * 1000).astype(np.int64)
    assert result.n_valid == len(reference), (
        f"max_depth_m={max_depth_m}: driftmap keeps codes {kept_codes.min()}..{kept_codes.max()}, "
        f"Open3D keeps {o3d_codes.min()}..{o3d_codes.max()}"
    )
    np.testing.assert_allclose(result.points.astype(np.float64), reference, rtol=0, atol=1e-6)


# --------------------------------------------------------------------------------------------------------------
# 2. worked examples
# --------------------------------------------------------------------------------------------------------------


def test_worked_example_2x2() -> None:
    depth = np.array([[1.0, 1.2], [0.9, 1.1]], dtype=np.float32)
    intr = PinholeIntrinsics(fx=500, fy=500, cx=0.5, cy=0.5, width=2, height=2)
    result = backproject(depth, intr)  # float metres, plausible ~1 m: the scale check passes on its own
    expected_points = np.array(
        [[-0.001, -0.001, 1.0], [0.0012, -0.0012, 1.2], [-0.0009, 0.0009, 0.9], [0.0011, 0.0011, 1.1]]
    )
    assert result.points.shape == (4, 3)
    np.testing.assert_array_equal(np.round(result.points.astype(np.float64), 4), expected_points)
    np.testing.assert_array_equal(result.pixel_index, [0, 1, 2, 3])
    assert result.depth_scale is None  # float images are metres already


def test_worked_example_2x2_uint16_millimetres_gives_same_points() -> None:
    depth_mm = np.array([[1000, 1200], [900, 1100]], dtype=np.uint16)
    intr = PinholeIntrinsics(fx=500, fy=500, cx=0.5, cy=0.5, width=2, height=2)
    result = backproject(depth_mm, intr, depth_scale=1000)
    np.testing.assert_allclose(
        result.points,
        [[-0.001, -0.001, 1.0], [0.0012, -0.0012, 1.2], [-0.0009, 0.0009, 0.9], [0.0011, 0.0011, 1.1]],
        rtol=0, atol=1e-6,
    )
    assert result.depth_scale == 1000.0


def test_worked_example_single_pixel_720p() -> None:
    depth = np.zeros((720, 1280), dtype=np.float32)
    depth[200, 640] = 2.0  # row v=200, column u=640
    intr = PinholeIntrinsics(fx=600, fy=600, cx=640, cy=360, width=1280, height=720)
    result = backproject(depth, intr)
    assert result.n_valid == 1
    assert result.pixel_index.tolist() == [200 * 1280 + 640]
    np.testing.assert_array_equal(np.round(result.points[0].astype(np.float64), 3), [0.0, -0.533, 2.0])
    np.testing.assert_allclose(result.points[0], [0.0, -160.0 / 600.0 * 2.0, 2.0], rtol=0, atol=1e-6)
    assert counts_of(result) == expected(ZERO=1280 * 720 - 1)


# --------------------------------------------------------------------------------------------------------------
# 3. invalid-pixel accounting
# --------------------------------------------------------------------------------------------------------------


def _float_image(dtype: type) -> tuple[np.ndarray, int]:
    values = (
        [np.nan] * 3
        + [np.inf] * 2
        + [-np.inf] * 4
        + [0.0] * 4 + [-0.0]
        + [-0.5, -1.0, -2.0, -1e-3, -30.0, -4.0]
        + [1e-4, 0.01, 0.1, 0.2, 0.3, 0.4, 0.4999]  # below min 0.5
        + [4.0, 4.0001, 5.0, 10.0, 100.0, 1e4, 65.535, 4.5]  # at/beyond max 4.0 (exclusive)
        + [0.5, 0.5001, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 3.999]  # valid, including z == min
    )
    n_valid = 9
    rng = np.random.default_rng(7)
    arr = np.array(values, dtype=dtype)
    rng.shuffle(arr)
    return arr.reshape(4, 11), n_valid


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float_image_counts_per_reason(dtype: type) -> None:
    depth, n_valid = _float_image(dtype)
    intr = PinholeIntrinsics(fx=100, fy=100, cx=5.0, cy=1.5, width=11, height=4)
    result = backproject(depth, intr, min_depth_m=0.5, max_depth_m=4.0, check_scale=False)
    assert counts_of(result) == expected(NAN=3, INF=6, ZERO=5, NEGATIVE=6, BELOW_MIN=7, BEYOND_MAX=8)
    assert result.n_valid == n_valid
    assert sum(result.invalid_counts.values()) + result.n_valid == result.n_pixels == 44
    z = result.points[:, 2]
    assert np.all((z >= np.float32(0.5)) & (z < np.float32(4.0)))
    assert np.all(np.isfinite(result.points))
    # the points are the valid pixels, in row-major order
    np.testing.assert_array_equal(z, depth.ravel()[result.pixel_index].astype(np.float32))
    assert np.all(np.diff(result.pixel_index) > 0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float_image_min_depth_zero_still_rejects_zero(dtype: type) -> None:
    depth = np.array([[0.0, 1e-3, 1.0, 2.0]], dtype=dtype)
    intr = PinholeIntrinsics(fx=100, fy=100, cx=1.5, cy=0.0, width=4, height=1)
    result = backproject(depth, intr, min_depth_m=0.0, max_depth_m=5.0, check_scale=False)
    assert counts_of(result) == expected(ZERO=1)
    assert result.pixel_index.tolist() == [1, 2, 3]


def test_float64_values_outside_float32_range_keep_their_reason() -> None:
    """A float64 image is metres as given: a finite 1e300 m is beyond max (not inf), -1e300 is negative
    (not inf), and 1e-300 m is below min (not zero)."""
    depth = np.array([[1e300, -1e300, 1e-300, 1.0]], dtype=np.float64)
    intr = PinholeIntrinsics(fx=100, fy=100, cx=1.5, cy=0.0, width=4, height=1)
    result = backproject(depth, intr, min_depth_m=0.1, max_depth_m=10.0, check_scale=False)
    assert counts_of(result) == expected(BEYOND_MAX=1, NEGATIVE=1, BELOW_MIN=1)
    assert result.n_valid == 1


def test_uint16_counts_per_reason() -> None:
    codes = (
        [0] * 5
        + [65535] * 4
        + [1, 50, 99, 100 - 1]  # below 0.1 m at 1000/m
        + [4000, 4001, 5000, 65534, 20000, 60000]  # at/beyond 4.0 m
        + [100, 101, 1000, 2500, 3999]  # valid, including z == min
    )
    depth = np.array(codes, dtype=np.uint16).reshape(4, 6)
    intr = PinholeIntrinsics(fx=100, fy=100, cx=2.5, cy=1.5, width=6, height=4)
    result = backproject(depth, intr, depth_scale=1000, min_depth_m=0.1, max_depth_m=4.0, check_scale=False)
    assert counts_of(result) == expected(ZERO=5, NO_READING_65535=4, BELOW_MIN=4, BEYOND_MAX=6)
    assert result.n_valid == 5
    np.testing.assert_allclose(result.points[:, 2], [0.1, 0.101, 1.0, 2.5, 3.999], rtol=0, atol=1e-7)
    assert sum(result.invalid_counts.values()) + result.n_valid == 24


_SCALES = st.sampled_from([1000.0, 4000.0, 5000.0])
# thresholds on a 1/8 m grid: exact in float32 and an integer number of codes at every scale above
_EIGHTHS = st.integers(min_value=0, max_value=8 * 12)


@settings(max_examples=150, deadline=None)
@given(
    depth=hnp.arrays(
        np.uint16,
        hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=12),
        elements=st.one_of(
            st.sampled_from([0, 65535]),
            st.integers(0, 65535),
            st.integers(0, 15000),
        ),
    ),
    scale=_SCALES,
    lo_hi=st.tuples(_EIGHTHS, _EIGHTHS).filter(lambda t: t[0] < t[1]),
    fx=st.floats(50, 1500),
    fy=st.floats(50, 1500),
    cx=st.floats(-5, 15),
    cy=st.floats(-5, 15),
)
def test_uint16_property(depth: np.ndarray, scale: float, lo_hi: tuple[int, int], fx: float, fy: float, cx: float,
                         cy: float) -> None:
    min_m, max_m = lo_hi[0] / 8.0, lo_hi[1] / 8.0
    h, w = depth.shape
    intr = PinholeIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h)
    result = backproject(depth, intr, depth_scale=scale, min_depth_m=min_m, max_depth_m=max_m, check_scale=False)

    code = depth.astype(np.int64)
    lo_code, hi_code = round(min_m * scale), round(max_m * scale)
    sentinel = code == 65535
    zero = code == 0
    below = ~zero & ~sentinel & (code < lo_code)
    beyond = ~sentinel & (code >= hi_code) & ~zero
    valid = ~(zero | sentinel | below | beyond)
    assert counts_of(result) == expected(ZERO=int(zero.sum()), NO_READING_65535=int(sentinel.sum()),
                                         BELOW_MIN=int(below.sum()), BEYOND_MAX=int(beyond.sum()))
    assert sum(result.invalid_counts.values()) + result.n_valid == depth.size
    np.testing.assert_array_equal(result.pixel_index, np.flatnonzero(valid))

    z = result.points[:, 2].astype(np.float64)
    assert np.all((z >= min_m - 1e-6) & (z < max_m))
    v, u = np.divmod(result.pixel_index, w)
    z_ref = code.ravel()[result.pixel_index] / scale
    rays = np.linalg.inv(intr.K) @ np.stack([u, v, np.ones_like(u)]).astype(np.float64)
    reference = (rays * z_ref).T
    np.testing.assert_allclose(result.points.astype(np.float64), reference, rtol=2e-6, atol=1e-6)


# --------------------------------------------------------------------------------------------------------------
# 4. the depth-scale unit mistakes
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("index", [0, 640])
def test_millimetres_read_with_scale_one_raises(sevenscenes_dir: Path, index: int) -> None:
    depth = read_depth(sevenscenes_dir, index)
    with pytest.raises(DepthScaleError) as info:
        backproject(depth, SEVENSCENES_INTR, depth_scale=1.0)
    err = info.value
    assert err.depth_scale_used == 1.0
    assert err.depth_scale_suggested == 1000.0
    message = str(err)
    assert "depth_scale=1 " in message or "depth_scale=1.0" in message  # names the scale used
    assert "1000" in message  # and suggests the right one


def test_depth_frame_scale_error_names_the_frame(sevenscenes_dir: Path) -> None:
    depth = read_depth(sevenscenes_dir, 250)
    prov = Provenance(str(sevenscenes_dir / "frame-000250.depth.png"), 250)
    with pytest.raises(DepthScaleError, match="frame 250") as info:
        depth_frame(depth, SEVENSCENES_INTR, frame_id=250, stamp_ns=0, pose=PoseEstimate(np.eye(4)),
                    depth_scale=1.0, provenance=prov)
    assert info.value.depth_scale_suggested == 1000.0
    assert "frame-000250.depth.png" in str(info.value)


def test_correct_scale_does_not_raise_and_huge_scale_does(sevenscenes_dir: Path) -> None:
    depth = read_depth(sevenscenes_dir, 0)
    backproject(depth, SEVENSCENES_INTR, depth_scale=1000.0)  # no error
    with pytest.raises(DepthScaleError) as info:
        backproject(depth, SEVENSCENES_INTR, depth_scale=1e6)  # scene at ~2 mm
    assert info.value.depth_scale_used == 1e6
    assert info.value.depth_scale_suggested == 1000.0
    # the check is not hidden by max_depth_m: a wrong scale raises even if the range would reject everything
    with pytest.raises(DepthScaleError):
        backproject(depth, SEVENSCENES_INTR, depth_scale=1.0, max_depth_m=5.0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_millimetres_in_float_image_raises(sevenscenes_dir: Path, dtype: type) -> None:
    depth_mm = read_depth(sevenscenes_dir, 999).astype(dtype)  # float holding millimetres
    depth_mm[depth_mm == 65535] = 0
    with pytest.raises(DepthScaleError) as info:
        backproject(depth_mm, SEVENSCENES_INTR)
    err = info.value
    assert err.depth_scale_used == 1.0
    assert err.depth_scale_suggested == 1000.0
    assert "1000" in str(err) and "metres" in str(err)
    # the same image divided by 1000 is fine and equals the uint16 path
    from_float = backproject(depth_mm / 1000.0, SEVENSCENES_INTR)
    from_uint16 = backproject(read_depth(sevenscenes_dir, 999), SEVENSCENES_INTR, depth_scale=1000)
    np.testing.assert_array_equal(from_float.pixel_index, from_uint16.pixel_index)
    np.testing.assert_allclose(from_float.points, from_uint16.points, rtol=0, atol=1e-6)


def test_non_positive_depth_scale_raises() -> None:
    depth = np.full((2, 2), 1000, dtype=np.uint16)
    intr = PinholeIntrinsics(fx=500, fy=500, cx=0.5, cy=0.5, width=2, height=2)
    for bad in (0.0, -1000.0, float("nan")):
        with pytest.raises(DepthScaleError):
            backproject(depth, intr, depth_scale=bad)


# --------------------------------------------------------------------------------------------------------------
# 5. intrinsics
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "width, height",
    [(320, 240), (480, 640), (640, 481), (641, 480)],
)
def test_intrinsics_size_mismatch_raises(sevenscenes_dir: Path, width: int, height: int) -> None:
    depth = read_depth(sevenscenes_dir, 0)
    intr = PinholeIntrinsics(fx=FX, fy=FY, cx=CX, cy=CY, width=width, height=height)
    with pytest.raises(IntrinsicsError, match=f"{width}x{height}"):
        backproject(depth, intr, depth_scale=1000)
    with pytest.raises(IntrinsicsError):
        depth_frame(depth, intr, frame_id=0, stamp_ns=0, pose=PoseEstimate(np.eye(4)))


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(fx=0.0), "fx"),
        (dict(fx=-585.0), "fx"),
        (dict(fy=0.0), "fy"),
        (dict(fy=-1e-9), "fy"),
        (dict(fx=float("nan")), "fx"),
        (dict(cy=float("inf")), "cy"),
        (dict(width=0), "width"),
        (dict(height=-480), "height"),
    ],
)
def test_invalid_intrinsics_raise(kwargs: dict, field: str) -> None:
    params = dict(fx=FX, fy=FY, cx=CX, cy=CY, width=W, height=H) | kwargs
    with pytest.raises(IntrinsicsError, match=field):
        PinholeIntrinsics(**params)


@pytest.mark.parametrize("stride", [0, -2, 1.5])
def test_a_bad_pixel_stride_is_an_intrinsics_error(stride: float) -> None:
    depth = np.full((H, W), 1500, np.uint16)
    with pytest.raises(IntrinsicsError, match=rf"pixel stride must be a positive integer, got {stride}"):
        depth_frame(depth, SEVENSCENES_INTR, frame_id=0, stamp_ns=0, depth_scale=1000.0,
                    pose=PoseEstimate(np.eye(4)), pixel_stride=stride)


def test_intrinsics_error_is_a_driftmap_error() -> None:
    assert issubclass(IntrinsicsError, driftmap.GeometryError)
    assert issubclass(DepthScaleError, driftmap.DepthError)
    assert issubclass(driftmap.TransformError, driftmap.GeometryError)


# --------------------------------------------------------------------------------------------------------------
# 7. invalid-fraction monitor
# --------------------------------------------------------------------------------------------------------------


def test_monitor_flags_jump_and_not_fluctuation() -> None:
    rng = np.random.default_rng(3)
    monitor = InvalidFractionMonitor()
    normal = np.clip(0.1 + rng.normal(0.0, 0.015, size=40), 0.0, 1.0)
    flagged = [monitor.update(float(f), f"frame {i}") for i, f in enumerate(normal)]
    assert flagged == [None] * len(normal)
    reason = monitor.update(0.6, "frame 40")
    assert reason is not None and "0.600" in reason
    # back to normal afterwards: not flagged
    assert monitor.update(0.11, "frame 41") is None
    assert monitor.update(0.13, "frame 42") is None


def test_monitor_needs_history_and_uses_recent_median() -> None:
    monitor = InvalidFractionMonitor(window=30, min_history=5, min_jump=0.15)
    # a high value with too little history is not flagged
    for f in (0.1, 0.1, 0.1, 0.1):
        assert monitor.update(f) is None
    assert monitor.update(0.9) is None  # only 4 frames of history
    monitor = InvalidFractionMonitor(window=30, min_history=5, min_jump=0.15)
    for _ in range(10):
        monitor.update(0.1)
    assert monitor.update(0.24) is None  # below median + min_jump
    assert monitor.update(0.26) is not None  # above it
    # a slowly drifting level is followed, not flagged
    monitor = InvalidFractionMonitor(window=10, min_history=5, min_jump=0.15)
    assert [monitor.update(0.1 + 0.01 * i) for i in range(50)] == [None] * 50


def test_monitor_through_depth_frame_on_real_frames(sevenscenes_dir: Path) -> None:
    monitor = InvalidFractionMonitor(min_history=5)
    pose = PoseEstimate(np.eye(4))
    for i in range(0, 60, 6):
        frame = depth_frame(read_depth(sevenscenes_dir, i), SEVENSCENES_INTR, frame_id=i, stamp_ns=i,
                            pose=pose, monitor=monitor)
        assert frame.quality is not None and frame.quality.flags == (), (i, frame.quality.invalid_fraction)
    # glass / black surface: 60% of the image without a reading
    depth = read_depth(sevenscenes_dir, 60).copy()
    depth[: int(0.6 * H)] = 0
    frame = depth_frame(depth, SEVENSCENES_INTR, frame_id=60, stamp_ns=60, pose=pose, monitor=monitor)
    assert frame.quality.flagged
    assert len(frame.quality.flags) == 1 and "invalid_fraction_jump" in frame.quality.flags[0]
    assert frame.quality.invalid_fraction > 0.6


# --------------------------------------------------------------------------------------------------------------
# 8. depth_frame
# --------------------------------------------------------------------------------------------------------------


def test_depth_frame_carries_quality_intrinsics_scale_provenance(sevenscenes_dir: Path) -> None:
    depth = read_depth(sevenscenes_dir, 250)
    prov = Provenance(str(sevenscenes_dir / "frame-000250.depth.png"), 250)
    T = np.eye(4)
    T[:3, 3] = (0.1, -0.2, 0.3)
    pose = PoseEstimate(T, revision=2, source=PoseSource.GROUND_TRUTH)
    colour = np.random.default_rng(0).integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    frame = depth_frame(depth, SEVENSCENES_INTR, frame_id=250, stamp_ns=8_333_333_250, pose=pose,
                        provenance=prov, min_depth_m=0.5, max_depth_m=3.0, color_rgb=colour)
    reference = backproject(depth, SEVENSCENES_INTR, depth_scale=1000, min_depth_m=0.5, max_depth_m=3.0)

    assert isinstance(frame, Frame)
    assert frame.frame_id == 250 and frame.stamp_ns == 8_333_333_250
    assert frame.sensor_kind is SensorKind.DEPTH_CAMERA
    assert frame.intrinsics == SEVENSCENES_INTR
    assert frame.depth_scale == 1000.0
    assert frame.provenance == prov
    assert frame.pose is pose and frame.pose.revision == 2
    np.testing.assert_array_equal(frame.points_sensor, reference.points)
    assert frame.points_sensor.dtype == np.float32 and not frame.points_sensor.flags.writeable

    q = frame.quality
    assert q is not None
    assert q.n_measurements == W * H
    assert q.n_valid == frame.n_points == reference.n_valid
    n_zero = int(np.count_nonzero(depth == 0))
    n_beyond = int(np.count_nonzero((depth >= 3000) & (depth != 65535)))
    n_below = int(np.count_nonzero((depth > 0) & (depth < 500)))
    assert dict(q.invalid_counts) == dict(reference.invalid_counts)
    assert q.invalid_counts[InvalidReason.ZERO.value] == n_zero
    assert q.invalid_counts[InvalidReason.BEYOND_MAX.value] == n_beyond
    assert q.invalid_counts[InvalidReason.BELOW_MIN.value] == n_below
    assert q.n_valid + sum(q.invalid_counts.values()) == q.n_measurements
    assert q.flags == ()
    # colour looked up at each point's own pixel
    np.testing.assert_array_equal(frame.attributes.color_rgb, colour.reshape(-1, 3)[reference.pixel_index])


def test_depth_frame_float_image_has_no_depth_scale() -> None:
    depth = np.array([[1.0, 1.2], [0.9, 1.1]], dtype=np.float32)
    intr = PinholeIntrinsics(fx=500, fy=500, cx=0.5, cy=0.5, width=2, height=2)
    frame = depth_frame(depth, intr, frame_id=1, stamp_ns=5, pose=PoseEstimate(np.eye(4)))
    assert frame.depth_scale is None
    assert frame.n_points == 4 and frame.quality.n_valid == 4 and frame.quality.invalid_fraction == 0.0
    assert frame.sensor_frame == "camera_depth_optical_frame"
