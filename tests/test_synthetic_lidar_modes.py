"""Synthetic LiDAR logs for real-LiDAR failure modes: a stationary start, stops, in-place turns, a rosette scanner,
per-point times from a moving sensor, and scan rates with the speed stated per second."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from driftmap import geometry
from driftmap.cli import app
from driftmap.errors import ConfigError, SourceError
from driftmap.sources.synthetic import (
    STREET_PERIMETER_M,
    LidarPattern,
    ScanMotion,
    SyntheticLog,
    SyntheticLogConfig,
    T_base_lidar,
    boxes_of,
    generate_synthetic_log,
    ground_truth_base_poses,
    ground_truth_base_poses_at,
    lidar_rays,
    motion_schedule,
)
from driftmap.trajectory import read_tum

CAMERA = dict(width=40, height=30, fx=32.8, fy=32.8, cx=19.5, cy=14.5)  # the depth camera small: LiDAR tests
ROOM = SyntheticLogConfig(lidar=True, lidar_beams=8, **CAMERA)
STREET = SyntheticLogConfig.street(loop_turns=0.1, speed_m_per_s=10.0, lidar_beams=8, lidar_azimuth_steps=512)
"""A tenth of the block (22 m) at 10 m/s and 10 Hz: 23 scans, 1 m apart."""


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def _scene(config: SyntheticLogConfig) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    for box in boxes_of(config):
        mesh = o3d.geometry.TriangleMesh.create_box(*np.subtract(box.max_m, box.min_m)).translate(box.min_m)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def _distance_m(scene: o3d.t.geometry.RaycastingScene, points_world: np.ndarray) -> np.ndarray:
    return scene.compute_distance(o3d.core.Tensor(points_world.astype(np.float32))).numpy()


def _yaw_rad(T: np.ndarray) -> float:
    return float(Rotation.from_matrix(T[:3, :3]).as_rotvec()[2])


def _steps_m(poses: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)


def test_default_logs_keep_their_motion_exactly() -> None:
    """The embedded log's motion is untouched: every scan moves, the poses are bit for bit the ones of the
    original ``linspace`` parameterisation, and the same log asked for at its own speed is the same log."""
    config = SyntheticLogConfig()
    assert set(motion_schedule(config).kinds) == {ScanMotion.MOVE}
    poses = ground_truth_base_poses(config)
    angles = np.linspace(0.0, 2.0 * math.pi * config.loop_turns, config.n_frames)
    for k, a in enumerate(angles):  # the generator before the motion modes
        assert np.array_equal(poses[k, :3, :3], Rotation.from_euler("z", a + math.pi / 2).as_matrix())
        assert np.array_equal(poses[k, :3, 3], [math.cos(a), math.sin(a), 0.0])
    at_speed = SyntheticLogConfig(speed_m_per_s=config.default_speed_m_per_s())
    assert at_speed.n_frames == config.n_frames
    assert np.array_equal(ground_truth_base_poses(at_speed), poses)
    street = SyntheticLogConfig.street()
    assert np.array_equal(ground_truth_base_poses(replace(street, speed_m_per_s=street.default_speed_m_per_s())),
                          ground_truth_base_poses(street))
    # the continuous trajectory passes through the frame poses
    stamps = config.start_stamp_ns + config.frame_period_ns * np.arange(config.n_frames, dtype=np.int64)
    np.testing.assert_allclose(ground_truth_base_poses_at(config, stamps), poses, atol=1e-12)


def test_lidar_modes_are_deterministic(tmp_path: Path) -> None:
    config = replace(ROOM, n_frames=14, stationary_start_frames=2, turn_in_place_at=(0.5,), turn_in_place_frames=1,
                     turn_in_place_deg_per_frame=50.0, lidar_pattern=LidarPattern.ROSETTE, lidar_points_per_scan=3000,
                     lidar_point_times=True)
    a = generate_synthetic_log(tmp_path / "a", config)
    b = generate_synthetic_log(tmp_path / "b", config)
    assert _digest(a) == _digest(b)
    assert "lidar/000005.time.bin" in _digest(a)
    c = generate_synthetic_log(tmp_path / "c", replace(config, seed=config.seed + 1))
    assert _digest(a)["lidar/000005.bin"] != _digest(c)["lidar/000005.bin"], "the seed must matter"
    assert _digest(a)["lidar/000005.time.bin"] == _digest(c)["lidar/000005.time.bin"]  # the pattern's times do not


def test_stationary_start_and_stops_stand_still(tmp_path: Path) -> None:
    """The first 5 scans and 2 stops of 3 scans stand: exactly 11 scans of zero motion, where asked; every other
    scan moves one equal step; stamps still increase; the odometry integrates the same motion."""
    config = replace(ROOM, n_frames=30, stationary_start_frames=5, stops=2, stop_frames=3)
    log = SyntheticLog(generate_synthetic_log(tmp_path / "log", config), sensor="lidar")
    gt = read_tum(log.path / "groundtruth.txt")  # the file itself (the depth camera's poses)
    assert np.all(np.diff(gt.stamps_ns) == config.frame_period_ns)
    steps = _steps_m(gt.poses)
    yaws = np.array([_yaw_rad(geometry.invert(gt.poses[k]) @ gt.poses[k + 1]) for k in range(len(gt) - 1)])
    still = np.flatnonzero((steps < 1e-9) & (np.abs(yaws) < 1e-9))
    moving = 29 - 11
    stop_at = [5 + round(j / 3 * moving) + 3 * (j - 1) for j in (1, 2)]  # after the start, j/3 of the moving path
    assert still.tolist() == [0, 1, 2, 3, 4, *range(stop_at[0], stop_at[0] + 3), *range(stop_at[1], stop_at[1] + 3)]
    np.testing.assert_allclose(np.delete(steps, still), steps[5], rtol=1e-9)  # the same step everywhere else
    assert steps[5] > 0.1
    assert [m.value for m in motion_schedule(config).kinds[:29]] == log.meta["scan_motion"][:29]
    # within the stationary scans the continuous trajectory stands too
    inside = config.start_stamp_ns + np.linspace(0, 5 * config.frame_period_ns - 1, 50).astype(np.int64)
    np.testing.assert_allclose(ground_truth_base_poses_at(config, inside), ground_truth_base_poses(config)[[0] * 50],
                               atol=1e-12)
    # each standing scan is a new noise draw of the same view
    first, second = log.lidar_frame(0).points_sensor, log.lidar_frame(1).points_sensor
    assert first.shape == second.shape and not np.array_equal(first, second)
    assert np.median(np.linalg.norm(first - second, axis=1)) < 0.03
    # the odometry: the same increments, 1 % longer, plus its noise (1 mm)
    odom_steps = _steps_m(read_tum(log.path / "odometry.txt").poses)
    assert np.all(odom_steps[still] < 0.006)
    moved = np.setdiff1d(np.arange(29), still)
    np.testing.assert_allclose(odom_steps[moved], 1.01 * steps[moved], atol=0.006)


def test_in_place_turns_turn_by_the_configured_yaw_and_the_loop_stays_a_loop() -> None:
    plain = replace(ROOM, n_frames=41)
    full = replace(plain, turns_in_place=2, turn_in_place_deg_per_frame=45.0, turn_in_place_frames=8,
                   speed_m_per_s=plain.default_speed_m_per_s() * 59 / 40)  # plain's step: 40 moving scans
    back = replace(plain, n_frames=41 + 4, turn_in_place_at=(0.25, 1.0), turn_in_place_deg_per_frame=-50.0,
                   turn_in_place_frames=1)
    assert full.n_frames == 41 + 16
    reference = ground_truth_base_poses(plain)
    for config, turn_yaws in ((full, [45.0] * 8), (back, [-50.0, 50.0])):
        poses = ground_truth_base_poses(config)
        kinds = motion_schedule(config).kinds[: config.n_frames - 1]
        turns = [k for k, m in enumerate(kinds) if m is ScanMotion.TURN]
        assert len(turns) == 2 * len(turn_yaws)
        for k in turns:
            delta = geometry.invert(poses[k]) @ poses[k + 1]
            assert np.linalg.norm(delta[:3, 3]) < 1e-12  # at a fixed position
        yaws = [math.degrees(_yaw_rad(geometry.invert(poses[k]) @ poses[k + 1])) for k in turns]
        np.testing.assert_allclose(yaws, turn_yaws * 2, atol=1e-9)
        # with the turns left out it is the plain log: each turn ends at the path heading, the end is the loop's
        keep = [0, *[k + 1 for k, m in enumerate(kinds) if m is ScanMotion.MOVE]]
        np.testing.assert_allclose(poses[keep], reference, atol=1e-9)
    np.testing.assert_allclose(ground_truth_base_poses(back)[-1], reference[-1], atol=1e-9)  # a turn at the end


def test_period_changes_the_frames_not_the_speed() -> None:
    """Speeds are per second: at 2 Hz a scan moves 5 times as far as at 10 Hz, and the loop is the same loop."""
    for base in (SyntheticLogConfig.street(), SyntheticLogConfig()):
        speed = base.default_speed_m_per_s()
        fast = replace(base, frame_period_ns=100_000_000, speed_m_per_s=speed)
        slow = replace(base, frame_period_ns=500_000_000, speed_m_per_s=speed)
        a, b = ground_truth_base_poses(fast), ground_truth_base_poses(slow)
        assert (len(a) - 1) == pytest.approx(5 * (len(b) - 1), abs=3)
        assert np.median(_steps_m(b)) == pytest.approx(5 * np.median(_steps_m(a)), rel=0.03)
        assert np.median(_steps_m(a)) == pytest.approx(speed * 0.1, rel=0.02)
        np.testing.assert_allclose(a[-1], b[-1], atol=1e-9)  # both end where the loop ends
    assert SyntheticLogConfig.street().default_speed_m_per_s() == pytest.approx(10.0, rel=0.01)


def test_rosette_scans_stay_in_the_fov_differ_and_fill_it(tmp_path: Path) -> None:
    config = replace(ROOM, n_frames=6, lidar_pattern=LidarPattern.ROSETTE, lidar_points_per_scan=6000)
    log = SyntheticLog(generate_synthetic_log(tmp_path / "log", config), sensor="lidar")
    half_fov = config.lidar_fov_deg / 2
    cells_seen: set[tuple[int, int]] = set()
    previous: set[tuple[int, int]] = set()
    cell = 0.02  # in tan(angle) on the plane x = 1: about 1.1 deg
    radius = math.tan(math.radians(half_fov))
    g = (np.arange(-40, 40) + 0.5) * cell
    cells_in_fov = int(np.sum(np.add.outer(g**2, g**2) < radius**2))
    coverage = []
    for k in range(5):
        pts = log.lidar_frame(k).points_sensor.astype(np.float64)
        assert len(pts) == config.lidar_points_per_scan  # the closed room returns every ray
        angle = np.degrees(np.arccos(pts[:, 0] / np.linalg.norm(pts, axis=1)))
        assert angle.max() <= half_fov + 1e-3 and angle.max() > half_fov - 0.1  # inside the cone, to its rim
        dirs, _ = lidar_rays(config, k)
        cells = set(zip(*np.floor(dirs[:, 1:] / dirs[:, :1] / cell).astype(int).T))
        if k:
            assert len(cells - previous) > 0.3 * len(cells), "a scan must look where the one before did not"
        previous = cells
        cells_seen |= cells
        coverage.append(len(cells_seen) / cells_in_fov)
    assert coverage[0] < 0.5 and coverage[4] > 0.9 and np.all(np.diff(coverage) > 0), coverage
    # with the room's walls in view the scan lies on the scene seen from the stamp pose (no point times)
    world = geometry.transform_points(log.ground_truth().poses[2], log.lidar_frame(2).points_sensor)
    assert np.median(_distance_m(_scene(config), world)) < config.lidar_range_sigma_m


@pytest.mark.parametrize("pattern", [LidarPattern.SPINNING, LidarPattern.ROSETTE])
def test_point_times_lie_in_the_scan_and_grow_along_the_pattern(tmp_path: Path, pattern: LidarPattern) -> None:
    config = replace(STREET, n_frames=4, speed_m_per_s=None, lidar_pattern=pattern, lidar_points_per_scan=4000,
                     lidar_point_times=True)
    log = SyntheticLog(generate_synthetic_log(tmp_path / "log", config), sensor="lidar")
    assert log.meta["lidar_time"]["unit"] == "ns"
    period = config.frame_period_ns
    for k in range(len(log)):
        frame = log.lidar_frame(k)
        t = frame.attributes.time_offset_ns
        assert t is not None and t.dtype == np.int64 and len(t) == frame.n_points
        assert t.min() >= 0 and t.max() < period
        assert np.array_equal(t, np.fromfile(log.path / f"lidar/{k:06d}.time.bin", dtype="<i8"))
        if pattern is LidarPattern.ROSETTE:  # along the curve: in time order
            assert np.all(np.diff(t) > 0)
            assert t.max() > 0.95 * period
        else:  # each ring in azimuth order, the time the azimuth's share of the turn
            p = frame.points_sensor.astype(np.float64)
            azimuth = np.mod(np.arctan2(p[:, 1], p[:, 0]), 2 * np.pi)
            steps = config.lidar_azimuth_steps
            expected = np.round(azimuth / (2 * np.pi) * steps) % steps * period // steps
            assert np.all(t == expected)
            ring_starts = np.flatnonzero(np.diff(t) < 0)
            assert len(ring_starts) <= config.lidar_beams - 1  # times fall back only where a ring begins
    no_times = SyntheticLog(generate_synthetic_log(tmp_path / "plain", replace(config, lidar_point_times=False)),
                            sensor="lidar")
    assert no_times.lidar_frame(0).attributes.time_offset_ns is None
    assert not list((no_times.path / "lidar").glob("*.time.bin")) and "lidar_time" not in no_times.meta


def _moving_cases() -> list:
    turning = replace(ROOM, n_frames=14, turn_in_place_at=(0.5,), turn_in_place_deg_per_frame=45.0,
                      turn_in_place_frames=8)
    return [
        pytest.param(replace(ROOM, n_frames=12), [3, 8], id="room-spinning"),
        pytest.param(replace(ROOM, n_frames=12, lidar_pattern=LidarPattern.ROSETTE, lidar_points_per_scan=6000), [3, 8],
                     id="room-rosette"),
        pytest.param(turning, [k for k, m in enumerate(motion_schedule(turning).kinds) if m is ScanMotion.TURN][:2],
                     id="room-turn-45deg"),
        pytest.param(replace(STREET, n_frames=12, speed_m_per_s=None), [3, 8], id="street-spinning"),
        pytest.param(replace(STREET, n_frames=12, speed_m_per_s=None, lidar_pattern=LidarPattern.ROSETTE,
                             lidar_points_per_scan=6000), [3, 8], id="street-rosette"),
    ]


@pytest.mark.parametrize(("config", "scans"), _moving_cases())
def test_moving_sensor_scans_deskew_onto_the_scene(tmp_path: Path, config: SyntheticLogConfig, scans: list[int]) -> None:
    """Each point placed with the ground-truth pose at its own capture time lies on the scene's boxes within the
    range noise; the same points placed with the scan-stamp pose (no deskew) are smeared by the motion."""
    config = replace(config, lidar_point_times=True)
    log = SyntheticLog(generate_synthetic_log(tmp_path / "log", config), sensor="lidar")
    scene = _scene(config)
    sigma = config.lidar_range_sigma_m
    for k in scans:
        frame = log.lidar_frame(k)
        pts = frame.points_sensor.astype(np.float64)
        T = ground_truth_base_poses_at(config, frame.stamp_ns + frame.attributes.time_offset_ns) @ T_base_lidar(config)
        deskewed = np.einsum("nij,nj->ni", T[:, :3, :3], pts) + T[:, :3, 3]
        at_stamp = geometry.transform_points(log.ground_truth().poses[k], frame.points_sensor)
        d_true, d_stamp = _distance_m(scene, deskewed), _distance_m(scene, at_stamp)
        assert np.median(d_true) < sigma and np.percentile(d_true, 95) < 2.5 * sigma, k  # |N(0, sigma)|: 0.67 / 1.96
        assert np.percentile(d_stamp, 95) > 4 * np.percentile(d_true, 95), k
        assert np.mean(d_stamp) > 3 * np.mean(d_true), k


def test_config_errors_name_the_field(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="turn_in_place_at"):
        SyntheticLogConfig(turns_in_place=1, turn_in_place_at=(0.5,), turn_in_place_deg_per_frame=45.0,
                           turn_in_place_frames=1)
    with pytest.raises(ConfigError, match="turn_in_place_deg_per_frame"):
        SyntheticLogConfig(turns_in_place=1, turn_in_place_frames=1)
    with pytest.raises(ConfigError, match="turn_in_place_frames"):
        SyntheticLogConfig(turns_in_place=1, turn_in_place_deg_per_frame=45.0)
    with pytest.raises(ConfigError, match="stop_frames"):
        SyntheticLogConfig(stops=2)
    with pytest.raises(ConfigError, match="n_frames"):
        SyntheticLogConfig(n_frames=10, stationary_start_frames=9)
    with pytest.raises(ConfigError, match="lidar"):
        SyntheticLogConfig(lidar_pattern="rosette")
    with pytest.raises(ConfigError, match="lidar_pattern"):
        SyntheticLogConfig(lidar=True, lidar_pattern="flash")
    with pytest.raises(ConfigError, match="speed_m_per_s"):
        SyntheticLogConfig(speed_m_per_s=0.0)
    with pytest.raises(ConfigError, match="stamps_ns"):
        ground_truth_base_poses_at(SyntheticLogConfig(), np.array([0], dtype=np.int64))
    folder = generate_synthetic_log(tmp_path / "log", replace(ROOM, n_frames=3, lidar_point_times=True))
    (folder / "lidar/000001.time.bin").write_bytes(b"\0" * 8)
    with pytest.raises(SourceError, match=r"000001\.time\.bin: 1 point times for the \d+ points"):
        SyntheticLog(folder, sensor="lidar").lidar_frame(1)


# ------------------------------------------------------------------------------------------ through the CLI


def _cli_log(tmp_path: Path, *args: str) -> SyntheticLog:
    out = tmp_path / "log"
    result = CliRunner().invoke(app, ["synth", str(out), *args])
    assert result.exit_code == 0, result.output
    assert f"{json.loads((out / 'synthetic.json').read_text())['config']['n_frames']} frames" in result.output
    return SyntheticLog(out, sensor="lidar")


def test_cli_synth_room_stationary_start_stops_turns_rosette_point_times(tmp_path: Path) -> None:
    log = _cli_log(tmp_path, "--stationary-start", "3", "--stops", "1", "--stop-frames", "2", "--turns", "1",
                   "--turn-deg-per-frame", "45", "--turn-frames", "8", "--lidar-pattern", "rosette",
                   "--points-per-scan", "2000", "--point-times")
    c = log.config
    assert (c.lidar, c.lidar_pattern, c.lidar_points_per_scan, c.lidar_point_times) == (True, LidarPattern.ROSETTE, 2000, True)
    assert (c.stationary_start_frames, c.stops, c.stop_frames) == (3, 1, 2)
    assert (c.turns_in_place, c.turn_in_place_deg_per_frame, c.turn_in_place_frames) == (1, 45.0, 8)
    assert len(log) == 60 + 3 + 2 + 8  # without --frames the room keeps its speed: the standing scans are added
    kinds = log.meta["scan_motion"]
    assert kinds[:3] == ["still"] * 3 and kinds.count("still") == 5 and kinds.count("turn") == 8
    gt = log.ground_truth().poses
    turn = kinds.index("turn")
    yaws = [math.degrees(_yaw_rad(geometry.invert(gt[k]) @ gt[k + 1])) for k in range(turn, turn + 8)]
    np.testing.assert_allclose(yaws, 45.0, atol=1e-6)
    frame = log.lidar_frame(turn)
    assert frame.n_points == 2000 and frame.attributes.time_offset_ns is not None


def test_cli_synth_street_period_speed_and_turn_at(tmp_path: Path) -> None:
    log = _cli_log(tmp_path, "--scene", "street", "--period-s", "0.5", "--speed-m-per-s", "20", "--turn-at", "0.5",
                   "--turn-deg-per-frame", "50", "--turn-frames", "1")
    c = log.config
    assert c.frame_period_ns == 500_000_000 and c.speed_m_per_s == 20.0 and c.turn_in_place_at == (0.5,)
    steps = _steps_m(log.ground_truth().poses)
    assert np.median(steps) == pytest.approx(10.0, rel=0.02)  # 20 m/s at 2 Hz
    assert len(log) == 1 + math.floor(c.loop_turns * STREET_PERIMETER_M / 10.0 + 0.5) + 2
    assert log.meta["scan_motion"].count("turn") == 2  # +50 deg, then back


def test_cli_synth_period_keeps_the_scene_speed(tmp_path: Path) -> None:
    log = _cli_log(tmp_path, "--scene", "street", "--period-s", "0.5")
    assert np.median(_steps_m(log.ground_truth().poses)) == pytest.approx(5.0, rel=0.02)  # 10 m/s at 2 Hz: 5 m
    assert len(log) == pytest.approx(245 / 5, abs=2)
    bad = CliRunner().invoke(app, ["synth", str(tmp_path / "bad"), "--frames", "10", "--speed-m-per-s", "1"])
    assert bad.exit_code == 2 and "--speed-m-per-s" in bad.output
