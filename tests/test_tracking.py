"""Tracking health and the robust retry of the scan-to-map odometry (registration/tracking.py), the scene reach
over many frames (preprocess/scene.py), and what loop closure does with flagged frames."""

from __future__ import annotations

import numpy as np
import pytest
import small_gicp
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.frame import Frame, PoseEstimate, SensorKind, TrackingHealth, TrackingStatus
from driftmap.preprocess.scene import diagnostics_scale, lidar_odometry_scale, sample_positions, scene_reach
from driftmap.registration import tracking
from driftmap.registration.loops import LoopClosureConfig, find_loops, make_keyframe
from driftmap.registration.odometry import OdometryConfig
from driftmap.store.frame_store import FrameStore


def _plane_points(n: int, rng: np.random.Generator) -> np.ndarray:
    return np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), np.zeros(n)])


def _box_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """Points on the floor and two walls of a corner: every direction of translation is constrained."""
    a, b, c = _plane_points(n, rng), _plane_points(n, rng), _plane_points(n, rng)
    b = b[:, [2, 0, 1]] + [3.0, 0.0, 0.0]  # the wall x = 3
    c = c[:, [0, 2, 1]] + [0.0, 3.0, 0.0]  # the wall y = 3
    return np.vstack([a, b, c])


def test_fit_to_map_counts_points_within_the_radius_and_measures_degeneracy() -> None:
    rng = np.random.default_rng(0)
    corner = _box_points(3000, rng)
    tree = small_gicp.KdTree(corner)
    fit = tracking.fit_to_map(corner[::7] + [0.0, 0.0, 0.01], corner, tree, 0.05, with_degeneracy=True)
    assert fit.fitness > 0.95 and 0.005 < fit.rmse_m < 0.05
    assert fit.degeneracy is not None and fit.degeneracy > 0.5  # three orthogonal planes
    off = tracking.fit_to_map(corner[::7] + [0.0, 0.0, 1.0], corner, tree, 0.05)
    assert off.fitness < fit.fitness - 0.3  # a metre off: only the walls' points still find a neighbour
    plane = _plane_points(3000, rng)
    flat = tracking.fit_to_map(plane[::7], plane, small_gicp.KdTree(plane), 0.05, with_degeneracy=True)
    assert flat.degeneracy is not None and flat.degeneracy < 0.05  # a single plane leaves two directions free


def _policy(**kw: object) -> tracking.RetryPolicy:
    base = dict(min_fitness=0.5, retry_fitness_ratio=0.9, min_gain=0.02, yaw_deg=(15.0, 30.0, 45.0),
                up_axis=tracking.UP_AXIS_LIDAR)
    base.update(kw)
    return tracking.RetryPolicy(**base)  # type: ignore[arg-type]


def _turn_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))


def test_retry_keeps_the_guess_that_fits_after_a_turn_stops() -> None:
    """A 40 deg turn, then none: the prediction (another 40 deg) lands in a wrong minimum; zero motion fits."""
    truth_deg = 40.0
    last_pose = tracking._turn((0, 0, 1), truth_deg)
    last_delta = tracking._turn((0, 0, 1), truth_deg)

    def align(guess: np.ndarray) -> np.ndarray:  # ICP converges to the truth within 20 deg of it, else stays put
        return last_pose if abs(_turn_deg(geometry.invert(last_pose) @ guess)) < 20.0 else guess

    def evaluate(T: np.ndarray) -> tracking.MapFit:
        err = abs(_turn_deg(geometry.invert(last_pose) @ T))
        return tracking.MapFit(max(0.0, 0.98 - err / 50.0), 0.01, None)

    attempt, status, reason, dev_m, dev_deg = tracking.register_robustly(
        align, evaluate, last_pose, last_delta, [0.97, 0.98, 0.98], _policy(), frame_id=7)
    assert status is TrackingStatus.RECOVERED and attempt.hypothesis in ("zero_motion", "half_velocity", "yaw-30", "yaw-45")
    assert np.allclose(attempt.T_world_sensor, last_pose)
    assert "fitness" in reason and dev_deg == pytest.approx(40.0, abs=1e-6)
    # without retries the same frame is lost, never silently accepted
    attempt, status, reason, _, _ = tracking.register_robustly(
        align, evaluate, last_pose, last_delta, [0.97, 0.98, 0.98], _policy(retry=False), frame_id=7)
    assert status is TrackingStatus.LOST and "retries are off" in reason


def test_retry_reports_lost_when_no_guess_fits_and_ok_when_the_prediction_fits() -> None:
    last_pose, last_delta = np.eye(4), tracking._turn((0, 0, 1), 10.0)

    def identity_align(guess: np.ndarray) -> np.ndarray:
        return guess

    attempt, status, reason, _, _ = tracking.register_robustly(
        identity_align, lambda T: tracking.MapFit(0.2, 0.1, None), last_pose, last_delta, [0.9], _policy(), frame_id=3)
    assert status is TrackingStatus.LOST and "no initial guess fits" in reason
    attempt, status, reason, _, _ = tracking.register_robustly(
        identity_align, lambda T: tracking.MapFit(0.95, 0.01, None), last_pose, last_delta, [0.96], _policy(), frame_id=3)
    assert status is TrackingStatus.OK and reason == "" and attempt.hypothesis == "constant_velocity"


def test_initial_guesses_cover_zero_half_and_turned_predictions() -> None:
    last_pose = geometry.make_transform(None, (1.0, 2.0, 0.0))
    delta = tracking._turn((0, 0, 1), 30.0)
    delta[:3, 3] = (0.4, 0.0, 0.0)
    guesses = dict(tracking.initial_guesses(last_pose, delta, tracking.UP_AXIS_LIDAR, (15.0, 45.0)))
    assert set(guesses) == {"zero_motion", "half_velocity", "yaw+15", "yaw-15", "yaw+45", "yaw-45", "turn+15", "turn-15",
                            "turn+45", "turn-45"}
    assert _turn_deg(geometry.invert(last_pose) @ guesses["turn+45"]) == pytest.approx(45.0)  # turned in place
    assert np.allclose(guesses["turn+45"][:3, 3], last_pose[:3, 3])
    assert np.allclose(guesses["zero_motion"], last_pose)
    half = geometry.invert(last_pose) @ guesses["half_velocity"]
    assert _turn_deg(half) == pytest.approx(15.0) and half[0, 3] == pytest.approx(0.2)
    assert _turn_deg(geometry.invert(last_pose @ delta) @ guesses["yaw-45"]) == pytest.approx(-45.0)


def test_tracking_health_round_trips_through_the_store(tmp_path) -> None:
    health = TrackingHealth(TrackingStatus.RECOVERED, fitness=0.97, rmse_m=0.12, degeneracy=0.7, deviation_m=2.1,
                            deviation_deg=12.3, hypothesis="zero_motion", n_points=800, fitness_radius_m=0.45,
                            reason="fitness 0.49 < 0.5")
    frame = Frame(frame_id=5, stamp_ns=10, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                  points_sensor=np.ones((4, 3), np.float32), pose=PoseEstimate(np.eye(4)), tracking=health)
    with FrameStore.create(tmp_path / "s") as store:
        store.append(frame)
        store.append(Frame(frame_id=6, stamp_ns=20, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                           points_sensor=np.ones((4, 3), np.float32), pose=PoseEstimate(np.eye(4))))
    store = FrameStore.open(tmp_path / "s")
    assert store.frame(5).tracking == health
    assert store.frame(6).tracking is None
    assert not health.flagged and TrackingHealth(TrackingStatus.LOST).flagged


def _scan(frame_id: int, reach_m: float) -> Frame:
    rng = np.random.default_rng(frame_id)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Frame(frame_id=frame_id, stamp_ns=frame_id, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                 points_sensor=(d * rng.uniform(0.5, reach_m, (2000, 1))).astype(np.float32), pose=PoseEstimate(np.eye(4)))


def test_odometry_lengths_come_from_the_median_reach_of_many_frames() -> None:
    """One scan facing a wall (2 m) among scans reaching 20 m does not set the lengths."""
    frames = [_scan(0, 2.0)] + [_scan(k, 20.0) for k in range(1, 9)]
    reach = scene_reach(frames)
    assert reach is not None and reach.n_frames == 9 and 19.0 < reach.reach_m < 20.0
    cfg = OdometryConfig.for_frames(frames, log=False)
    wall_only = OdometryConfig.for_frame(frames[0], log=False)
    assert cfg.voxel_size_m == pytest.approx(1.0 * reach.reach_m / 25.0)
    assert wall_only.voxel_size_m < 0.1 < cfg.voxel_size_m
    # the scales are continuous in the reach (no indoor / outdoor switch)
    reaches = np.linspace(1.0, 60.0, 600)
    for f in (lidar_odometry_scale, diagnostics_scale):
        values = np.array([f(r) for r in reaches])
        assert np.all(np.diff(values) >= 0) and np.max(np.abs(np.diff(values))) < 0.05
    assert diagnostics_scale(4.0) == 1.0 and diagnostics_scale(30.0) == 5.0 and diagnostics_scale(15.0) == 3.0
    assert sample_positions(80) == sorted(set(sample_positions(80))) and sample_positions(80)[-1] == 79
    assert len(sample_positions(80)) == 15 and sample_positions(3) == [0, 1, 2]


def test_loop_candidates_across_a_flagged_stretch_are_refused_unverified() -> None:
    rng = np.random.default_rng(1)
    pts = _box_points(2000, rng)
    lc = LoopClosureConfig(min_gap_s=1.0, proximity_radius_m=1.0, submap_radius_frames=0, registration_voxel_m=0.1,
                           descriptor_candidates=0)
    keyframes = [make_keyframe(k * 10, k * 10, np.eye(4), pts, lc, stamp_ns=int(k * 2e9)) for k in range(3)]
    trusted = find_loops(keyframes, lc)
    assert trusted and all(c.result is not None for c in trusted)
    refused = find_loops(keyframes, lc, flagged={15: 15})  # a lost frame between keyframes 1 and 2 (rows 10..20)
    across = [c for c in refused if c.b == 20]
    assert across and all(not c.accepted and c.result is None and "flagged" in c.reason and "15" in c.reason
                          for c in across)
    before = [c for c in refused if c.b == 10]  # 0 <-> 10 does not lean on frame 15
    assert before and all(c.result is not None for c in before)


def _wall_and_floor(n: int, rng: np.random.Generator) -> np.ndarray:
    """The floor z = 0 and the wall x = 3: translation along y is not constrained."""
    a, b = _plane_points(n, rng), _plane_points(n, rng)
    return np.vstack([a, b[:, [2, 0, 1]] + [3.0, 0.0, 0.0]])


@pytest.mark.parametrize("scene, weak_axis", [("wall_and_floor", 1), ("corner", None)])
def test_weak_directions_keep_the_prediction_and_the_constrained_ones_the_registration(scene, weak_axis) -> None:
    """small_gicp's point-to-plane Hessian of a scan of a wall and the floor has a free direction (world y); along it
    the registration's translation is replaced by the prediction's, across it the registration is kept. A corner
    constrains every direction: nothing is replaced."""
    rng = np.random.default_rng(3)
    world = _wall_and_floor(4000, rng) if scene == "wall_and_floor" else _box_points(4000, rng)
    T_true = geometry.make_transform(Rotation.from_euler("xyz", (5.0, -3.0, 30.0), degrees=True), (0.5, -0.4, 1.0))
    scan = geometry.transform_points(geometry.invert(T_true), world)
    target, tree = small_gicp.preprocess_points(world, downsampling_resolution=0.1, num_neighbors=10)
    source, _ = small_gicp.preprocess_points(scan, downsampling_resolution=0.1, num_neighbors=10)
    start = T_true.copy()
    start[:3, 3] += (0.02, 0.3, 0.0)  # 2 cm across the wall, 30 cm along it
    res = small_gicp.align(target, source, tree, start, registration_type="PLANE_ICP", max_correspondence_distance=0.2)
    T_reg = np.array(res.T_target_source)
    assert abs(T_reg[0, 3] - T_true[0, 3]) < 0.005  # the wall pulls x back
    out, weak = tracking.keep_prediction_along_weak_directions(T_reg, T_true, np.asarray(res.H), 0.11)
    if weak_axis is None:
        assert weak is None and np.array_equal(out, T_reg)
        return
    assert abs(T_reg[1, 3] - T_true[1, 3]) > 0.25  # nothing pulls y back: the registration slid with the start
    assert weak is not None and weak.directions_world.shape == (1, 3)
    assert abs(weak.directions_world[0, weak_axis]) > 0.99 and weak.degeneracy < 0.11
    assert weak.replaced_m == pytest.approx(abs(T_reg[1, 3] - T_true[1, 3]), abs=0.01)
    assert np.allclose(out[:3, 3], T_true[:3, 3], atol=0.01)  # y from the prediction, x and z the registration's
    assert np.array_equal(out[:3, :3], T_reg[:3, :3])
    same, none = tracking.keep_prediction_along_weak_directions(T_reg, T_true, np.asarray(res.H), 0.0)
    assert none is None and np.array_equal(same, T_reg)  # 0: off
