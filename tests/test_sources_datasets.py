"""Data-set sources on the real shared data: 7-Scenes, TUM RGB-D (a folder built from real 7-Scenes frames),
KITTI odometry, Redwood / ICL-NUIM, folders of PLY / PCD scans, and the trajectory readers (TUM, KITTI, EuRoC,
Redwood .log) against evo as a reference implementation."""

from __future__ import annotations

import json
import logging
import os
import shutil
from decimal import Decimal
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from PIL import Image
from scipy.spatial import cKDTree

import driftmap
from cloud_files import write_pcd, write_ply, xyz_columns
from driftmap import DepthScaleError, PinholeIntrinsics, PoseSource, SensorKind, SourceError
from driftmap.errors import ConfigError
from driftmap.sources.base import open_source
from driftmap.sources.cloud_folder import CloudFolder
from driftmap.sources.kitti import KittiOdometry
from driftmap.sources.redwood import RedwoodRgbd
from driftmap.sources.sevenscenes import SevenScenes
from driftmap.sources.tum import TUM_GENERIC_INTRINSICS, TUM_INTRINSICS, TumRgbd, tum_setup
from driftmap.trajectory import (
    Trajectory,
    detect_trajectory_format,
    read_euroc,
    read_kitti,
    read_redwood_log,
    read_trajectory,
    write_kitti,
    write_tum,
)

PERIOD_30HZ_NS = 33_333_333
SEVENSCENES_K = PinholeIntrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
# 7-Scenes frames across the sequence; 33 and 850 carry 65535 "no reading" pixels
SEVENSCENES_FRAMES = (0, 33, 250, 640, 850, 999)


def _shared(datasets_dir: Path, name: str) -> Path:
    path = datasets_dir / name
    if not path.exists():
        message = f"shared data not found at {path}"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(message + "; in CI the data must be present", pytrace=False)
        pytest.skip(message)
    return path


@pytest.fixture(scope="module")
def icl_dir(datasets_dir: Path) -> Path:
    return _shared(datasets_dir, "icl-nuim-livingroom1-5frames")


@pytest.fixture(scope="module")
def trajectories_dir(datasets_dir: Path) -> Path:
    return _shared(datasets_dir, "trajectories")


def _png(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path))


def _sevenscenes_png(folder: Path, frame_id: int) -> Path:
    return folder / f"frame-{frame_id:06d}.depth.png"


# ---- detection ---------------------------------------------------------------------------------------------------


def test_detection_picks_the_format_of_each_shared_folder(
    sevenscenes_dir: Path, kitti_dir: Path, icl_dir: Path
) -> None:
    assert isinstance(open_source(sevenscenes_dir), SevenScenes)
    assert isinstance(open_source(kitti_dir), KittiOdometry)
    assert isinstance(open_source(icl_dir), RedwoodRgbd)


def test_a_folder_of_no_known_format_names_every_format_tried(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("nothing to see")
    with pytest.raises(SourceError, match="cannot tell the format") as info:
        open_source(tmp_path)
    for name in ("7scenes", "tum", "kitti", "redwood", "cloud_folder"):
        assert name in str(info.value)


def test_unknown_options_are_rejected_with_the_accepted_ones(icl_dir: Path) -> None:
    with pytest.raises(SourceError, match=r"unknown option\(s\) max_dept_m .*accepted: .*max_depth_m"):
        open_source(icl_dir, max_dept_m=3.0)


def test_a_map_saved_into_a_dataset_folder_does_not_make_it_a_cloud_folder(tmp_path: Path, kitti_dir: Path) -> None:
    (tmp_path / "velodyne").mkdir()
    shutil.copy(kitti_dir / "velodyne" / "000000.bin", tmp_path / "velodyne")
    o3d.t.io.write_point_cloud(str(tmp_path / "map.ply"), o3d.t.geometry.PointCloud(np.zeros((3, 3), np.float32)))
    assert isinstance(open_source(tmp_path), KittiOdometry)


# ---- 7-Scenes ----------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sevenscenes(sevenscenes_dir: Path) -> SevenScenes:
    return open_source(sevenscenes_dir)


def test_sevenscenes_frames_equal_backproject_of_the_png(sevenscenes: SevenScenes, sevenscenes_dir: Path) -> None:
    assert len(sevenscenes) == 1000 and sevenscenes.frame_ids() == list(range(1000))
    assert sevenscenes.intrinsics == SEVENSCENES_K
    n_sentinel = 0
    for frame_id in SEVENSCENES_FRAMES:
        frame = sevenscenes.frame(frame_id)
        png = _sevenscenes_png(sevenscenes_dir, frame_id)
        expected = driftmap.backproject(_png(png), SEVENSCENES_K, depth_scale=1000.0, min_depth_m=0.2, max_depth_m=4.0)
        np.testing.assert_array_equal(frame.points_sensor, expected.points)
        assert frame.frame_id == frame_id
        assert frame.stamp_ns == frame_id * PERIOD_30HZ_NS
        assert frame.sensor_kind is SensorKind.DEPTH_CAMERA and frame.depth_scale == 1000.0
        assert frame.intrinsics == SEVENSCENES_K
        assert frame.provenance.source_uri == str(png.resolve()) and frame.provenance.index == frame_id
        # no estimate in the data: the ground truth is never the frame's pose
        assert frame.pose.source is PoseSource.NONE
        np.testing.assert_array_equal(frame.T_world_sensor, np.eye(4))
        n_sentinel += frame.quality.invalid_counts["no_reading_65535"]
    assert n_sentinel > 0, "frames 33 and 850 carry 65535 'no reading' pixels"


def test_sevenscenes_ground_truth_equals_the_pose_files(sevenscenes: SevenScenes, sevenscenes_dir: Path) -> None:
    gt = sevenscenes.ground_truth()
    np.testing.assert_array_equal(gt.frame_ids, np.arange(1000))
    np.testing.assert_array_equal(gt.stamps_ns, np.arange(1000) * PERIOD_30HZ_NS)
    for frame_id in range(0, 1000, 37):
        raw = np.loadtxt(sevenscenes_dir / f"frame-{frame_id:06d}.pose.txt")
        np.testing.assert_array_equal(gt.poses[frame_id][:3, 3], raw[:3, 3])
        # rotations are written with ~1e-4 error and projected onto SO(3) on reading
        np.testing.assert_allclose(gt.poses[frame_id][:3, :3], raw[:3, :3], atol=1e-3)


def test_sevenscenes_frames_placed_with_ground_truth_agree(sevenscenes: SevenScenes) -> None:
    gt = sevenscenes.ground_truth()
    a = sevenscenes.frame(0).points_world(gt.poses[0])[::5]
    b = sevenscenes.frame(30).points_world(gt.poses[30])[::5]
    median_m = float(np.median(cKDTree(a).query(b)[0]))
    assert median_m < 0.015, f"frames 0 and 30 under ground truth: median NN distance {median_m:.4f} m"


def test_sevenscenes_slicing_keeps_the_data_set_frame_numbers(sevenscenes_dir: Path) -> None:
    src = open_source(sevenscenes_dir, frames="10:20:2")
    assert src.frame_ids() == [10, 12, 14, 16, 18]
    frames = list(src)
    assert [f.frame_id for f in frames] == [10, 12, 14, 16, 18]
    assert [f.stamp_ns for f in frames] == [i * PERIOD_30HZ_NS for i in (10, 12, 14, 16, 18)]
    assert src.ground_truth().frame_ids.tolist() == [10, 12, 14, 16, 18]
    assert src.frame(1).frame_id == 12


def test_sevenscenes_poses_from_ground_truth(sevenscenes_dir: Path, sevenscenes: SevenScenes) -> None:
    src = open_source(sevenscenes_dir, frames="640:641", poses_from_ground_truth=True)
    frame = src.frame(0)
    assert frame.pose.source is PoseSource.GROUND_TRUTH
    np.testing.assert_array_equal(frame.T_world_sensor, sevenscenes.ground_truth().poses[640])


def test_sevenscenes_rejects_colour_and_a_wrong_depth_scale(sevenscenes_dir: Path) -> None:
    with pytest.raises(SourceError, match="not registered"):
        open_source(sevenscenes_dir, color=True)
    with pytest.raises(DepthScaleError) as info:
        open_source(sevenscenes_dir, depth_scale=5000.0).frame(0)
    assert info.value.depth_scale_suggested == 1000.0


def test_sevenscenes_missing_pose_file_is_named(tmp_path: Path, sevenscenes_dir: Path) -> None:
    for frame_id in (0, 1):
        shutil.copy(_sevenscenes_png(sevenscenes_dir, frame_id), tmp_path)
    shutil.copy(sevenscenes_dir / "frame-000000.pose.txt", tmp_path)
    src = open_source(tmp_path)
    assert isinstance(src, SevenScenes)
    with pytest.raises(SourceError, match=r"frame-000001\.pose\.txt.*frame 1"):
        src.ground_truth()
    assert open_source(tmp_path, lenient=True).ground_truth().frame_ids.tolist() == [0]


def test_sevenscenes_missing_depth_image_is_named(tmp_path: Path, sevenscenes_dir: Path,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    """A sequence whose frame 1 has its pose (and colour) but no depth image: the source leaves it out, and
    reading -- and building -- a selection that spans it logs a warning naming the frame and the file."""
    from driftmap.pipeline.build import build

    folder = tmp_path / "seq"
    folder.mkdir()
    (folder / "camera-intrinsics.txt").symlink_to(sevenscenes_dir / "camera-intrinsics.txt")
    for i in range(6):
        for kind in ("depth.png", "pose.txt", "color.jpg"):
            if not (i == 1 and kind == "depth.png"):
                (folder / f"frame-{i:06d}.{kind}").symlink_to(sevenscenes_dir / f"frame-{i:06d}.{kind}")
    (folder / "frame-000004.depth.png").unlink()
    (folder / "frame-000004.pose.txt").unlink()
    (folder / "frame-000004.color.jpg").unlink()  # a gap in the numbering: frame 4 has no file at all
    src = SevenScenes(folder)
    missing = folder / "frame-000001.depth.png"
    assert src.frame_ids() == [0, 2, 3, 5] and src.missing_depth == [(1, missing), (4, folder / "frame-000004.depth.png")]

    def warnings() -> list[str]:
        return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "no depth image" in r.getMessage()]

    with caplog.at_level(logging.WARNING, logger="driftmap.sources.sevenscenes"):
        assert [f.frame_id for f in SevenScenes(folder, frames="1:3")] == [2, 3]  # the selection spans neither
        assert not warnings()
        result = build(folder, tmp_path / "store", poses_from_source=True, loop_closure=False)
    assert result.n_frames == 4
    (message,) = warnings()
    assert f"frame 1 ({missing} missing)" in message and "frame 4 (" in message and "2 frame(s)" in message


# ---- TUM RGB-D (built from real 7-Scenes frames) -----------------------------------------------------------------

TUM_START_S = 1305031102
TUM_GT_OFFSET_NS = 4_000_000  # ground truth rows 4 ms after each depth stamp (within the 20 ms tolerance)


def _tum_stamp_ns(k: int) -> int:
    # every third Kinect frame (~10 Hz), irregular by a few ms like real logs
    return TUM_START_S * 1_000_000_000 + k * 3 * PERIOD_30HZ_NS + (k % 3) * 1_000_000


def _build_tum(
    folder: Path, sevenscenes_dir: Path, frame_ids: tuple[int, ...], *, no_gt_for: int | None = None
) -> Path:
    """A TUM RGB-D folder from 7-Scenes frames: depth in 1/5000 m units, depth.txt, groundtruth.txt."""
    (folder / "depth").mkdir(parents=True)
    depth_lines, gt_stamps, gt_poses = ["# depth maps", "# timestamp filename"], [], []
    for k, frame_id in enumerate(frame_ids):
        mm = _png(_sevenscenes_png(sevenscenes_dir, frame_id)).astype(np.uint32)
        codes = np.where(mm == 65535, 0, mm * 5)
        assert codes.max() < 65535
        stamp = _tum_stamp_ns(k)
        name = f"depth/{stamp // 10**9}.{stamp % 10**9:09d}.png"
        Image.fromarray(codes.astype(np.uint16)).save(folder / name)
        depth_lines.append(f"{stamp // 10**9}.{stamp % 10**9:09d} {name}")
        if k != no_gt_for:
            T = np.loadtxt(sevenscenes_dir / f"frame-{frame_id:06d}.pose.txt")
            gt_stamps += [stamp - 30_000_000, stamp + TUM_GT_OFFSET_NS]  # a farther row 30 ms before
            gt_poses += [np.eye(4), T]
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    write_tum(folder / "groundtruth.txt", Trajectory(np.array(gt_stamps, dtype=np.int64), np.array(gt_poses)))
    return folder


TUM_FRAMES = (0, 33, 250, 640, 850)


@pytest.fixture(scope="module")
def tum_dir(tmp_path_factory: pytest.TempPathFactory, sevenscenes_dir: Path) -> Path:
    return _build_tum(tmp_path_factory.mktemp("tum") / "from_7scenes", sevenscenes_dir, TUM_FRAMES, no_gt_for=3)


def test_tum_frames_equal_the_sevenscenes_frames(tum_dir: Path, sevenscenes: SevenScenes) -> None:
    src = open_source(tum_dir, intrinsics=(585.0, 585.0, 320.0, 240.0), max_depth_m=4.0)
    assert isinstance(src, TumRgbd)
    assert src.frame_ids() == list(range(len(TUM_FRAMES)))
    for k, frame in enumerate(src):
        expected = sevenscenes.frame(TUM_FRAMES[k])
        assert frame.frame_id == k and frame.stamp_ns == _tum_stamp_ns(k)
        assert frame.depth_scale == 5000.0 and frame.pose.source is PoseSource.NONE
        # mm / 1000 and (5 mm) / 5000 are the same real number: the float32 points agree exactly
        np.testing.assert_allclose(frame.points_sensor, expected.points_sensor, rtol=0, atol=1e-6)


def test_tum_ground_truth_round_trips_and_unmatched_frames_are_reported(
    tum_dir: Path, sevenscenes: SevenScenes
) -> None:
    src = open_source(tum_dir, intrinsics=(585.0, 585.0, 320.0, 240.0))
    assert src.frames_without_ground_truth == [3]
    gt = src.ground_truth()
    assert gt.frame_ids.tolist() == [0, 1, 2, 4]
    assert gt.stamps_ns.tolist() == [_tum_stamp_ns(k) for k in (0, 1, 2, 4)]
    expected = sevenscenes.ground_truth().poses[[TUM_FRAMES[k] for k in (0, 1, 2, 4)]]
    np.testing.assert_allclose(gt.poses, expected, atol=1e-6)
    # with the ground truth as the estimate, the frame without a match fails (lenient: is skipped)
    with pytest.raises(SourceError, match="no ground-truth pose within 20 ms of frame 3"):
        list(open_source(tum_dir, intrinsics=(585.0, 585.0, 320.0, 240.0), poses_from_ground_truth=True))
    lenient = open_source(tum_dir, intrinsics=(585.0, 585.0, 320.0, 240.0), poses_from_ground_truth=True, lenient=True)
    frames = list(lenient)
    assert [f.frame_id for f in frames] == [0, 1, 2, 4]
    assert all(f.pose.source is PoseSource.GROUND_TRUTH for f in frames)
    np.testing.assert_allclose(np.array([f.T_world_sensor for f in frames]), expected, atol=1e-6)


def test_tum_intrinsics_defaults(tum_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    assert tum_setup("rgbd_dataset_freiburg2_desk") == "fr2" and tum_setup("fr3_office") == "fr3"
    assert tum_setup("from_7scenes") is None
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.tum"):
        src = open_source(tum_dir)
    assert src.intrinsics == TUM_GENERIC_INTRINSICS
    assert "525/525/319.5/239.5" in caplog.text
    assert open_source(tum_dir, intrinsics="fr1").intrinsics == TUM_INTRINSICS["fr1"]


def test_tum_wrong_depth_scale_is_caught(tum_dir: Path) -> None:
    with pytest.raises(DepthScaleError) as info:
        open_source(tum_dir, intrinsics=(585.0, 585.0, 320.0, 240.0), depth_scale=1000.0).frame(0)
    assert info.value.depth_scale_suggested == 5000.0


def test_tum_duplicate_stamp_names_the_file_and_both_frames(tmp_path: Path, tum_dir: Path) -> None:
    folder = tmp_path / "dup"
    shutil.copytree(tum_dir, folder)
    lines = (folder / "depth.txt").read_text().splitlines()
    stamp_1 = lines[3].split()[0]  # data rows start after 2 comment lines
    lines[4] = f"{stamp_1} {lines[4].split()[1]}"
    (folder / "depth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(SourceError, match=r"depth\.txt: duplicate stamp: frame 2 .* frame 1"):
        open_source(folder)
    src = open_source(folder, lenient=True, intrinsics=(585.0, 585.0, 320.0, 240.0))
    assert src.frame_ids() == [0, 1, 3, 4]
    assert len(src.skipped) == 1 and "frame 2" in src.skipped[0][1]


# ---- KITTI ---------------------------------------------------------------------------------------------------------


def _tr(kitti_dir: Path) -> np.ndarray:
    line = next(line for line in (kitti_dir / "calib.txt").read_text().splitlines() if line.startswith("Tr:"))
    Tr = np.eye(4)
    Tr[:3, :] = np.array(line.split()[1:], dtype=float).reshape(3, 4)
    return Tr


def test_kitti_frames_are_the_raw_scans(kitti_dir: Path) -> None:
    src = open_source(kitti_dir)
    assert src.frame_ids() == list(range(16))
    times_s = np.loadtxt(kitti_dir / "times.txt")
    for frame_id in (0, 7, 15):
        frame = src.frame(frame_id)
        raw = np.fromfile(kitti_dir / "velodyne" / f"{frame_id:06d}.bin", dtype=np.float32).reshape(-1, 4)
        np.testing.assert_array_equal(frame.points_sensor, raw[:, :3])
        np.testing.assert_array_equal(frame.attributes.intensity, raw[:, 3])
        assert frame.frame_id == frame_id and frame.sensor_kind is SensorKind.LIDAR
        assert abs(frame.stamp_ns - times_s[frame_id] * 1e9) < 1
        assert frame.pose.source is PoseSource.NONE


def test_kitti_ground_truth_is_cam0_converted_to_velodyne(kitti_dir: Path, trajectories_dir: Path) -> None:
    gt = open_source(kitti_dir).ground_truth()
    assert gt.frame_ids.tolist() == list(range(16))
    Tr = _tr(kitti_dir)
    full = read_kitti(trajectories_dir / "KITTI_00_gt.txt")
    expected = np.linalg.inv(Tr) @ full.poses[:16] @ Tr
    np.testing.assert_allclose(gt.poses, expected, atol=1e-5)
    travel_m = float(np.sum(np.linalg.norm(np.diff(gt.positions_m, axis=0), axis=1)))
    assert abs(travel_m - 12.9) < 0.05, travel_m
    # the Velodyne ground truth moves forward along the Velodyne x axis (cam0 z): the conversion is applied
    assert gt.positions_m[-1, 0] > 12.0


def test_kitti_poses_from_ground_truth(kitti_dir: Path) -> None:
    src = open_source(kitti_dir, frames="3:5", poses_from_ground_truth=True)
    frame = src.frame(1)
    assert frame.frame_id == 4 and frame.pose.source is PoseSource.GROUND_TRUTH
    np.testing.assert_array_equal(frame.T_world_sensor, src.ground_truth().poses[1])


def _small_kitti(folder: Path, kitti_dir: Path, n: int = 3) -> Path:
    (folder / "velodyne").mkdir(parents=True)
    for k in range(n):
        shutil.copy(kitti_dir / "velodyne" / f"{k:06d}.bin", folder / "velodyne")
    shutil.copy(kitti_dir / "calib.txt", folder)
    (folder / "times.txt").write_text("\n".join((kitti_dir / "times.txt").read_text().splitlines()[:n]) + "\n")
    (folder / "poses.txt").write_text("\n".join((kitti_dir / "poses.txt").read_text().splitlines()[:n]) + "\n")
    return folder


def test_kitti_truncated_scan_raises_and_is_skipped_when_lenient(tmp_path: Path, kitti_dir: Path) -> None:
    folder = _small_kitti(tmp_path / "seq", kitti_dir)
    bad = folder / "velodyne" / "000001.bin"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) - 6])
    with pytest.raises(SourceError, match=r"000001\.bin: size .* not a positive multiple of 16"):
        list(open_source(folder))
    src = open_source(folder, lenient=True)
    assert [f.frame_id for f in src] == [0, 2]
    assert len(src.skipped) == 1 and "000001.bin" in src.skipped[0][1]


def test_kitti_short_pose_file_names_the_first_frame_without_a_pose(tmp_path: Path, kitti_dir: Path) -> None:
    folder = _small_kitti(tmp_path / "seq", kitti_dir)
    lines = (folder / "poses.txt").read_text().splitlines()
    (folder / "poses.txt").write_text("\n".join(lines[:2]) + "\n")
    expected = r"poses\.txt: 2 pose rows for 3 frames; the first frame without a pose is frame 2"
    with pytest.raises(SourceError, match=expected):  # the scans' poses would come from it: an error
        open_source(folder, poses_from_ground_truth=True)
    assert open_source(folder, lenient=True).ground_truth().frame_ids.tolist() == [0, 1]
    # ground truth nobody asked to place the scans with: a warning, the scans are read (odometry builds work)
    assert open_source(folder).ground_truth().frame_ids.tolist() == [0, 1]


def test_kitti_without_calibration_reads_the_scans_and_drops_nan_points(tmp_path: Path, kitti_dir: Path,
                                                                       caplog: pytest.LogCaptureFixture) -> None:
    import logging

    folder = _small_kitti(tmp_path / "seq", kitti_dir)
    (folder / "calib.txt").unlink()
    with pytest.raises(SourceError, match=r"calib\.txt: calibration not found"):
        open_source(folder, poses_from_ground_truth=True)
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.kitti"):
        src = open_source(folder)
    assert src.ground_truth() is None and any("without ground truth" in r.getMessage() for r in caplog.records)
    full = src.frame(1).points_sensor
    bin1 = folder / "velodyne" / "000001.bin"
    scan = np.fromfile(bin1, dtype="<f4").reshape(-1, 4)
    scan[[5, 17], 1] = [np.nan, np.inf]
    bin1.unlink()  # a symlink or a copy: write a file of our own
    scan.tofile(bin1)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.kitti"):
        frame = open_source(folder).frame(1)
    assert np.array_equal(frame.points_sensor, np.delete(full, [5, 17], axis=0))
    assert len(frame.attributes.intensity) == len(frame.points_sensor)
    assert any("000001.bin: frame 1: 2 of" in r.getMessage() for r in caplog.records)


def test_kitti_non_monotonic_times_name_the_file_and_frames(tmp_path: Path, kitti_dir: Path) -> None:
    folder = _small_kitti(tmp_path / "seq", kitti_dir)
    rows = (folder / "times.txt").read_text().splitlines()
    rows[1], rows[2] = rows[2], rows[1]
    (folder / "times.txt").write_text("\n".join(rows) + "\n")
    with pytest.raises(SourceError, match=r"times\.txt: stamp goes back in time: frame 2 .* frame 1"):
        open_source(folder)
    assert open_source(folder, lenient=True).frame_ids() == [0, 1]


def test_missing_folder_is_named(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such file or folder"):
        open_source(tmp_path / "nope")
    with pytest.raises(SourceError, match=r"velodyne: no such folder"):
        open_source(tmp_path, format="kitti")


# ---- Redwood / ICL-NUIM --------------------------------------------------------------------------------------------

ICL_K = PinholeIntrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)


def test_icl_frames_with_odometry_estimate_and_ground_truth(icl_dir: Path) -> None:
    src = open_source(icl_dir)
    assert src.frame_ids() == [0, 1, 2, 3, 4]
    assert src.intrinsics == ICL_K  # from camera_primesense.json (column-major)
    odometry = read_redwood_log(icl_dir / "odometry.log")
    truth = read_redwood_log(icl_dir / "trajectory.log")
    frames = list(src)
    for k, frame in enumerate(frames):
        png = icl_dir / "depth" / f"{k:05d}.png"
        expected = driftmap.backproject(_png(png), ICL_K, depth_scale=1000.0, min_depth_m=0.2, max_depth_m=5.0)
        np.testing.assert_array_equal(frame.points_sensor, expected.points)
        assert frame.frame_id == k and frame.stamp_ns == k * PERIOD_30HZ_NS and frame.depth_scale == 1000.0
        assert frame.pose.source is PoseSource.ODOMETRY
        np.testing.assert_array_equal(frame.T_world_sensor, odometry.poses[k])
    gt = src.ground_truth()
    assert gt.frame_ids.tolist() == [0, 1, 2, 3, 4]
    np.testing.assert_array_equal(gt.poses, truth.poses)
    assert not np.allclose(gt.poses, odometry.poses, atol=1e-2), "the estimate must not be the ground truth"
    with_gt = open_source(icl_dir, frames="2:3", poses_from_ground_truth=True).frame(0)
    assert with_gt.pose.source is PoseSource.GROUND_TRUTH
    np.testing.assert_array_equal(with_gt.T_world_sensor, truth.poses[2])


def test_icl_depth_is_millimetres(icl_dir: Path) -> None:
    # 1000 units/m makes frames 0 and 4 agree best under the ground truth
    spread = {}
    for scale in (800.0, 1000.0, 1250.0):
        src = open_source(icl_dir, depth_scale=scale, sensor_range_m=None)
        gt = src.ground_truth().poses
        a, b = src.frame(0).points_world(gt[0])[::7], src.frame(4).points_world(gt[4])[::7]
        spread[scale] = float(np.median(cKDTree(a).query(b)[0]))
    assert spread[1000.0] < 0.01 and spread[1000.0] < min(spread[800.0], spread[1250.0]), spread
    # TUM's 5000 puts this room at 0.2-0.5 m, which a Kinect-class camera cannot see: caught, not accepted
    with pytest.raises(DepthScaleError, match="suggests depth_scale=1000") as info:
        open_source(icl_dir, depth_scale=5000.0).frame(0)
    assert info.value.depth_scale_used == 5000.0 and info.value.depth_scale_suggested == 1000.0
    with pytest.raises(DepthScaleError):  # millimetres read as metres
        open_source(icl_dir, depth_scale=1.0).frame(0)


def test_icl_colour_is_attached_per_point(icl_dir: Path) -> None:
    frame = open_source(icl_dir, frames="1:2", color=True).frame(0)
    result = driftmap.backproject(_png(icl_dir / "depth" / "00001.png"), ICL_K, min_depth_m=0.2, max_depth_m=5.0)
    colour = np.asarray(Image.open(icl_dir / "color" / "00001.jpg").convert("RGB")).reshape(-1, 3)
    np.testing.assert_array_equal(frame.attributes.color_rgb, colour[result.pixel_index])


def test_row_major_intrinsics_json_is_rejected(tmp_path: Path, icl_dir: Path) -> None:
    folder = tmp_path / "icl"
    shutil.copytree(icl_dir, folder)
    (folder / "camera_primesense.json").write_text(
        json.dumps({"width": 640, "height": 480, "intrinsic_matrix": [525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1]})
    )
    with pytest.raises(SourceError, match="column-major"):
        open_source(folder)


# ---- folders of PLY / PCD scans ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def kitti_clouds(kitti_dir: Path) -> dict[int, np.ndarray]:
    """Real KITTI points (every 20th point of three scans), keyed by the number used in the file name."""
    scans = {}
    for number, k in ((2, 0), (10, 1), (7, 2)):
        scans[number] = np.fromfile(kitti_dir / "velodyne" / f"{k:06d}.bin", dtype=np.float32).reshape(-1, 4)[::20]
    return scans


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_cloud_folder_round_trip(tmp_path: Path, kitti_clouds: dict[int, np.ndarray], suffix: str) -> None:
    for number, scan in kitti_clouds.items():
        cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(scan[:, :3].copy()))
        cloud.point["intensity"] = o3d.core.Tensor(scan[:, 3:4].copy())
        assert o3d.t.io.write_point_cloud(str(tmp_path / f"scan_{number}{suffix}"), cloud)
    src = open_source(tmp_path)
    assert isinstance(src, CloudFolder)
    assert src.frame_ids() == [2, 7, 10]  # by number, not by name
    for frame in src:
        scan = kitti_clouds[frame.frame_id]
        np.testing.assert_array_equal(frame.points_sensor, scan[:, :3])
        np.testing.assert_array_equal(frame.attributes.intensity, scan[:, 3])
        assert frame.sensor_kind is SensorKind.LIDAR and frame.pose.source is PoseSource.NONE
        assert frame.stamp_ns == frame.frame_id * 100_000_000
    assert open_source(tmp_path, sensor_kind="depth_camera").frame(0).sensor_kind is SensorKind.DEPTH_CAMERA


def test_cloud_folder_pose_file_is_the_estimate(
    tmp_path: Path, kitti_clouds: dict[int, np.ndarray], kitti_dir: Path
) -> None:
    clouds = tmp_path / "clouds"
    clouds.mkdir()
    for number, scan in kitti_clouds.items():
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan[:, :3].astype(np.float64)))
        o3d.io.write_point_cloud(str(clouds / f"{number:04d}.pcd"), pcd)
    poses = read_kitti(kitti_dir / "poses.txt").poses[:3]
    stamps = np.array([1_000_000_000, 1_100_000_000, 1_200_000_000], dtype=np.int64)
    write_tum(tmp_path / "poses_tum.txt", Trajectory(stamps, poses))
    src = open_source(clouds, poses=tmp_path / "poses_tum.txt")
    frames = list(src)
    assert [f.stamp_ns for f in frames] == stamps.tolist()  # TUM stamps become the frame stamps
    assert all(f.pose.source is PoseSource.LOG for f in frames)
    np.testing.assert_allclose(np.array([f.T_world_sensor for f in frames]), poses, atol=1e-6)
    write_kitti(tmp_path / "poses_kitti.txt", Trajectory(np.arange(3), poses))
    frames = list(open_source(clouds, poses=tmp_path / "poses_kitti.txt"))
    assert [f.stamp_ns for f in frames] == [n * 100_000_000 for n in (2, 7, 10)]  # KITTI rows carry no time
    write_kitti(tmp_path / "short.txt", Trajectory(np.arange(2), poses[:2]))
    expected = r"short\.txt: 2 poses for 3 clouds; the first cloud without a pose is 0010\.pcd"
    with pytest.raises(SourceError, match=expected):
        open_source(clouds, poses=tmp_path / "short.txt")


def test_cloud_folder_bad_input(tmp_path: Path) -> None:
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ones((4, 3), np.float32)))
    o3d.t.io.write_point_cloud(str(tmp_path / "scan_1.ply"), cloud)
    o3d.t.io.write_point_cloud(str(tmp_path / "scan_01.pcd"), cloud)
    with pytest.raises(SourceError, match=r"scan_01\.pcd and .*scan_1\.ply: both are frame 1"):
        open_source(tmp_path)
    (tmp_path / "scan_01.pcd").unlink()
    (tmp_path / "scan_2.ply").write_text("not a ply file")
    with pytest.raises(SourceError, match=r"scan_2\.ply: no points could be read"):
        list(open_source(tmp_path))
    assert [f.frame_id for f in open_source(tmp_path, lenient=True)] == [1]


# ---- cloud folders: normals, stamps and per-point times are checked against the data ---------------------------------


def _balm_csv_stamps_ns(balm_dir: Path) -> list[int]:
    """The last entry of every 4th line of alidarPose.csv, seconds as written -> ns (Decimal, not the reader)."""
    lines = [line for line in (balm_dir / "alidarPose.csv").read_text().splitlines() if line.strip()]
    return [int(Decimal(line.rstrip(",").split(",")[3]) * 10**9) for line in lines[3::4]]


def test_balm_frames_are_stamped_from_alidarpose_csv_and_not_posed_by_it(balm_dir: Path) -> None:
    src = open_source(balm_dir)
    assert isinstance(src, CloudFolder) and src.describe()["stamps"] == "alidarPose.csv"
    assert src.frame_ids() == list(range(80))  # full0 .. full79 by number, not by name (full10 after full9)
    stamps = np.array(src.stamps_ns())
    expected = np.array(_balm_csv_stamps_ns(balm_dir))
    assert len(expected) == 80 and np.abs(stamps - expected).max() <= 1_000  # within 1 us (exact, in fact)
    steps_s = np.diff(stamps) / 1e9
    assert 0.45 < steps_s.min() and steps_s.max() < 0.55  # 2 Hz, not the 10 Hz assumed for folders without stamps
    assert src.frame(0).pose.source is PoseSource.NONE  # the csv gives the stamps only: poses need poses= / --poses


def test_balm_zero_normals_are_not_used(balm_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.point_fields"):
        frame = open_source(balm_dir, frames="3:4").frame(0)
    assert frame.attributes.normal_sensor is None and frame.attributes.intensity is not None
    cloud = o3d.t.io.read_point_cloud(str(balm_dir / "full3.pcd"))
    n = len(cloud.point["positions"])
    assert not cloud.point["normals"].numpy().any()  # the file really holds all-zero normals
    (message,) = [r.getMessage() for r in caplog.records]
    assert f"full3.pcd (frame 3): normals not used ({n} of {n} are unusable: {n} zero, 0 NaN/inf, 0 not unit" in message


def _unit_normals(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
@pytest.mark.parametrize("variant", ["unit", "nan", "not_unit", "zero"])
def test_cloud_folder_normals_are_used_only_when_all_are_unit_vectors(
    tmp_path: Path, suffix: str, variant: str, caplog: pytest.LogCaptureFixture
) -> None:
    rng = np.random.default_rng(5)
    n = 200
    normals = _unit_normals(rng, n)
    if variant == "nan":
        normals[10] = np.nan
    elif variant == "not_unit":
        normals[:100] *= 0.5
    elif variant == "zero":
        normals[20:30] = 0.0
    names = ("normal_x", "normal_y", "normal_z") if suffix == ".pcd" else ("nx", "ny", "nz")
    columns = xyz_columns(rng, n) | {name: normals[:, k].copy() for k, name in enumerate(names)}
    (write_pcd if suffix == ".pcd" else write_ply)(tmp_path / f"scan_0{suffix}", columns)
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.point_fields"):
        frame = open_source(tmp_path, period_ns=100_000_000).frame(0)
    if variant == "unit":
        assert frame.attributes.normal_sensor.tobytes() == normals.tobytes()  # kept bit-exact
        assert not caplog.records
        return
    assert frame.attributes.normal_sensor is None
    counts = {"nan": "1 of 200 are unusable: 0 zero, 1 NaN/inf, 0 not unit",
              "not_unit": "100 of 200 are unusable: 0 zero, 0 NaN/inf, 100 not unit",
              "zero": "10 of 200 are unusable: 10 zero, 0 NaN/inf, 0 not unit"}[variant]
    (message,) = [r.getMessage() for r in caplog.records]
    assert f"scan_0{suffix} (frame 0): normals not used ({counts}" in message


def _scan(path: Path, rng: np.random.Generator, n: int = 50, **extra: np.ndarray) -> Path:
    return write_pcd(path, xyz_columns(rng, n) | extra)


@pytest.mark.parametrize(
    ("names", "unit", "stamps_ns"),
    [
        (["1630577758.569490", "1630577759.068947", "1630577759.568717"], "s",
         [1630577758_569490000, 1630577759_068947000, 1630577759_568717000]),
        (["1630577758569", "1630577758669", "1630577758770"], "ms",
         [1630577758_569000000, 1630577758_669000000, 1630577758_770000000]),
        (["1630577758569490", "1630577758669490", "1630577758769491"], "us",
         [1630577758_569490000, 1630577758_669490000, 1630577758_769491000]),
        (["lidar_1630577758569490123", "lidar_1630577758669490123", "lidar_1630577758769490124"], "ns",
         [1630577758_569490123, 1630577758_669490123, 1630577758_769490124]),
    ],
    ids=["s", "ms", "us", "ns"],
)
def test_cloud_file_names_that_are_stamps_stamp_the_frames(tmp_path: Path, names: list[str], unit: str,
                                                           stamps_ns: list[int]) -> None:
    rng = np.random.default_rng(1)
    for name in reversed(names):
        _scan(tmp_path / f"{name}.pcd", rng)
    src = open_source(tmp_path)
    assert src.describe()["stamps"] == f"file names ({unit})"
    assert src.stamps_ns() == stamps_ns  # exact
    assert src.frame_ids() == [0, 1, 2]  # the index in stamp order (the names are not frame numbers)
    assert [Path(f.provenance.source_uri).stem for f in src] == names


def test_cloud_file_names_that_are_not_stamps_are_frame_numbers(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(2)
    for n in (123, 124, 126):  # frame numbers, far below any epoch time
        _scan(tmp_path / f"{n:06d}.pcd", rng)
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.cloud_folder"):
        src = open_source(tmp_path)
    assert src.frame_ids() == [123, 124, 126] and src.describe()["stamps"] == "assumed 10 Hz"
    assert src.stamps_ns() == [123 * 100_000_000, 124 * 100_000_000, 126 * 100_000_000]
    (message,) = [r.getMessage() for r in caplog.records]
    assert "no stamps in the folder; they are assumed" in message and "times.txt" in message and "--period-s" in message
    # epoch-sized numbers 1 us apart are not the stamps of a sensor's frames (the period must be 1 ms .. 10 s)
    other = tmp_path / "us"
    other.mkdir()
    for k in range(3):
        _scan(other / f"{1630577758569490 + k}.pcd", rng)
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.stamps"):
        assert open_source(other, period_ns=50_000_000).describe()["stamps"].startswith("period 0.05 s")
    assert any("look like stamps in us, but their median step is 1e-06 s" in r.getMessage() for r in caplog.records)
    # two names that are the same stamp are named, not silently merged
    same = tmp_path / "same"
    same.mkdir()
    _scan(same / "1630577758.5.pcd", rng)
    _scan(same / "1630577758.500.pcd", rng)
    with pytest.raises(SourceError, match=r"1630577758\.5\.pcd and .*1630577758\.500\.pcd: both file names are the stamp"):
        open_source(same)


def test_cloud_folder_stamp_precedence(tmp_path: Path, kitti_dir: Path) -> None:
    """(a) a pose file given with poses= that has stamps > (b) names > (c) times.txt > (d) a 4x4 pose file with stamps
    in the folder > (e) period_ns > (f) the nominal 10 Hz; period_ns is refused when the folder has stamps."""
    rng = np.random.default_rng(3)
    folder = tmp_path / "clouds"
    folder.mkdir()
    for n in range(4):
        _scan(folder / f"scan_{n}.pcd", rng)
    assert open_source(folder).describe()["stamps"] == "assumed 10 Hz"
    src = open_source(folder, period_ns=500_000_000)
    assert src.describe()["stamps"] == "period 0.5 s (period_ns / --period-s)"
    assert src.stamps_ns() == [0, 500_000_000, 1_000_000_000, 1_500_000_000]
    # (d): a BALM-style 4x4 file with stamps (comma-separated, trailing commas)
    poses = read_kitti(kitti_dir / "poses.txt").poses[:4]
    blocks = [f"{1630577700 + k}.25" for k in range(4)]
    (folder / "lidarPose.csv").write_text("".join(
        "".join(",".join(f"{v:.6f}" for v in T[i]) + ",\n" for i in range(3)) + f"0,0,0,{s},\n" for T, s in zip(poses, blocks)))
    src = open_source(folder)
    assert src.describe()["stamps"] == "lidarPose.csv" and src.frame(0).pose.source is PoseSource.NONE
    assert src.stamps_ns() == [(1630577700 + k) * 10**9 + 250_000_000 for k in range(4)]
    with pytest.raises(ConfigError, match=r"period_ns=500000000 \(--period-s 0\.5\): .* has stamps of its own \(lidarPose\.csv\)"):
        open_source(folder, period_ns=500_000_000)
    # (c) beats (d)
    (folder / "times.txt").write_text("".join(f"{0.1 * k:.6e}\n" for k in range(4)))
    src = open_source(folder)
    assert src.describe()["stamps"] == "times.txt"
    assert src.stamps_ns() == [0, 100_000_000, 200_000_000, 300_000_000]
    # (a) beats them all
    tum_stamps = np.array([5, 6, 7, 8], dtype=np.int64) * 1_000_000_000
    write_tum(tmp_path / "p.tum", Trajectory(tum_stamps, poses))
    src = open_source(folder, poses=tmp_path / "p.tum")
    assert src.describe()["stamps"] == "p.tum" and src.stamps_ns() == tum_stamps.tolist()
    # (b) beats (c) and (d)
    for n in range(4):
        (folder / f"scan_{n}.pcd").rename(folder / f"{1630577800 + n}.100.pcd")
    assert open_source(folder).describe()["stamps"] == "file names (s)"


def test_cloud_folder_stamp_file_must_fit_the_clouds(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    for n in (2, 3, 4):
        _scan(tmp_path / f"{n:06d}.pcd", rng)
    times = tmp_path / "times.txt"
    times.write_text("0.0\n0.1\n")
    with pytest.raises(SourceError, match=r"times\.txt: 2 stamps for 3 clouds \(frames 2\.\.4\)"):
        open_source(tmp_path)
    times.write_text("".join(f"{0.1 * k:.1f}\n" for k in range(10)))  # the whole sequence: row n = frame n
    src = open_source(tmp_path)
    assert src.stamps_ns() == [200_000_000, 300_000_000, 400_000_000]
    times.write_text("0\n100\n200\n")  # milliseconds, not seconds
    with pytest.raises(SourceError, match=r"times\.txt: read as seconds, .* median step is 100 s, outside"):
        open_source(tmp_path)
    times.write_text("0.0\n0.2\n0.1\n")
    with pytest.raises(SourceError, match=r"times\.txt .*stamp goes back in time: frame 4 .* frame 3"):
        open_source(tmp_path)


#: (field, values written, the offsets in ns they must become); the scan is stamped 1630577758.5 s
_STAMP_S = "1630577758.5"
_STAMP_NS = 1630577758_500_000_000
_OFFSETS_NS = np.arange(0, 100, dtype=np.int64) * 1_953_125  # multiples of 2^-9 s: exact in float32 seconds
TIME_FIELDS = {
    "livox_offset_time": ("offset_time", _OFFSETS_NS.astype(np.uint32), _OFFSETS_NS),
    "ouster_t": ("t", _OFFSETS_NS.astype(np.uint32), _OFFSETS_NS),
    "velodyne_time": ("time", (-_OFFSETS_NS[::-1] / 1e9).astype(np.float32), -_OFFSETS_NS[::-1]),  # before the stamp
    "hesai_timestamp": ("timestamp", (1630577758.5 + _OFFSETS_NS / 1e9).astype(np.float64), _OFFSETS_NS),  # absolute
}


@pytest.mark.parametrize("variant", sorted(TIME_FIELDS))
def test_cloud_folder_per_point_times_become_time_offsets(tmp_path: Path, variant: str) -> None:
    field, values, expected = TIME_FIELDS[variant]
    rng = np.random.default_rng(6)
    _scan(tmp_path / "scan_0.pcd", rng, n=len(values), **{field: values})
    (tmp_path / "times.txt").write_text(_STAMP_S + "\n")
    frame = open_source(tmp_path).frame(0)
    assert frame.stamp_ns == _STAMP_NS
    assert frame.attributes.time_offset_ns.dtype == np.int64
    np.testing.assert_array_equal(frame.attributes.time_offset_ns, expected)  # exactly


@pytest.mark.parametrize("variant", ["span", "nan", "absolute_without_stamps", "ply_uint"])
def test_cloud_folder_implausible_time_field_is_not_used(tmp_path: Path, variant: str,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(7)
    n = 100
    if variant == "span":  # 5 s of "offsets" in one scan
        _scan(tmp_path / "scan_0.pcd", rng, n=n, time=np.linspace(0, 5, n).astype(np.float32))
    elif variant == "nan":
        t = np.linspace(0, 0.1, n).astype(np.float32)
        t[3] = np.nan
        _scan(tmp_path / "scan_0.pcd", rng, n=n, time=t)
    elif variant == "absolute_without_stamps":  # epoch seconds, but the folder's stamps are only assumed
        _scan(tmp_path / "scan_0.pcd", rng, n=n, timestamp=1630577758.5 + np.linspace(0, 0.1, n))
    else:  # a PLY uint property Open3D's reader skips
        write_ply(tmp_path / "scan_0.ply", xyz_columns(rng, n) | {"t": np.arange(n, dtype=np.uint32) * 1000})
    with caplog.at_level(logging.WARNING, logger="driftmap.sources"):
        frame = open_source(tmp_path, period_ns=100_000_000).frame(0)
    assert frame.attributes.time_offset_ns is None
    field = {"span": "time", "nan": "time", "absolute_without_stamps": "timestamp", "ply_uint": "t"}[variant]
    messages = [r.getMessage() for r in caplog.records if "per-point time" in r.getMessage()]
    assert len(messages) == 1 and "scan_0" in messages[0] and "(frame 0)" in messages[0]
    assert f"field {field!r} not used" in messages[0] or f"property {field!r} not used" in messages[0]


# ---- trajectory readers ------------------------------------------------------------------------------------------


def _quat_wxyz_to_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    """Hamilton unit quaternion (w first) -> rotation matrix, written out (independent of scipy's ordering)."""
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def test_euroc_reader_handles_the_wxyz_quaternion(trajectories_dir: Path) -> None:
    from evo.tools import file_interface

    path = trajectories_dir / "V102_groundtruth.csv"
    assert detect_trajectory_format(path) == "euroc"
    traj = read_trajectory(path)
    # a known row: the first one
    assert traj.stamps_ns[0] == 1403715524907143168
    np.testing.assert_array_equal(traj.poses[0][:3, 3], [0.515356, 1.996773, 0.971104])
    q = np.array([0.161996, 0.789985, -0.205376, 0.554528])
    np.testing.assert_allclose(traj.poses[0][:3, :3], _quat_wxyz_to_matrix(*(q / np.linalg.norm(q))), atol=1e-12)
    reference = file_interface.read_euroc_csv_trajectory(str(path))
    assert len(traj) == reference.num_poses == 16702
    np.testing.assert_allclose(traj.poses, np.array(reference.poses_se3), atol=1e-9)
    assert read_euroc(path).stamps_ns[-1] == traj.stamps_ns[-1]


def test_tum_and_kitti_readers_agree_with_evo(trajectories_dir: Path) -> None:
    from evo.tools import file_interface

    tum = trajectories_dir / "fr2_desk_groundtruth.txt"
    traj = read_trajectory(tum)
    reference = file_interface.read_tum_trajectory_file(str(tum))
    assert len(traj) == reference.num_poses
    np.testing.assert_allclose(traj.poses, np.array(reference.poses_se3), atol=1e-9)
    assert traj.stamps_ns[0] == 1311868163_869700000  # exact: "1311868163.8697"
    kitti = trajectories_dir / "KITTI_00_gt.txt"
    traj = read_trajectory(kitti)
    assert detect_trajectory_format(kitti) == "kitti" and len(traj) == 4541
    reference = file_interface.read_kitti_poses_file(str(kitti))
    np.testing.assert_allclose(traj.poses, np.array(reference.poses_se3), atol=1e-12)
    np.testing.assert_array_equal(traj.poses[1][:3, 3], [-4.690294e-02, -2.839928e-02, 8.586941e-01])


def test_redwood_log_reader_and_detection_errors(icl_dir: Path, trajectories_dir: Path, tmp_path: Path) -> None:
    traj = read_trajectory(icl_dir / "trajectory.log")
    assert traj.frame_ids.tolist() == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(traj.poses[0][:3, 3], [-0.31057997014702826, 0.5730122438481298, 2.1264800183565487])
    with pytest.raises(SourceError, match="1 fields") as info:
        read_trajectory(trajectories_dir / "KITTI_00_gt_times.txt")
    for name in ("tum", "kitti", "euroc", "redwood"):
        assert f"{name}:" in str(info.value)
    broken = tmp_path / "broken.log"
    broken.write_text("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(SourceError, match="multiple of 5"):
        read_redwood_log(broken)
