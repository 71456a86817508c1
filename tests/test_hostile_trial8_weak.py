"""The eighth hostile-input trial's weak findings (issue 22, docs/bad-input.md) on sources, stores and the volume,
through the path the user took: W10 a TUM setup name on another depth source, W11 ``--format`` contradicting the
file's bytes, W12 a voxel size blamed on the poses, W14 recover advice that did not fit a damaged layout, W15 a
warning said twice per frame and a hint said twice per line."""

from __future__ import annotations

import errno
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli
from pydantic import ValidationError

from driftmap.cli import _message
from driftmap.config import VolumeConfig
from driftmap.errors import ConfigError, OutputWriteError
from driftmap.sources.kitti import KittiOdometry
from driftmap.volume.grid import GridSpec


def test_w10_a_tum_setup_name_on_7scenes_is_named_not_looked_for_as_a_file(sevenscenes_dir: Path,
                                                                             tmp_path: Path) -> None:
    line = one_error(run_cli("build", sevenscenes_dir, "--frames", "0:2", "--intrinsics", "fr1", "--out",
                             tmp_path / "s", "--no-loop-closure"))
    assert "'fr1' names a TUM RGB-D camera setup, which only TUM sequences take" in line, line
    assert "not found" not in line
    assert not (tmp_path / "s").exists()


def test_w11_a_format_the_bytes_contradict_is_refused(datasets_dir: Path, tmp_path: Path) -> None:
    mcap = datasets_dir / "bags" / "nav2_turtlebot.mcap"
    line = one_error(run_cli("build", mcap, "--format", "rosbag1", "--out", tmp_path / "s", "--no-loop-closure"))
    assert f"{mcap}: is an MCAP file (by its first bytes or layout), not a ROS 1 bag" in line, line
    bag = datasets_dir / "bags" / "ROS_example.bag"
    line = one_error(run_cli("build", bag, "--format", "mcap", "--out", tmp_path / "s", "--no-loop-closure"))
    assert "is a ROS 1 bag (by its first bytes or layout), not an MCAP file" in line, line


def test_w12_a_voxel_size_below_a_tenth_of_a_millimetre_is_refused_and_a_fine_grid_blames_the_voxels() -> None:
    with pytest.raises(ValidationError, match="greater than or equal to 0.0001"):
        VolumeConfig(voxel_size_m=1e-300)
    with pytest.raises(ConfigError, match="the voxels are too small for this extent"):
        GridSpec.covering(np.zeros(3), np.full(3, 2.0), 1e-300)
    with pytest.raises(ConfigError, match="are the poses of this revision absurd"):
        GridSpec.covering(np.zeros(3), np.full(3, 1e30), 0.02)


def test_w14_recover_on_a_damaged_layout_says_to_move_the_file_aside(room10: dict[str, Path], tmp_path: Path) -> None:
    """A store.json symlink loop or a segment that is a folder: "free space and run recover again" met the same
    error every time; the advice now fits (move it aside), and following it recovers the store."""
    loop = tmp_path / "loop"
    shutil.copytree(room10["gt"], loop)
    (loop / "store.json").unlink()
    (loop / "store.json").symlink_to("store.json")
    line = one_error(run_cli("recover", loop))
    assert "Too many levels of symbolic links [ELOOP]; store.json is not the regular file" in line, line
    assert "free space" not in line and line.count("[ELOOP]") == 1, line
    (loop / "store.json").rename(loop / "store.json.aside")
    done = run_cli("recover", loop)
    said = " ".join(done.stdout.split())
    assert done.returncode == 0 and "rebuilt from 1 segments: kept 10 frames" in said, (said, done.stderr)
    folder = tmp_path / "folder"
    shutil.copytree(room10["gt"], folder)
    (folder / "segment-000000.mcap").unlink()
    (folder / "segment-000000.mcap").mkdir()
    line = one_error(run_cli("recover", folder))
    assert "[EISDIR]; segment-000000.mcap is not the regular file" in line and "free space" not in line, line
    assert line.count("recovering the store failed") == 1, line


def test_w15_a_hint_and_a_warning_are_said_once(kitti_dir: Path, tmp_path: Path,
                                                caplog: pytest.LogCaptureFixture) -> None:
    error = OutputWriteError("x.ply: writing --map failed: Read-only file system; the file system is mounted "
                             "read-only: write elsewhere", path="x.ply", errno=errno.EROFS)
    assert _message(error).count("write elsewhere") == 1
    folder = tmp_path / "kitti"
    (folder / "velodyne").mkdir(parents=True)
    for scan in sorted((kitti_dir / "velodyne").glob("*.bin"))[:2]:
        points = np.fromfile(scan, dtype=np.float32).reshape(-1, 4)
        points[:7, 0] = np.nan
        points.tofile(folder / "velodyne" / scan.name)
    source = KittiOdometry(folder)
    with caplog.at_level(logging.WARNING, logger="driftmap.sources.kitti"):
        for _ in range(2):  # a pre-pass and the build read each scan
            for frame in source:
                assert np.isfinite(frame.points_sensor).all()
    said = [r.getMessage() for r in caplog.records if "NaN or infinite" in r.getMessage()]
    assert len(said) == 2 and all("7 of" in m for m in said), said


def test_w9_a_period_that_rounds_to_no_nanosecond_says_so(kitti_dir: Path, tmp_path: Path) -> None:
    line = one_error(run_cli("build", kitti_dir, "--period-s", "1e-12", "--out", tmp_path / "s", "--no-loop-closure"))
    assert "--period-s: 1e-12 s rounds to 0 ns" in line and "positive" not in line, line
    line = one_error(run_cli("build", kitti_dir, "--period-s", "-1", "--out", tmp_path / "s", "--no-loop-closure"))
    assert "must be a positive number of seconds, got -1" in line, line


def test_w13_text_where_a_number_or_flag_belongs_is_refused_in_every_table(tmp_path: Path) -> None:
    """pydantic reads ``voxel_size_m = "0.05"`` as 0.05 m: a config file's numbers and flags must be written as
    such in every table (names and enumerations stay text)."""
    from driftmap.config import DriftmapConfig

    cases = [('[volume]\nvoxel_size_m = "0.05"\n', 'volume.voxel_size_m: expected a number, got \'0.05\' (text, in quotes'),
             ("[map]\nexport_voxel_size_m = true\n", "map.export_voxel_size_m: expected a number, got true"),
             ('[volume]\nkeep_frame_voxels = "false"\n', "volume.keep_frame_voxels: expected true or false")]
    for k, (text, expected) in enumerate(cases):
        file = tmp_path / f"c{k}.toml"
        file.write_text(text)
        with pytest.raises(ConfigError, match=None) as info:
            DriftmapConfig.load(file)
        assert f"{file}: {expected}" in str(info.value), str(info.value)
    (tmp_path / "ok.toml").write_text('[volume]\nunknown_is = "free"\nvoxel_size_m = 0.05\nkeep_frame_voxels = false\n')
    assert DriftmapConfig.load(tmp_path / "ok.toml").volume.voxel_size_m == 0.05


def test_t9_w4_a_refused_list_item_is_one_error_line(room10: dict[str, Path], tmp_path: Path) -> None:
    """``voxel_sizes_m = [0.0]`` added pydantic's "should have at least 1 item after validation" to the item's own
    error: a second, wrong line."""
    config = tmp_path / "d.toml"
    config.write_text("[diagnose.double_wall]\nvoxel_sizes_m = [0.0]\n")
    out = run_cli("diagnose", room10["gt"], "--config", config, "--json", tmp_path / "d.json")
    line = one_error(out)
    assert "diagnose.double_wall.voxel_sizes_m.0: Input should be greater than 0 (got 0.0)" in line, line
    assert "at least 1 item" not in line and not (tmp_path / "d.json").exists()
