"""The readers through the command line: ``--period-s`` for folders of clouds (build, convert; refused where a
format or a folder has stamps of its own)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cloud_files import write_pcd
from driftmap.cli import app
from driftmap.errors import ConfigError
from driftmap.sources.base import open_source
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import read_kitti

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
