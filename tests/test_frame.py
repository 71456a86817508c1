"""Frame, PoseEstimate and the rigid-transform checks: immutability, copying, world transforms with real
7-Scenes ground-truth poses, and rejection of non-rigid poses with messages that name the field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from driftmap import (
    Frame,
    GeometryError,
    PinholeIntrinsics,
    PointAttributes,
    PoseEstimate,
    PoseSource,
    SensorKind,
    TransformError,
    backproject,
)

INTR = PinholeIntrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)


def make_frame(points, pose: PoseEstimate | None = None, **kwargs) -> Frame:
    return Frame(
        frame_id=kwargs.pop("frame_id", 7),
        stamp_ns=kwargs.pop("stamp_ns", 1_000),
        sensor_name="cam",
        sensor_kind=SensorKind.DEPTH_CAMERA,
        points_sensor=points,
        pose=pose if pose is not None else PoseEstimate(np.eye(4)),
        **kwargs,
    )


def a_rigid_transform(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T[:3, 3] = rng.uniform(-5, 5, size=3)
    return T


def read_sevenscenes(sevenscenes_dir: Path, index: int) -> tuple[np.ndarray, np.ndarray]:
    depth = np.asarray(o3d.io.read_image(str(sevenscenes_dir / f"frame-{index:06d}.depth.png")))
    pose = np.loadtxt(sevenscenes_dir / f"frame-{index:06d}.pose.txt")
    assert pose.shape == (4, 4)
    return depth, pose


# --------------------------------------------------------------------------------------------------------------
# 6. points are read-only float32 and never shared with the caller
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_points_are_readonly_float32_nx3(dtype: type) -> None:
    src = np.random.default_rng(0).normal(size=(100, 3)).astype(dtype)
    frame = make_frame(src)
    pts = frame.points_sensor
    assert pts.dtype == np.float32
    assert pts.shape == (100, 3)
    assert frame.n_points == 100
    assert not pts.flags.writeable
    with pytest.raises(ValueError):
        pts[0, 0] = 1.0
    np.testing.assert_array_equal(pts, src.astype(np.float32))


def test_adopted_points_are_shared_read_only_and_views_are_still_copied() -> None:
    """``adopt_readonly`` (depth_frame's hand-over of the points it made) shares an array that owns its data,
    made read-only; a view (its base could still be written through) is left alone and the frame copies it."""
    from driftmap.frame import adopt_readonly
    from driftmap.preprocess.depth import depth_frame

    own = np.random.default_rng(1).normal(size=(50, 3)).astype(np.float32)
    frame = make_frame(adopt_readonly(own))
    assert frame.points_sensor is own and not own.flags.writeable
    base = np.zeros((60, 3), np.float32)
    view = adopt_readonly(base[:50])
    assert view.flags.writeable
    frame = make_frame(view)
    assert not np.shares_memory(frame.points_sensor, base)
    base[0, 0] = 5.0
    assert frame.points_sensor[0, 0] == 0.0

    depth = np.full((48, 64), 1500, np.uint16)
    depth[::3, ::5] = 0  # invalid pixels: the buffer is shrunk to the valid points
    K = PinholeIntrinsics(fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=64, height=48)
    reference = backproject(depth, K)
    made = depth_frame(depth, K, frame_id=0, stamp_ns=0, pose=PoseEstimate(np.eye(4), source=PoseSource.NONE))
    assert reference.points.flags.owndata and reference.points.base is None
    np.testing.assert_array_equal(made.points_sensor, reference.points)
    assert made.points_sensor.flags.owndata and not made.points_sensor.flags.writeable


def _writable_float32(src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return src, src


def _writable_float64(src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    arr = src.astype(np.float64)
    return arr, arr


def _readonly_view_of_writable(src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    view = src[:]
    view.setflags(write=False)
    return view, src  # hand the frame a read-only view, keep writing through the base


def _readonly_then_writable_again(src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    src.setflags(write=False)
    return src, src


def _fortran_order(src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    arr = np.asfortranarray(src)
    return arr, arr


@pytest.mark.parametrize(
    "handoff",
    [_writable_float32, _writable_float64, _readonly_view_of_writable, _readonly_then_writable_again, _fortran_order],
)
def test_mutating_the_callers_array_does_not_change_the_frame(handoff) -> None:
    src = np.random.default_rng(1).normal(size=(50, 3)).astype(np.float32)
    before = src.copy()
    given, writer = handoff(src)
    frame = make_frame(given)
    writer.setflags(write=True)
    writer[:] = 123.0
    assert not frame.points_sensor.flags.writeable
    np.testing.assert_array_equal(frame.points_sensor, before)


def test_mutating_the_callers_attribute_array_does_not_change_the_frame() -> None:
    pts = np.zeros((4, 3), np.float32)
    intensity = np.array([1.0, 2.0, 3.0, 4.0], np.float32)
    view = intensity[:]
    view.setflags(write=False)
    frame = make_frame(pts, attributes=PointAttributes(intensity=view))
    intensity[:] = -1.0
    np.testing.assert_array_equal(frame.attributes.intensity, [1.0, 2.0, 3.0, 4.0])
    assert not frame.attributes.intensity.flags.writeable


@pytest.mark.parametrize("shape", [(10, 2), (10, 4), (30,), (2, 3, 3)])
def test_points_of_wrong_shape_are_rejected(shape: tuple[int, ...]) -> None:
    with pytest.raises(GeometryError, match="points_sensor"):
        make_frame(np.zeros(shape, np.float32))


def test_attributes_must_match_point_count() -> None:
    with pytest.raises(GeometryError, match="intensity"):
        make_frame(np.zeros((5, 3), np.float32), attributes=PointAttributes(intensity=np.zeros(4, np.float32)))


def test_frame_is_frozen() -> None:
    frame = make_frame(np.zeros((3, 3), np.float32))
    with pytest.raises(AttributeError):
        frame.points_sensor = np.ones((3, 3), np.float32)  # type: ignore[misc]


# --------------------------------------------------------------------------------------------------------------
# 6. world transform with real 7-Scenes ground truth, and with_pose
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("index", [0, 250, 640, 999])
def test_sevenscenes_ground_truth_pose_is_accepted(sevenscenes_dir: Path, index: int) -> None:
    """7-Scenes ground-truth rotations are orthonormal only to ~1e-4 (KinectFusion output written with
    limited precision); a real ground-truth pose must still be usable as a PoseEstimate."""
    _, T_file = read_sevenscenes(sevenscenes_dir, index)
    pose = PoseEstimate(T_file, source=PoseSource.GROUND_TRUTH)
    T = pose.T_world_sensor
    assert not T.flags.writeable
    np.testing.assert_allclose(T, T_file, rtol=0, atol=1e-3)
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), rtol=0, atol=1e-3)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize("index", [0, 250, 640, 999])
def test_points_world_with_sevenscenes_ground_truth(sevenscenes_dir: Path, index: int) -> None:
    depth, T_file = read_sevenscenes(sevenscenes_dir, index)
    points = backproject(depth, INTR, depth_scale=1000).points
    frame = make_frame(points, PoseEstimate(T_file, source=PoseSource.GROUND_TRUTH), intrinsics=INTR,
                       depth_scale=1000.0)
    world = frame.points_world()
    assert world.dtype == np.float32 and world.shape == points.shape

    T = frame.T_world_sensor
    reference = points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(world.astype(np.float64), reference, rtol=0, atol=1e-6)
    # and with the file's matrix itself (the stored pose may be re-orthonormalised, by < 1e-3)
    reference_file = points.astype(np.float64) @ T_file[:3, :3].T + T_file[:3, 3]
    assert np.max(np.abs(world - reference_file)) < 5e-3
    # an explicit pose overrides the frame's own
    T_other = a_rigid_transform(index)
    reference_other = points.astype(np.float64) @ T_other[:3, :3].T + T_other[:3, 3]
    np.testing.assert_allclose(frame.points_world(T_other).astype(np.float64), reference_other, rtol=0, atol=1e-5)


def test_points_world_matches_float64_reference_for_a_synthetic_pose() -> None:
    rng = np.random.default_rng(5)
    points = rng.uniform(-4, 4, size=(1000, 3)).astype(np.float32)
    T = a_rigid_transform(3)
    frame = make_frame(points, PoseEstimate(T))
    reference = points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(frame.points_world().astype(np.float64), reference, rtol=0, atol=2e-6)
    # round trip through the inverse recovers the sensor-frame points
    T_inv = np.linalg.inv(T)
    back = frame.points_world().astype(np.float64) @ T_inv[:3, :3].T + T_inv[:3, 3]
    np.testing.assert_allclose(back, points, rtol=0, atol=5e-6)


def test_with_pose_keeps_points_and_changes_world() -> None:
    points = np.random.default_rng(2).uniform(-1, 1, size=(200, 3)).astype(np.float32)
    frame = make_frame(points, PoseEstimate(a_rigid_transform(1), revision=0, source=PoseSource.ODOMETRY))
    new_pose = PoseEstimate(a_rigid_transform(2), revision=1, source=PoseSource.LOOP_CLOSURE)
    moved = frame.with_pose(new_pose)
    np.testing.assert_array_equal(moved.points_sensor, frame.points_sensor)
    assert not moved.points_sensor.flags.writeable
    assert moved.pose is new_pose and moved.pose.revision == 1
    assert frame.pose.revision == 0  # the original is untouched
    assert (moved.frame_id, moved.stamp_ns, moved.sensor_name) == (frame.frame_id, frame.stamp_ns, frame.sensor_name)
    T = new_pose.T_world_sensor
    np.testing.assert_allclose(moved.points_world(), points.astype(np.float64) @ T[:3, :3].T + T[:3, 3],
                               rtol=0, atol=2e-6)
    assert np.max(np.abs(moved.points_world() - frame.points_world())) > 0.1


def test_pose_is_a_readonly_copy() -> None:
    T = a_rigid_transform(4)
    pose = PoseEstimate(T)
    T[0, 3] += 10.0
    assert pose.T_world_sensor[0, 3] == pytest.approx(T[0, 3] - 10.0)
    assert not pose.T_world_sensor.flags.writeable
    assert pose.T_world_sensor.dtype == np.float64


# --------------------------------------------------------------------------------------------------------------
# 5. non-rigid poses are rejected, naming the field
# --------------------------------------------------------------------------------------------------------------


def _scaled() -> np.ndarray:
    T = a_rigid_transform(0)
    T[:3, :3] *= 1.01
    return T


def _reflection() -> np.ndarray:
    T = a_rigid_transform(0)
    T[:3, :3] = T[:3, :3] @ np.diag([1.0, 1.0, -1.0])  # orthonormal, det = -1
    return T


def _bad_last_row() -> np.ndarray:
    T = a_rigid_transform(0)
    T[3] = [0.0, 0.0, 0.1, 1.0]
    return T


def _projective_scale() -> np.ndarray:
    T = a_rigid_transform(0)
    T[3, 3] = 2.0
    return T


def _nan() -> np.ndarray:
    T = a_rigid_transform(0)
    T[1, 2] = np.nan
    return T


def _inf_translation() -> np.ndarray:
    T = a_rigid_transform(0)
    T[0, 3] = np.inf
    return T


def _sheared() -> np.ndarray:
    T = np.eye(4)
    T[0, 1] = 0.05
    return T


def _wrong_shape() -> np.ndarray:
    return a_rigid_transform(0)[:3]


NON_RIGID = {
    "scaled": _scaled,
    "reflection": _reflection,
    "bad_last_row": _bad_last_row,
    "projective_scale": _projective_scale,
    "nan": _nan,
    "inf_translation": _inf_translation,
    "sheared": _sheared,
    "wrong_shape": _wrong_shape,
}


def test_reflection_fixture_really_is_orthonormal_with_negative_determinant() -> None:
    R = _reflection()[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(-1.0)


@pytest.mark.parametrize("kind", sorted(NON_RIGID))
def test_pose_estimate_rejects_non_rigid(kind: str) -> None:
    with pytest.raises(TransformError, match="PoseEstimate.T_world_sensor"):
        PoseEstimate(NON_RIGID[kind]())


@pytest.mark.parametrize("kind", sorted(NON_RIGID))
def test_frame_rejects_non_rigid_extrinsics(kind: str) -> None:
    with pytest.raises(TransformError, match="T_base_sensor") as info:
        make_frame(np.zeros((3, 3), np.float32), T_base_sensor=NON_RIGID[kind](), frame_id=42)
    assert "frame 42" in str(info.value)


@pytest.mark.parametrize("kind", ["scaled", "reflection", "bad_last_row", "nan"])
def test_frame_rejects_a_raw_non_rigid_matrix_as_pose(kind: str) -> None:
    """A Frame must not carry an unvalidated pose: a bare (non-rigid) 4x4 handed in as ``pose`` is rejected."""
    with pytest.raises(TransformError, match="(?i)pose"):
        make_frame(np.zeros((3, 3), np.float32), pose=NON_RIGID[kind]())  # type: ignore[arg-type]


def test_rigid_pose_with_tiny_float_noise_is_accepted() -> None:
    T = a_rigid_transform(9)
    T[:3, :3] += 1e-7 * np.random.default_rng(0).normal(size=(3, 3))
    assert np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max() > 1e-12  # the noise is there (1.3e-7): not a no-op
    pose = PoseEstimate(T)
    P = pose.T_world_sensor
    np.testing.assert_array_equal(P[3], [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(P[:3, 3], T[:3, 3])  # only the rotation block is projected
    # accepted as given up to the noise: the projection moved it by 7.9e-8 (the noise has max |entry| ~2e-7)
    np.testing.assert_allclose(P, T, rtol=0.0, atol=1e-6)
    # ...and stored exactly rigid: as_rigid projects onto SO(3) whenever |R^T R - I| > 1e-12 (measured: 8.9e-16)
    R = P[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() <= 1e-12
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


def test_frame_rejects_bad_scalars() -> None:
    with pytest.raises(GeometryError, match="stamp_ns"):
        make_frame(np.zeros((1, 3), np.float32), stamp_ns=1.5)
    with pytest.raises(GeometryError, match="depth_scale"):
        make_frame(np.zeros((1, 3), np.float32), depth_scale=0.0)
    with pytest.raises(GeometryError, match="depth_scale"):
        make_frame(np.zeros((1, 3), np.float32), depth_scale=float("nan"))
    with pytest.raises(GeometryError, match="depth_scale must be a positive number, got '1'"):
        make_frame(np.zeros((1, 3), np.float32), depth_scale="1")
    # ids and stamps go into int64 columns of the store: a uint64 hash or sequence number must not get in
    pts = np.zeros((1, 3), np.float32)
    with pytest.raises(GeometryError, match=r"Frame.frame_id = 9223372036854775808 does not fit"):
        make_frame(pts, frame_id=2**63)
    with pytest.raises(GeometryError, match=r"frame 7: stamp_ns = 18446744073709551615 does not fit"):
        make_frame(pts, stamp_ns=np.uint64(2**64 - 1))
    with pytest.raises(GeometryError, match="Frame.frame_id must be an integer, got None"):
        make_frame(pts, frame_id=None)
    with pytest.raises(GeometryError, match=r"frame 7: stamp_ns must be an integer number of nanoseconds, got None"):
        make_frame(pts, stamp_ns=None)
    assert make_frame(pts, frame_id=2**63 - 1, stamp_ns=-(2**63)).frame_id == 2**63 - 1
    with pytest.raises(GeometryError, match=r"frame 7: sensor_kind: 'sonar' is not one of \['depth_camera', 'lidar'\]"):
        Frame(frame_id=7, stamp_ns=0, sensor_name="x", sensor_kind="sonar", points_sensor=pts, pose=PoseEstimate(np.eye(4)))
    with pytest.raises(GeometryError, match=r"PoseEstimate.source: 'bogus' is not one of"):
        PoseEstimate(np.eye(4), source="bogus")
    with pytest.raises(GeometryError, match=r"PoseEstimate.revision must be >= 0"):
        PoseEstimate(np.eye(4), revision=-1)


def test_top_level_entry_points_are_lazy() -> None:
    """`import driftmap` stays light; the store, map view, sources and build are reachable from it."""
    import subprocess
    import sys

    code = ("import sys, driftmap; heavy = [m for m in ('open3d', 'gtsam', 'kiss_icp') if m in sys.modules]; "
            "assert not heavy, heavy; from driftmap import FrameStore, MapView, ChangeSet, open_source, build; "
            "assert FrameStore.__module__ == 'driftmap.store.frame_store' and MapView.__name__ == 'MapView'")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    import driftmap

    with pytest.raises(AttributeError):
        driftmap.NoSuchThing  # noqa: B018
