"""The frame KITTI pose files are read in on a store of KITTI Velodyne scans.

A KITTI data set's own ``poses.txt`` holds left-camera (cam0) poses; the store holds ``T_world_velo``. ``build
--poses``, ``correct --format kitti`` and ``diagnose --gt-format kitti`` must all convert that file
(``inv(Tr) @ T_cam0 @ Tr``) and take other KITTI files as Velodyne poses, unless told otherwise with
``--kitti-frame`` (one shared function: :func:`driftmap.sources.kitti.kitti_rows_as_velodyne`).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from driftmap import geometry
from driftmap.cli import app
from driftmap.errors import ConfigError
from driftmap.pipeline.build import build
from driftmap.pipeline.pose_files import kitti_origin_of_store
from driftmap.sources.kitti import read_calib_tr, velo_poses_from_cam0
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import Trajectory, read_kitti, write_kitti

FRAMES = "0:16:3"  # frames 0, 3, 6, 9, 12, 15: small and fast, spans the 16 shared frames


@pytest.fixture(scope="module")
def velo_rows(kitti_dir: Path) -> np.ndarray:
    """The data set's cam0 ground truth converted to the Velodyne frame (every row)."""
    return velo_poses_from_cam0(read_kitti(kitti_dir / "poses.txt").poses, read_calib_tr(kitti_dir / "calib.txt"))


@pytest.fixture(scope="module")
def gt_store(kitti_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A store of KITTI scans built with the source's own (Velodyne-frame) ground truth, no loop closure."""
    out = tmp_path_factory.mktemp("kitti_frames") / "gt"
    build(kitti_dir, out, poses_from_source=True, frames=FRAMES, loop_closure=False)
    return out


@pytest.fixture
def store_copy(gt_store: Path, tmp_path: Path) -> Path:
    """A private copy of ``gt_store`` that a test may add revisions to."""
    return Path(shutil.copytree(gt_store, tmp_path / "store"))


def _diagnose(store: Path, gt: Path, out: Path, *extra: str) -> dict:
    result = CliRunner().invoke(app, ["diagnose", str(store), "--json", str(out), "--gt", str(gt), "--gt-format", "kitti",
                                      "--points-per-frame", "300", *extra])
    assert result.exit_code == 0, (result.output, result.exception)
    return json.loads(out.read_text())["trajectory"]


def test_diagnose_says_when_nothing_was_revisited(kitti_dir: Path, tmp_path: Path) -> None:
    """Scans 0-5 cover 4.3 m of road, less than the 10 m of travel that makes a second visit: no surface can be
    seen on two visits, so the between-visit smearing score is 0 and the output says why, while the
    frame-to-frame score still measures. (With every 3rd of the 16 frames, 13 m, some far surfaces are.)"""
    store = tmp_path / "short"
    build(kitti_dir, store, poses_from_source=True, frames="0:6", loop_closure=False)
    out = tmp_path / "d.json"
    result = CliRunner().invoke(app, ["diagnose", str(store), "--json", str(out)])
    assert result.exit_code == 0, (result.output, result.exception)
    data = json.loads(out.read_text())
    assert data["double_wall"]["voxels_evaluated"] > 100
    assert all(s["voxels_revisited"] == 0 for s in data["double_wall"]["per_scale"])
    assert data["smearing_score_m"] == 0.0 and data["smearing_score_frames_m"] > 0.0
    assert "no surface was seen on two visits" in " ".join(result.output.split())


def test_lidar_double_walls_separate_a_consistent_map_from_an_inconsistent_one(kitti_dir: Path, tmp_path: Path) -> None:
    """False-flag control for LiDAR on real scans: the 16 KITTI 00 scans placed by KISS-ICP (scan-to-map
    registration, so the scans agree with each other) are flagged at most 0.5 % (measured 0.0 % of ~3500 surface
    voxels). Placed by the data set's ground truth, whose relative rotation drifts ~1.6 deg (~1 deg of it pitch)
    from KISS-ICP's over these 13 m, the same scans hold the ground twice (11-31 cm, seen from far against near)
    and >= 1 % is flagged (measured 1.65 %), mostly with near-vertical normals."""
    from driftmap.diagnostics.report import diagnose_store

    build(kitti_dir, tmp_path / "kiss", loop_closure=False)
    build(kitti_dir, tmp_path / "gt", poses_from_source=True, loop_closure=False)
    out = {}
    for name in ("kiss", "gt"):
        with FrameStore.open(tmp_path / name) as store:
            assert len(store) == 16
            out[name] = diagnose_store(store, 0).double_walls
    kiss, gt = out["kiss"], out["gt"]
    assert kiss.voxels_evaluated > 2000 and gt.voxels_evaluated > 2000
    assert kiss.fraction_flagged <= 0.005, kiss.fraction_flagged
    assert gt.fraction_flagged >= 0.01, gt.fraction_flagged
    ground = [r for r in gt.regions if abs(float(r.normal[2])) >= np.cos(np.radians(25))]
    assert sum(r.n_voxels for r in ground) >= 0.5 * sum(r.n_voxels for r in gt.regions)
    assert gt.frame_smearing_score_m > 2.0 * kiss.frame_smearing_score_m


def _correct(store: Path, poses: Path, *extra: str) -> None:
    result = CliRunner().invoke(app, ["correct", str(store), "--poses", str(poses), "--format", "kitti", *extra])
    assert result.exit_code == 0, (result.output, result.exception)


def test_the_store_knows_its_kitti_sequence(gt_store: Path, kitti_dir: Path) -> None:
    with FrameStore.open(gt_store) as store:
        origin = kitti_origin_of_store(store)
    assert origin is not None
    assert origin.sequence_dir.resolve() == kitti_dir.resolve()
    assert origin.poses_file is not None and origin.poses_file.resolve() == (kitti_dir / "poses.txt").resolve()
    assert origin.calib_file is not None and origin.is_own_poses_file(kitti_dir / "poses.txt")


def test_diagnose_converts_the_datasets_cam0_ground_truth(gt_store: Path, kitti_dir: Path, tmp_path: Path) -> None:
    """ATE of the store built from the ground truth against the same ground truth read from poses.txt is ~0.

    Read unconverted (``--kitti-frame velodyne``), the rows are cam0 poses: on this almost straight stretch the
    rigid ATE alignment absorbs most of the frame change (ATE ~0.6 mm), but the relative motions are in the
    wrong axes (RPE ~ metres); the converted reading makes both vanish."""
    right = _diagnose(gt_store, kitti_dir / "poses.txt", tmp_path / "auto.json")
    wrong = _diagnose(gt_store, kitti_dir / "poses.txt", tmp_path / "velo.json", "--kitti-frame", "velodyne")
    assert right["n_frames_matched"] == wrong["n_frames_matched"] == 6
    assert right["ate_rmse_m"] < 1e-6 and right["ate_max_m"] < 1e-6  # < 1 micrometre, not just < 1 mm
    assert right["rpe_trans_rmse_m"] < 1e-5
    assert right["rpe_rot_rmse_deg"] < 1e-4  # the file's 6-digit rotations are projected onto SO(3) first
    assert wrong["ate_rmse_m"] > 100 * max(right["ate_rmse_m"], 1e-6)
    assert wrong["rpe_trans_rmse_m"] > 0.5  # frame-to-frame motion of ~1 m/frame, along the wrong axes


def test_correct_converts_the_datasets_cam0_ground_truth(store_copy: Path, kitti_dir: Path, velo_rows: np.ndarray,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="driftmap.sources.kitti"):
        _correct(store_copy, kitti_dir / "poses.txt")
    assert any("cam0 ground truth" in r.getMessage() and r.levelno == logging.INFO for r in caplog.records)
    with FrameStore.open(store_copy) as store:
        ids = [int(i) for i in store.frame_ids]
        assert ids == [0, 3, 6, 9, 12, 15] and store.head == 1
        got = store.poses(1)
        from_source = store.poses(0)
    expected = np.array([geometry.as_rigid(velo_rows[i]) for i in ids])  # stored poses are projected onto SO(3)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got[:, :3, 3], velo_rows[ids][:, :3, 3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(got, from_source, rtol=0, atol=1e-9)  # = --poses-from-source


def test_correct_recognises_a_copy_of_the_datasets_poses(store_copy: Path, kitti_dir: Path, velo_rows: np.ndarray,
                                                         tmp_path: Path) -> None:
    copy = Path(shutil.copyfile(kitti_dir / "poses.txt", tmp_path / "00.txt"))
    _correct(store_copy, copy)
    with FrameStore.open(store_copy) as store:
        ids = [int(i) for i in store.frame_ids]
        np.testing.assert_allclose(store.poses(1)[:, :3, 3], velo_rows[ids][:, :3, 3], rtol=0, atol=1e-9)


def test_explicit_velodyne_keeps_the_rows(store_copy: Path, kitti_dir: Path) -> None:
    """``--kitti-frame velodyne``: even the data set's own poses.txt is taken as it is."""
    _correct(store_copy, kitti_dir / "poses.txt", "--kitti-frame", "velodyne")
    raw = read_kitti(kitti_dir / "poses.txt").poses
    with FrameStore.open(store_copy) as store:
        ids = [int(i) for i in store.frame_ids]
        got = store.poses(1)
        from_source = store.poses(0)
    np.testing.assert_allclose(got, np.array([geometry.as_rigid(raw[i]) for i in ids]), rtol=0, atol=1e-9)
    assert np.max(np.abs(got[:, :3, 3] - from_source[:, :3, 3])) > 0.1  # not the Velodyne poses


def test_other_kitti_files_are_velodyne_poses_unless_told_cam0(store_copy: Path, kitti_dir: Path, velo_rows: np.ndarray,
                                                               tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Another KITTI file: auto keeps its rows (with a warning); ``--kitti-frame cam0`` converts them with the
    calibration of the data set the store came from."""
    cam0 = read_kitti(kitti_dir / "poses.txt").poses
    ids = np.arange(len(cam0), dtype=np.int64)
    velo_file, cam0_file = tmp_path / "lidar_odometry.txt", tmp_path / "cam0_rewritten.txt"
    write_kitti(velo_file, Trajectory(ids, velo_rows, ids))
    write_kitti(cam0_file, Trajectory(ids, cam0, ids))  # same poses, other bytes: not recognised as the data set's
    with caplog.at_level(logging.INFO, logger="driftmap.sources.kitti"):
        _correct(store_copy, velo_file)
    # Velodyne rows (they move along x): an info line, no warning to learn to ignore
    assert any(r.levelno == logging.INFO and "taken as Velodyne poses" in r.getMessage() for r in caplog.records)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and r.name == "driftmap.sources.kitti"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.kitti"):  # cam0 rows read in auto: a warning
        _correct(store_copy, cam0_file, "--kitti-frame", "auto")
    assert any("they look like cam0 poses" in r.getMessage() for r in caplog.records)
    _correct(store_copy, cam0_file, "--kitti-frame", "cam0")
    with FrameStore.open(store_copy) as store:
        stored = [int(i) for i in store.frame_ids]
        np.testing.assert_allclose(store.poses(1)[:, :3, 3], velo_rows[stored][:, :3, 3], rtol=0, atol=1e-8)
        np.testing.assert_allclose(store.poses(3), store.poses(0), rtol=0, atol=1e-7)  # 9-decimal rewrite


def test_build_uses_the_same_rule(kitti_dir: Path, velo_rows: np.ndarray, tmp_path: Path) -> None:
    """build --poses: a rewritten cam0 file is taken as Velodyne poses in auto, converted with --kitti-frame cam0."""
    cam0 = read_kitti(kitti_dir / "poses.txt").poses
    ids = np.arange(len(cam0), dtype=np.int64)
    cam0_file = tmp_path / "cam0_rewritten.txt"
    write_kitti(cam0_file, Trajectory(ids, cam0, ids))
    build(kitti_dir, tmp_path / "auto", poses_file=cam0_file, frames="5:16:5", loop_closure=False)
    build(kitti_dir, tmp_path / "cam0", poses_file=cam0_file, frames="5:16:5", loop_closure=False, kitti_frame="cam0")
    with FrameStore.open(tmp_path / "auto") as auto, FrameStore.open(tmp_path / "cam0") as converted:
        assert [int(i) for i in converted.frame_ids] == [5, 10, 15]
        np.testing.assert_allclose(auto.poses(0)[:, :3, 3], cam0[[5, 10, 15], :3, 3], rtol=0, atol=1e-8)
        np.testing.assert_allclose(converted.poses(0)[:, :3, 3], velo_rows[[5, 10, 15], :3, 3], rtol=0, atol=1e-8)


def test_cam0_without_calibration_is_an_error(kitti_dir: Path, velo_rows: np.ndarray, tmp_path: Path) -> None:
    """A store whose KITTI data set has lost its calib.txt: cam0 rows cannot be converted -> a clear error
    naming the pose file, exit code 1, and nothing imported; ``--calib`` supplies the calibration."""
    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    for name in ("000000.bin", "000001.bin", "000002.bin"):
        shutil.copyfile(kitti_dir / "velodyne" / name, seq / "velodyne" / name)
    for name in ("calib.txt", "poses.txt", "times.txt"):
        shutil.copyfile(kitti_dir / name, seq / name)
    store_path = tmp_path / "store"
    build(seq, store_path, poses_from_source=True, loop_closure=False)
    (seq / "calib.txt").unlink()

    env = {**os.environ, "COLUMNS": "200"}
    out = subprocess.run([sys.executable, "-m", "driftmap.cli", "correct", str(store_path), "--poses", str(seq / "poses.txt"),
                          "--format", "kitti", "--kitti-frame", "cam0"], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 1, out.stderr
    last = " ".join(out.stderr.split())  # rich may wrap the line
    assert "error:" in last and "poses.txt" in last and "calib" in last, out.stderr
    assert "Traceback" not in out.stderr

    runner = CliRunner()
    for extra in ([], ["--kitti-frame", "cam0"]):  # auto: the data set's own cam0 file, but no calibration
        bad = runner.invoke(app, ["correct", str(store_path), "--poses", str(seq / "poses.txt"), "--format", "kitti", *extra])
        assert bad.exit_code == 1 and isinstance(bad.exception, ConfigError), (extra, bad.output, bad.exception)
        assert str(seq / "poses.txt") in str(bad.exception)
    bad = runner.invoke(app, ["diagnose", str(store_path), "--json", str(tmp_path / "d.json"), "--gt", str(seq / "poses.txt"),
                              "--gt-format", "kitti", "--kitti-frame", "cam0"])
    assert bad.exit_code == 1 and isinstance(bad.exception, ConfigError), (bad.output, bad.exception)
    with FrameStore.open(store_path) as store:
        assert len(store.revisions) == 1  # nothing was imported

    _correct(store_path, seq / "poses.txt", "--kitti-frame", "cam0", "--calib", str(kitti_dir / "calib.txt"))
    with FrameStore.open(store_path) as store:
        np.testing.assert_allclose(store.poses(1), store.poses(0), rtol=0, atol=1e-9)
        np.testing.assert_allclose(store.poses(1)[:, :3, 3], velo_rows[:3, :3, 3], rtol=0, atol=1e-9)


def test_kitti_frame_options_are_refused_where_they_mean_nothing(store_copy: Path, kitti_dir: Path, tmp_path: Path) -> None:
    """A TUM file with --kitti-frame, an unknown frame name, a --kitti-frame without --gt: errors, nothing imported."""
    tum = tmp_path / "poses.tum"
    tum.write_text("0.0 0 0 0 0 0 0 1\n")
    with FrameStore.open(store_copy, "a") as store:
        with pytest.raises(ConfigError, match="KITTI"):
            store.import_poses(tum, format="tum", kitti_frame="cam0")
    runner = CliRunner()
    bad = runner.invoke(app, ["correct", str(store_copy), "--poses", str(kitti_dir / "poses.txt"), "--format", "kitti",
                              "--kitti-frame", "camera"])
    assert bad.exit_code == 1 and isinstance(bad.exception, ConfigError) and "camera" in str(bad.exception)
    bad = runner.invoke(app, ["diagnose", str(store_copy), "--json", str(tmp_path / "d.json"), "--kitti-frame", "cam0"])
    assert bad.exit_code == 1 and isinstance(bad.exception, ConfigError)
    with FrameStore.open(store_copy) as store:
        assert len(store.revisions) == 1


def test_scans_from_a_converted_mcap_keep_their_kitti_sequence(kitti_dir: Path, velo_rows: np.ndarray, tmp_path: Path,
                                                                caplog: pytest.LogCaptureFixture) -> None:
    """``convert`` records the sequence an MCAP was read from (its ``origin``): a store built from the MCAP
    converts the data set's cam0 ``poses.txt`` in ``auto`` as a store built from the folder does (build,
    correct, diagnose). When the sequence folder is gone, the rows are taken as they are with the camera-motion
    warning (it was silent), and ``--kitti-frame cam0 --calib`` still converts them."""
    from driftmap.export.mcap import convert
    from driftmap.sources.ros import read_export_origin

    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    for i in range(0, 16, 3):
        shutil.copyfile(kitti_dir / "velodyne" / f"{i:06d}.bin", seq / "velodyne" / f"{i:06d}.bin")
    for name in ("calib.txt", "poses.txt", "times.txt"):
        shutil.copyfile(kitti_dir / name, seq / name)
    mcap = tmp_path / "kitti.mcap"
    convert(seq, mcap)
    again = tmp_path / "again.mcap"  # an MCAP converted from the MCAP names the same data set
    convert(mcap, again, frames="0:3")
    assert read_export_origin(again) == read_export_origin(mcap) == {"format": "kitti", "path": str(seq.resolve()),
                                                                     "options": {}}
    store_path = tmp_path / "store"
    build(mcap, store_path, poses_file=seq / "poses.txt", loop_closure=False)  # the data set's cam0 file
    with FrameStore.open(store_path) as store:
        origin = kitti_origin_of_store(store)
        assert origin is not None and origin.sequence_dir == seq.resolve()
        stored = [int(i) for i in store.frame_ids]
        assert stored == list(range(0, 16, 3))
        np.testing.assert_allclose(store.poses(0)[:, :3, 3], velo_rows[stored][:, :3, 3], rtol=0, atol=1e-9)
    _correct(store_path, seq / "poses.txt")
    with FrameStore.open(store_path) as store:
        np.testing.assert_allclose(store.poses(1), store.poses(0), rtol=0, atol=1e-9)
    assert _diagnose(store_path, seq / "poses.txt", tmp_path / "d.json")["ate_rmse_m"] < 1e-6

    shutil.rmtree(seq)  # the data set has moved: the store no longer knows it
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.kitti"):
        _correct(store_path, kitti_dir / "poses.txt")
    messages = [r.getMessage() for r in caplog.records]
    assert any("no longer there" in m for m in messages), messages
    assert any("they look like cam0 poses" in m and "--calib" in m for m in messages), messages
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.kitti"):  # told the frame: the origin is not asked
        _correct(store_path, kitti_dir / "poses.txt", "--kitti-frame", "cam0", "--calib", str(kitti_dir / "calib.txt"))
    assert not [r for r in caplog.records if r.name == "driftmap.sources.kitti"], [r.getMessage() for r in caplog.records]
    with FrameStore.open(store_path) as store:
        head = len(store.revisions) - 1
        np.testing.assert_allclose(store.poses(head), store.poses(0), rtol=0, atol=1e-9)
