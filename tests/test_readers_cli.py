"""The readers through the command line: ``--period-s`` for folders of clouds (build, convert; refused where a
format or a folder has stamps of its own), and pose files of one 4x4 matrix per frame (BALM's alidarPose.csv) or
Redwood ``.log`` blocks for ``build --poses``, ``diagnose --gt`` and ``correct --poses``."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cloud_files import write_pcd
from driftmap.cli import app
from driftmap.errors import ConfigError, StoreError
from driftmap.sources.base import open_source
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import read_kitti, read_redwood_log

BALM_FRAMES = "0:10"


def _cli(*args: object) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env)


def _ok(args: list[object]) -> str:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, (result.output, result.exception)
    return result.output


def _refused(args: list[object]) -> BaseException:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code != 0 and result.exception is not None, result.output
    return result.exception


def _write_4x4(path: Path, poses: np.ndarray, stamps_s: list[str] | None, separator: str = " ") -> Path:
    blocks = []
    for k, T in enumerate(poses):
        rows = [[repr(float(v)) for v in T[i]] for i in range(3)]
        rows.append(["0", "0", "0", "1" if stamps_s is None else stamps_s[k]])
        blocks.append("".join(separator.join(r) + "\n" for r in rows))
    path.write_text("\n".join(blocks))
    return path


def _balm_csv(balm_dir: Path) -> tuple[np.ndarray, list[str]]:
    """The csv's matrices and stamp texts, read here without the library's reader."""
    lines = [line.rstrip(",").split(",") for line in (balm_dir / "alidarPose.csv").read_text().splitlines() if line.strip()]
    values = np.array([[float(v) for v in row] for row in lines]).reshape(-1, 4, 4)
    stamps = [row[3] for row in lines[3::4]]
    values[:, 3, 3] = 1.0
    return values, stamps


def _stamp_ns(text: str) -> int:
    return int(Decimal(text) * 10**9)


# ---- --period-s ----------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cloud_folder(kitti_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four real KITTI scans (every 10th point) as PCD files scan_0..scan_3: a folder without stamps."""
    folder = tmp_path_factory.mktemp("clouds") / "clouds"
    folder.mkdir()
    for k in range(4):
        scan = np.fromfile(kitti_dir / "velodyne" / f"{k:06d}.bin", dtype=np.float32).reshape(-1, 4)[::10]
        write_pcd(folder / f"scan_{k}.pcd", {"x": scan[:, 0], "y": scan[:, 1], "z": scan[:, 2], "intensity": scan[:, 3]})
    return folder


def test_build_period_s_stamps_a_cloud_folder(cloud_folder: Path, kitti_dir: Path, tmp_path: Path) -> None:
    """A 2 Hz folder: --period-s 0.5 stamps frame n at n * 0.5 s (recorded for --resume), and a 4x4 pose file
    without stamps (last rows 0 0 0 1) places frame n with block n."""
    poses = read_kitti(kitti_dir / "poses.txt").poses[:4]
    pose_file = _write_4x4(tmp_path / "poses.txt", poses, None)
    out = tmp_path / "store"
    _ok(["build", cloud_folder, "--out", out, "--period-s", "0.5", "--poses", pose_file, "--no-loop-closure"])
    with FrameStore.open(out) as store:
        assert store.ledger.stamps_ns.tolist() == [0, 500_000_000, 1_000_000_000, 1_500_000_000]
        np.testing.assert_allclose(store.poses(0), poses, atol=1e-6)
    record = json.loads((out / "build_source.json").read_text())
    assert record["source_options"] == {"period_ns": 500_000_000}
    # without it the folder is assumed 10 Hz; --resume must read the stamps the same way
    again = _refused(["build", cloud_folder, "--out", out, "--resume", "--poses", pose_file, "--no-loop-closure"])
    assert isinstance(again, ConfigError) and "--period-s 0.5" in str(again)


@pytest.mark.parametrize("which", ["7scenes", "synthetic", "balm"])
def test_build_period_s_is_refused_where_the_frames_have_stamps(which: str, sevenscenes_dir: Path, balm_dir: Path,
                                                               tmp_path: Path) -> None:
    from driftmap.demo import embedded_log_path

    source = {"7scenes": sevenscenes_dir, "synthetic": embedded_log_path(), "balm": balm_dir}[which]
    exc = _refused(["build", source, "--out", tmp_path / "s", "--period-s", "0.5", "--frames", "0:2"])
    assert isinstance(exc, ConfigError)
    if which == "balm":  # a folder of clouds, but with stamps of its own
        assert "--period-s 0.5" in str(exc) and "has stamps of its own (alidarPose.csv)" in str(exc)
    else:
        assert str(exc).startswith(f"--period-s: does not apply to {source} (format {which}")
        assert "format {} stamps its frames itself".format(which) in str(exc)
    assert not (tmp_path / "s").exists()


def test_period_s_errors_are_one_line(cloud_folder: Path, tmp_path: Path) -> None:
    from driftmap.demo import embedded_log_path

    for args, expected in ((("build", embedded_log_path(), "--out", tmp_path / "s", "--period-s", "0.5"), "format synthetic"),
                           (("convert", embedded_log_path(), tmp_path / "c.mcap", "--period-s", "0.5"), "format synthetic"),
                           (("convert", cloud_folder, tmp_path / "c.mcap", "--period-s", "0"), "positive")):
        out = _cli(*args)
        assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
        line = [x for x in out.stderr.strip().splitlines() if x.strip()][-1]
        assert line.startswith("error: --period-s") and expected in " ".join(out.stderr.split()), out.stderr
    assert not (tmp_path / "c.mcap").exists()


def test_convert_period_s_stamps_the_exported_frames(cloud_folder: Path, tmp_path: Path) -> None:
    _ok(["convert", cloud_folder, tmp_path / "slow.mcap", "--period-s", "0.5"])
    _ok(["convert", cloud_folder, tmp_path / "nominal.mcap"])
    slow, nominal = open_source(tmp_path / "slow.mcap"), open_source(tmp_path / "nominal.mcap")
    assert [f.stamp_ns for f in slow] == [k * 500_000_000 for k in range(4)]
    assert [f.stamp_ns for f in nominal] == [k * 100_000_000 for k in range(4)]  # assumed 10 Hz
    assert [f.points_sensor.tobytes() for f in slow] == [f.points_sensor.tobytes() for f in nominal]


# ---- 4x4 pose files: BALM's alidarPose.csv -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def balm_store(balm_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """BALM scans 0-9 placed with alidarPose.csv (``build --poses``), no loop closure."""
    out = tmp_path_factory.mktemp("balm") / "store"
    _ok(["build", balm_dir, "--out", out, "--frames", BALM_FRAMES, "--poses", balm_dir / "alidarPose.csv",
         "--no-loop-closure"])
    return out


def test_build_poses_4x4_csv_places_the_frames_with_its_matrices(balm_store: Path, balm_dir: Path) -> None:
    matrices, stamps = _balm_csv(balm_dir)
    with FrameStore.open(balm_store) as store:
        assert store.frame_ids.tolist() == list(range(10))
        assert store.ledger.stamps_ns.tolist() == [_stamp_ns(s) for s in stamps[:10]]  # the csv's stamps, to the ns
        np.testing.assert_allclose(store.poses(0), matrices[:10], atol=1e-5)  # 6 decimals, projected onto SO(3)
        assert store.ledger.revision(0).source.value == "external_file"


def test_build_poses_4x4_without_stamps_matches_by_index(balm_dir: Path, tmp_path: Path) -> None:
    matrices, _ = _balm_csv(balm_dir)
    shifted = matrices.copy()
    shifted[:, :3, 3] += (1.0, 2.0, 0.0)
    plain = _write_4x4(tmp_path / "plain.txt", shifted[:12], None)
    out = tmp_path / "store"
    _ok(["build", balm_dir, "--out", out, "--frames", "4:8", "--poses", plain, "--no-loop-closure"])
    with FrameStore.open(out) as store:
        assert store.frame_ids.tolist() == [4, 5, 6, 7]
        np.testing.assert_allclose(store.poses(0), shifted[4:8], atol=1e-5)  # block n = frame n


def test_diagnose_gt_4x4_gives_zero_ate_for_its_own_poses(balm_store: Path, balm_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "d.json"
    _ok(["diagnose", balm_store, "--json", out, "--gt", balm_dir / "alidarPose.csv", "--gt-format", "4x4",
         "--points-per-frame", "2000"])
    trajectory = json.loads(out.read_text())["trajectory"]
    assert trajectory["ate_rmse_m"] < 1e-5 and trajectory["rpe_trans_rmse_m"] < 1e-5
    # a ground truth moved by 5 cm on every other frame shows up (so the ATE above could fail)
    matrices, stamps = _balm_csv(balm_dir)
    moved = matrices.copy()
    moved[1::2, 0, 3] += 0.05
    _ok(["diagnose", balm_store, "--json", out, "--gt", _write_4x4(tmp_path / "m.csv", moved, stamps, ","),
         "--gt-format", "4x4", "--points-per-frame", "2000"])
    assert json.loads(out.read_text())["trajectory"]["ate_rmse_m"] > 0.02


def test_correct_4x4_matches_by_stamp_and_by_index(balm_store: Path, balm_dir: Path, tmp_path: Path) -> None:
    store_path = Path(shutil.copytree(balm_store, tmp_path / "store"))
    matrices, stamps = _balm_csv(balm_dir)
    moved = matrices.copy()
    moved[:, :3, 3] += (0.1, 0.0, 0.0)
    # stamps shifted by 1 ms and rows reversed in time would be refused: keep the order, shift the stamps
    shifted_stamps = [str(Decimal(s) + Decimal("0.001")) for s in stamps]
    stamped = _write_4x4(tmp_path / "moved.csv", moved, shifted_stamps, ",")
    output = _ok(["correct", store_path, "--poses", stamped, "--format", "4x4"])
    assert "10 frames set from moved.csv" in output and "70 rows" in output
    with FrameStore.open(store_path) as store:
        np.testing.assert_allclose(store.poses(), moved[:10], atol=1e-5)
    # by stamp the tolerance counts: 1 ms off is outside --max-dt-ms 0.5
    exc = _refused(["correct", store_path, "--poses", stamped, "--format", "4x4", "--max-dt-ms", "0.5"])
    assert isinstance(exc, StoreError) and "no row matched" in str(exc)
    # --match index takes block i as frame i, whatever its stamp
    back = matrices.copy()
    back[:, :3, 3] -= (0.0, 0.2, 0.0)
    _ok(["correct", store_path, "--poses", _write_4x4(tmp_path / "back.csv", back, [str(k) + ".5" for k in range(80)], ","),
         "--format", "4x4", "--match", "index"])
    with FrameStore.open(store_path) as store:
        np.testing.assert_allclose(store.poses(), back[:10], atol=1e-5)
    # a file without stamps matches by index; asking for stamps is refused
    plain = _write_4x4(tmp_path / "plain.txt", matrices, None)
    _ok(["correct", store_path, "--poses", plain, "--format", "4x4"])
    with FrameStore.open(store_path) as store:
        np.testing.assert_allclose(store.poses(), matrices[:10], atol=1e-5)
    exc = _refused(["correct", store_path, "--poses", plain, "--format", "4x4", "--match", "stamp"])
    assert isinstance(exc, ConfigError) and "has no stamps" in str(exc) and "match by index" in str(exc)


# ---- Redwood .log -----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def icl_store(icl_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """ICL-NUIM's 5 frames placed with its trajectory.log (``build --poses``)."""
    icl = icl_dir
    out = tmp_path_factory.mktemp("icl") / "store"
    _ok(["build", icl, "--out", out, "--poses", icl / "trajectory.log", "--no-loop-closure"])
    return icl, out


def test_redwood_log_for_build_diagnose_and_correct(icl_store: tuple[Path, Path], tmp_path: Path) -> None:
    icl, built = icl_store
    trajectory = read_redwood_log(icl / "trajectory.log")
    with FrameStore.open(built) as store:
        assert store.frame_ids.tolist() == [0, 1, 2, 3, 4]
        np.testing.assert_allclose(store.poses(0), trajectory.poses, atol=1e-9)
    out = tmp_path / "d.json"
    _ok(["diagnose", built, "--json", out, "--gt", icl / "trajectory.log", "--gt-format", "redwood",
         "--points-per-frame", "2000"])
    assert json.loads(out.read_text())["trajectory"]["ate_rmse_m"] < 1e-9
    store_path = Path(shutil.copytree(built, tmp_path / "store"))
    _ok(["correct", store_path, "--poses", icl / "odometry.log", "--format", "redwood"])
    with FrameStore.open(store_path) as store:
        np.testing.assert_allclose(store.poses(), read_redwood_log(icl / "odometry.log").poses, atol=1e-9)
    # the ids the file names are the frames it places: a .log of frames 2-4 only moves frames 2-4
    text = (icl / "trajectory.log").read_text().splitlines()
    blocks = [text[5 * k: 5 * k + 5] for k in range(5)]
    moved = []
    for block in blocks[2:]:
        rows = [line.split() for line in block[1:]]
        rows[0][3] = repr(float(rows[0][3]) + 0.25)
        moved += [block[0]] + [" ".join(r) for r in rows]
    (tmp_path / "part.log").write_text("\n".join(moved) + "\n")
    _ok(["correct", store_path, "--poses", tmp_path / "part.log", "--format", "redwood", "--no-propagate"])
    with FrameStore.open(store_path) as store:
        before, after = store.poses(store.head - 1), store.poses()
    np.testing.assert_allclose(after[2:, 0, 3] - trajectory.poses[2:, 0, 3], 0.25, atol=1e-9)
    np.testing.assert_array_equal(after[:2], before[:2])  # frames 0 and 1 have no block: unchanged
    exc = _refused(["correct", store_path, "--poses", tmp_path / "part.log", "--format", "redwood", "--match", "stamp"])
    assert isinstance(exc, ConfigError) and "has no stamps" in str(exc)
