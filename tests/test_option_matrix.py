"""Issue 22: every source option of ``build`` and ``convert`` -- the command-line flags and the ``[depth]`` settings
-- on every source format, through the command line. The matrix is not written here: it is the readers' own
declarations (``option_matrix``, the table in docs/cli.md). Where a format takes an option, the command runs
with it; where it does not, the command refuses it with the documented message before anything is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cloud_files import write_pcd, write_ros_log
from PIL import Image
from typer.testing import CliRunner

from driftmap.cli import app
from driftmap.errors import ConfigError
from driftmap.pipeline.source_options import DEPTH_OPTION_SETTINGS, SOURCE_OPTION_FLAGS, option_matrix
from driftmap.sources.base import open_source, registered_formats

LOG = Path(__file__).resolve().parents[1] / "datasets" / "synthetic-loop"
MATRIX = option_matrix()

FLAG_VALUES = {"--sensor": ["depth"], "--topic": ["/points"], "--pose-from-tf": ["odom,base_link"],
               "--pose-from-odometry": ["/odom"], "--lenient": [], "--period-s": ["0.5"], "--point-layout": ["auto"]}
"""A value each flag takes wherever it applies (the sample inputs below are made to fit them)."""
DEPTH_ENV = {"depth.min_depth_m": {"DRIFTMAP_DEPTH__MIN_DEPTH_M": "0.3"},
             "depth.max_depth_m": {"DRIFTMAP_DEPTH__MAX_DEPTH_M": "3.5"},
             "depth.check_scale = false": {"DRIFTMAP_DEPTH__CHECK_SCALE": "false"}}


def test_the_matrix_covers_every_format_and_option() -> None:
    assert set(MATRIX) == set(registered_formats())
    assert all(set(row) == set(SOURCE_OPTION_FLAGS.values()) | set(DEPTH_OPTION_SETTINGS.values()) for row in MATRIX.values())
    assert set(FLAG_VALUES) == set(SOURCE_OPTION_FLAGS.values())
    assert all(any(row[c] for row in MATRIX.values()) for c in FLAG_VALUES)  # every flag applies somewhere


@pytest.fixture(scope="module")
def samples(tmp_path_factory: pytest.TempPathFactory, sevenscenes_dir: Path, kitti_dir: Path, icl_dir: Path) -> dict[str, Path]:
    """A small input of every registered format."""
    root = tmp_path_factory.mktemp("formats")
    tum = root / "tum"
    (tum / "depth").mkdir(parents=True)
    rows = []
    for k in range(2):
        mm = np.asarray(Image.open(sevenscenes_dir / f"frame-{k:06d}.depth.png")).astype(np.uint32)
        Image.fromarray(np.where(mm == 65535, 0, mm * 5).astype(np.uint16)).save(tum / "depth" / f"{100 + k}.000000.png")
        rows.append(f"{100 + k}.000000 depth/{100 + k}.000000.png")
    (tum / "depth.txt").write_text("\n".join(rows) + "\n")
    scans = np.fromfile(kitti_dir / "velodyne" / "000000.bin", dtype="<f4").reshape(-1, 4)[::4]
    clouds = root / "clouds"
    clouds.mkdir()
    for k in range(2):
        write_pcd(clouds / f"{k:06d}.pcd", {"x": scans[:, 0], "y": scans[:, 1] + 0.1 * k, "z": scans[:, 2]})
    ros_scans = [(10**9 + k * 10**8, scans[:, :3].copy(), scans[:, 3].copy()) for k in range(2)]
    T = [np.eye(4), np.eye(4)]
    T[1][0, 3] = 0.1
    out = {"synthetic": LOG, "7scenes": sevenscenes_dir, "tum": tum, "kitti": kitti_dir, "redwood": icl_dir,
           "cloud_folder": clouds}
    for kind, name in (("mcap", "log.mcap"), ("rosbag1", "log.bag"), ("rosbag2", "log_bag2")):
        out[kind] = write_ros_log(root / name, kind, ros_scans, T, np.eye(4))
    assert set(out) == set(registered_formats())
    return out


def _invoke(args: list, env: dict | None = None):  # noqa: ANN202
    return CliRunner().invoke(app, [str(a) for a in args], env=env)


def _refused(result, what: str, fmt: str) -> None:  # noqa: ANN001
    assert result.exit_code != 0, result.output
    assert isinstance(result.exception, ConfigError), (result.exception, result.output)
    message = str(result.exception)
    assert f"{what}: does not apply to" in message and f"(format {fmt}" in message, message


def _accepted(result, what: str) -> None:  # noqa: ANN001
    assert result.exit_code == 0, (what, result.exception, result.output)


CELLS = [(fmt, flag) for fmt in sorted(MATRIX) for flag in FLAG_VALUES]


@pytest.mark.slow
@pytest.mark.parametrize(("fmt", "flag"), CELLS, ids=[f"{f}{g}" for f, g in CELLS])
def test_source_flags_on_every_format_through_build_and_convert(fmt: str, flag: str, samples: dict, tmp_path: Path) -> None:
    src = samples[fmt]
    option = [flag, *FLAG_VALUES[flag]]
    build = _invoke(["build", src, "--out", tmp_path / "s", "--frames", "0:2", "--no-loop-closure", *option])
    convert = _invoke(["convert", src, tmp_path / "c.mcap", "--frames", "0:2", *option])
    if MATRIX[fmt][flag]:
        _accepted(build, flag)
        _accepted(convert, flag)
    else:
        _refused(build, flag, fmt)
        _refused(convert, flag, fmt)
        assert not (tmp_path / "s").exists() and not (tmp_path / "c.mcap").exists()


DEPTH_CELLS = [(fmt, setting) for fmt in sorted(MATRIX) for setting in DEPTH_OPTION_SETTINGS.values()]


@pytest.mark.slow
@pytest.mark.parametrize(("fmt", "setting"), DEPTH_CELLS, ids=[f"{f}-{s.split()[0]}" for f, s in DEPTH_CELLS])
def test_depth_settings_on_every_format_through_build(fmt: str, setting: str, samples: dict, tmp_path: Path) -> None:
    src = samples[fmt]
    args, env = ["build", src, "--out", tmp_path / "s", "--frames", "0:2", "--no-loop-closure"], None
    if setting.startswith("depth.depth_scale"):
        args += ["--depth-scale", "5000" if fmt == "tum" else "1000"]
    elif setting.startswith("depth.intrinsics"):
        if MATRIX[fmt][setting]:
            K = open_source(src, fmt, frames="0:1", pixel_stride=1).frame(0).intrinsics
            args += ["--intrinsics", f"{K.fx},{K.fy},{K.cx},{K.cy}"]
        else:
            args += ["--intrinsics", "500,500,320,240"]
    else:
        env = DEPTH_ENV[setting]
    result = _invoke(args, env)
    if MATRIX[fmt][setting]:
        _accepted(result, setting)
    else:
        _refused(result, setting, fmt)
        assert not (tmp_path / "s").exists()
