"""The CLI's handling of bad input: usage errors for option values, one-line errors (exit 1) for unreadable or
unwritable files, file names printed verbatim (no rich markup), and counts that match what was written."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from driftmap.sources.synthetic import SyntheticLog
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import Trajectory, read_tum, write_tum


def _cli(*args: object) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env)


@pytest.fixture(scope="module")
def store_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from driftmap.demo import embedded_log_path

    path = tmp_path_factory.mktemp("cli") / "store"
    with FrameStore.create(path) as store:
        for k, frame in enumerate(SyntheticLog(embedded_log_path())):
            if k >= 8:
                break
            store.append(frame)
    return path


def _one_line_error(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 1, (out.returncode, out.stdout, out.stderr)
    assert "Traceback" not in out.stderr, out.stderr
    lines = [line for line in out.stderr.strip().splitlines() if line.strip()]
    assert lines and lines[-1].startswith("error:"), out.stderr
    return lines[-1]


@pytest.mark.parametrize("args", [
    ("correct", "{store}", "--poses", "{tum}", "--format", "xyz"),
    ("correct", "{store}", "--poses", "{tum}", "--match", "foo"),
    ("correct", "{store}", "--poses", "{tum}", "--source", "banana"),
    ("export", "{store}", "--trajectory", "{tmp}/t.txt", "--format", "xyz"),
    ("perturb", "{tum}", "{tmp}/p.tum", "--format", "xyz", "--drift-percent-per-m", "1"),
    ("view", "{store}", "--color", "foo", "--out", "{tmp}/v"),
    ("view", "{store}", "--backend", "foo", "--out", "{tmp}/v"),
    ("diagnose", "{store}", "--json", "{tmp}/d.json", "--gt", "{tum}", "--gt-format", "foo"),
    ("build", "{store}", "--out", "{tmp}/b", "--format", "foo"),
    ("convert", "{store}", "{tmp}/c.mcap", "--format", "foo"),
])
def test_bad_option_values_are_usage_errors(store_path: Path, tmp_path: Path, args: tuple[str, ...]) -> None:
    tum = tmp_path / "own.tum"
    assert _cli("export", store_path, "--trajectory", tum).returncode == 0
    out = _cli(*(a.format(store=store_path, tum=tum, tmp=tmp_path) for a in args))
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert "Traceback" not in out.stderr and "is not one of" in out.stderr
    bad = next(a for a in args if a in ("xyz", "foo", "banana"))
    assert bad in out.stderr and args[args.index(bad) - 1] in out.stderr  # the value and the option
    assert not [p for p in tmp_path.iterdir() if p.name in ("v", "d.json", "b", "c.mcap")], "nothing is written"


def test_unwritable_outputs_and_undecodable_inputs_give_one_line_errors(store_path: Path, tmp_path: Path) -> None:
    a_dir = tmp_path / "a_dir"
    a_dir.mkdir()
    line = _one_line_error(_cli("export", store_path, "--trajectory", a_dir))
    assert str(a_dir) in line
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    line = _one_line_error(_cli("export", store_path, "--trajectory", a_file / "t.tum"))
    assert str(a_file) in line
    # diagnose, convert and perturb find such outputs before their work, and write nothing
    for args, flag in ((("diagnose", store_path, "--json", a_file / "d.json"), "--json"),
                       (("diagnose", store_path, "--json", tmp_path / "d.json", "--report", a_file), "--report"),
                       (("convert", store_path, a_file / "c.mcap"), "OUT.mcap"),
                       (("perturb", tmp_path / "none.tum", a_dir, "--drift-percent-per-m", "1"), "POSES_OUT")):
        line = _one_line_error(_cli(*args))
        assert flag in line and (str(a_file) in line or str(a_dir) in line), line
    assert not (tmp_path / "d.json").exists()
    binary = tmp_path / "b.tum"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    _one_line_error(_cli("perturb", binary, tmp_path / "o.tum", "--drift-percent-per-m", "1"))


def test_file_names_are_printed_verbatim(store_path: Path, tmp_path: Path) -> None:
    """Brackets in a path are not rich markup: "o[red].tum" is printed as it is, and "run[/].tum" does not crash."""
    tum = tmp_path / "own.tum"
    assert _cli("export", store_path, "--trajectory", tum).returncode == 0
    for name in ("o[red].tum", "run[/].tum"):
        out = _cli("perturb", tum, tmp_path / name, "--drift-percent-per-m", "1")
        assert out.returncode == 0, out.stderr
        assert name in out.stdout and (tmp_path / name).exists()


def test_map_export_reports_the_points_written(store_path: Path, tmp_path: Path) -> None:
    ply = tmp_path / "m.ply"
    out = _cli("export", store_path, "--map", ply, "--voxel-size-m", "0.05")
    assert out.returncode == 0, out.stderr
    n = len(o3d.io.read_point_cloud(str(ply)).points)
    assert f"{n:,} points" in out.stdout, (n, out.stdout)
    assert "provenance" in out.stdout and Path(str(ply) + ".provenance.npz").exists()


def test_revisions_count_real_changes_only(store_path: Path, tmp_path: Path) -> None:
    """A correction that moves the last 3 frames reports 3 frames changed, not the TUM round-off of the others;
    re-importing the head's own poses says that it changes nothing (and the table shows 0 frames changed)."""
    work = tmp_path / "s"
    import shutil

    shutil.copytree(store_path, work)
    own = tmp_path / "own.tum"
    assert _cli("export", work, "--trajectory", own).returncode == 0
    same = _cli("correct", work, "--poses", own)
    assert same.returncode == 0 and "changes no pose" in " ".join(same.stderr.split()), same.stderr
    traj = read_tum(own)
    moved = traj.poses.copy()
    moved[-3:, :3, 3] += 0.05
    write_tum(tmp_path / "moved.tum", Trajectory(traj.stamps_ns, moved))
    out = _cli("correct", work, "--poses", tmp_path / "moved.tum", "--no-propagate")
    assert out.returncode == 0, out.stderr
    table = _cli("revisions", work)
    assert table.returncode == 0
    rows = [[c.strip() for c in line.split("│") if c.strip()] for line in table.stdout.splitlines() if "external_file" in line]
    assert [r[4] for r in rows] == ["0", "3"], table.stdout
    with FrameStore.open(work) as store:
        assert len(store.revisions) == 3
        np.testing.assert_allclose(store.poses()[-3:, :3, 3] - store.poses(0)[-3:, :3, 3], 0.05, atol=1e-6)


def test_diagnose_gt_options_without_gt_are_refused(store_path: Path, tmp_path: Path) -> None:
    line = _one_line_error(_cli("diagnose", store_path, "--gt-format", "kitti", "--json", tmp_path / "d.json"))
    assert "--gt-format" in line and not (tmp_path / "d.json").exists()


def test_convert_with_an_empty_selection_writes_nothing(sevenscenes_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "e.mcap"
    line = _one_line_error(_cli("convert", sevenscenes_dir, out, "--frames", "3:3"))
    assert "no frame" in line and not out.exists() and not list(tmp_path.glob("*.partial"))


def test_export_checks_the_map_name_before_writing_anything(store_path: Path, tmp_path: Path) -> None:
    out = _cli("export", store_path, "--trajectory", tmp_path / "t.tum", "--map", tmp_path / "m.xyz")
    assert out.returncode == 2 and ".ply or .pcd" in " ".join(out.stderr.split()), out.stderr
    assert not (tmp_path / "t.tum").exists()
    out = _cli("export", store_path, "--trajectory", tmp_path / "t.tum", "--map", tmp_path / "m.ply", "--voxel-size-m", "-1")
    assert out.returncode == 2 and "--voxel-size-m" in out.stderr and "must be positive" in out.stderr, out.stderr
    assert not (tmp_path / "t.tum").exists()


def test_poses_from_source_means_the_same_on_a_data_set_and_its_mcap(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """Issue 22 case 7: --poses-from-source on an MCAP that `driftmap convert` made of a data set takes the ground
    truth it carries, as the same flag does on the folder (it was refused, "never taken as the pose estimate")."""
    from driftmap.frame import PoseSource
    from driftmap.store.frame_store import FrameStore

    log = tmp_path / "c.mcap"
    assert _cli("convert", sevenscenes_dir, log, "--frames", "0:6:3").returncode == 0
    for src, out, extra in ((log, "m", ()), (sevenscenes_dir, "f", ("--frames", "0:6:3"))):
        done = _cli("build", src, "--out", tmp_path / out, "--poses-from-source", "--no-loop-closure", *extra)
        assert done.returncode == 0, done.stderr
    with FrameStore.open(tmp_path / "m") as m, FrameStore.open(tmp_path / "f") as f:
        assert list(m.frame_ids) == list(f.frame_ids) == [0, 3]
        np.testing.assert_allclose(m.poses(0), f.poses(0), rtol=0, atol=1e-12)
        assert m.frame(3).pose.source is PoseSource.GROUND_TRUTH


def test_export_refuses_existing_outputs_without_overwrite(store_path: Path, tmp_path: Path) -> None:
    """Every export output (--map, --trajectory, --mcap, the map's provenance file) is refused when it exists,
    before anything is written; --overwrite replaces them."""
    tum, ply = tmp_path / "t.tum", tmp_path / "m.ply"
    assert _cli("export", store_path, "--trajectory", tum, "--map", ply, "--voxel-size-m", "0.05").returncode == 0
    before = {p: p.read_bytes() for p in (tum, ply, Path(f"{ply}.provenance.npz"))}
    fresh = tmp_path / "fresh.tum"
    for args, name in (((("--trajectory", tum)), "t.tum"), (("--trajectory", fresh, "--map", ply), "m.ply")):
        line = _one_line_error(_cli("export", store_path, *args))
        assert name in line and "--overwrite" in line, line
    assert not fresh.exists()  # nothing written when one output is refused
    ply.unlink()
    line = _one_line_error(_cli("export", store_path, "--map", ply, "--voxel-size-m", "0.05"))
    assert "provenance" in line, line
    assert not ply.exists()
    out = _cli("export", store_path, "--trajectory", tum, "--map", ply, "--voxel-size-m", "0.05", "--overwrite")
    assert out.returncode == 0, out.stderr
    assert tum.read_bytes() == before[tum] and ply.exists()


def test_export_map_voxel_size_from_the_configuration(store_path: Path, tmp_path: Path) -> None:
    """`export --map` without --voxel-size-m writes every point, unless map.export_voxel_size_m is set (environment
    or the [map] table of --config); --voxel-size-m overrides both."""
    def points(name: str) -> int:
        return len(o3d.io.read_point_cloud(str(tmp_path / name)).points)

    assert _cli("export", store_path, "--map", tmp_path / "all.ply").returncode == 0
    with FrameStore.open(store_path) as store:
        total = sum(store.frame(int(i)).n_points for i in store.frame_ids)
    assert points("all.ply") == total
    env = {**os.environ, "COLUMNS": "200", "DRIFTMAP_MAP__EXPORT_VOXEL_SIZE_M": "0.05"}
    out = subprocess.run([sys.executable, "-m", "driftmap.cli", "export", str(store_path), "--map", str(tmp_path / "env.ply")],
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    assert points("env.ply") < total / 10 and "voxel 0.05 m" in out.stdout
    config = tmp_path / "c.toml"
    config.write_text("[map]\nexport_voxel_size_m = 0.05\n")
    assert _cli("export", store_path, "--map", tmp_path / "file.ply", "--config", config).returncode == 0
    assert points("file.ply") == points("env.ply")
    assert _cli("export", store_path, "--map", tmp_path / "flag.ply", "--config", config, "--voxel-size-m", "0.2").returncode == 0
    assert points("flag.ply") < points("file.ply")
    config.write_text("[map]\nexport_voxel_size = 0.05\n")
    line = _one_line_error(_cli("export", store_path, "--map", tmp_path / "typo.ply", "--config", config))
    assert f"{config}: map.export_voxel_size: unknown setting" in line and not (tmp_path / "typo.ply").exists()


def test_a_wrong_depth_scale_names_the_flag_that_fixes_it(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """Depth images in 0.1 mm units read as millimetres: build refuses, naming --depth-scale 10000 (and the
    check's switch), before a store exists; with --depth-scale 10000 the frames equal the original ones."""
    from PIL import Image

    folder = tmp_path / "tenth-mm"
    folder.mkdir()
    (folder / "camera-intrinsics.txt").symlink_to(sevenscenes_dir / "camera-intrinsics.txt")
    for i in range(2):
        depth = np.asarray(Image.open(sevenscenes_dir / f"frame-{i:06d}.depth.png")).astype(np.uint32)
        valid = (depth != 0) & (depth != 65535)
        Image.fromarray(np.where(valid, depth * 10, depth).astype(np.uint16)).save(folder / f"frame-{i:06d}.depth.png")
    line = _one_line_error(_cli("build", folder, "--out", tmp_path / "s", "--no-loop-closure"))
    assert "--depth-scale 10000" in line and "check_scale" in line and "sensor_range_m" not in line, line
    assert not (tmp_path / "s").exists()
    out = _cli("build", folder, "--out", tmp_path / "s", "--no-loop-closure", "--depth-scale", "10000")
    assert out.returncode == 0, out.stderr
    ref = _cli("build", sevenscenes_dir, "--out", tmp_path / "ref", "--frames", "0:2", "--no-loop-closure")
    assert ref.returncode == 0, ref.stderr
    with FrameStore.open(tmp_path / "s") as fixed, FrameStore.open(tmp_path / "ref") as original:
        assert fixed.frame_ids.tolist() == original.frame_ids.tolist() == [0, 1]
        for i in (0, 1):
            np.testing.assert_allclose(fixed.frame(i).points_sensor, original.frame(i).points_sensor, atol=1e-6)
    # a LiDAR source has no depth scale: the flag is refused, naming the setting and the format
    kitti = _one_line_error(_cli("build", sevenscenes_dir.parent / "kitti-00-frames0-15", "--out", tmp_path / "k",
                                 "--depth-scale", "1000"))
    assert "depth.depth_scale (--depth-scale)" in kitti and "kitti" in kitti


def test_convert_keeps_an_existing_output_unless_overwrite(tmp_path: Path) -> None:
    from driftmap.demo import embedded_log_path

    out = tmp_path / "c.mcap"
    assert _cli("convert", embedded_log_path(), out, "--frames", "0:2").returncode == 0
    first = out.read_bytes()
    line = _one_line_error(_cli("convert", embedded_log_path(), out, "--frames", "0:3"))
    assert f"{out}: already exists (OUT.mcap); pass --overwrite" in line and out.read_bytes() == first
    assert _cli("convert", embedded_log_path(), out, "--frames", "0:3", "--overwrite").returncode == 0
    assert out.read_bytes() != first


def test_messages_for_a_file_that_is_not_what_the_command_wants(store_path: Path, tmp_path: Path, kitti_dir: Path,
                                                                datasets_dir: Path) -> None:
    # a KITTI pose file read as TUM says so
    line = _one_line_error(_cli("diagnose", store_path, "--json", tmp_path / "d.json", "--gt", kitti_dir / "poses.txt"))
    assert "expected 8 columns" in line and "a KITTI pose file?" in line and "--gt-format kitti" in line
    # stamps that never meet: both ranges are named
    tum = tmp_path / "late.tum"
    assert _cli("export", store_path, "--trajectory", tum).returncode == 0
    rows = [line.split() for line in tum.read_text().splitlines() if line and not line.startswith("#")]
    tum.write_text("".join(f"{float(r[0]) + 3600:.9f} {' '.join(r[1:])}\n" for r in rows))
    line = _one_line_error(_cli("correct", store_path, "--poses", tum))
    assert "no row matched a stored frame (match by stamp)" in line and "the file's stamps span" in line
    line = _one_line_error(_cli("diagnose", store_path, "--json", tmp_path / "d.json", "--gt", tum))
    assert "the file's stamps span" in line and "the frames'" in line
    # a log file given where a store belongs: not a store (and no advice to recover it)
    bag = datasets_dir / "bags" / "nav2_turtlebot.mcap"
    line = _one_line_error(_cli("info", bag))
    assert "is a file, not a driftmap store" in line and "recover" not in line


def test_synth_keeps_an_earlier_log_unless_overwrite(tmp_path: Path) -> None:
    """``synth`` into an earlier synthetic log is refused (nothing touched) unless ``--overwrite``, which leaves no
    stale frame behind; a folder holding anything else is refused either way."""
    out = tmp_path / "log"
    small = ("--frames", "4", "--seed", "3")
    assert _cli("synth", out, *small).returncode == 0
    before = sorted(p.name for p in (out / "depth").iterdir())
    line = _one_line_error(_cli("synth", out, "--frames", "3"))
    assert "a synthetic log exists" in line and "--overwrite" in line
    assert sorted(p.name for p in (out / "depth").iterdir()) == before
    assert _cli("synth", out, "--frames", "3", "--overwrite").returncode == 0
    assert sorted(p.name for p in (out / "depth").iterdir()) == before[:3]
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    line = _one_line_error(_cli("synth", other, "--overwrite"))
    assert "holds no synthetic log" in line and [p.name for p in other.iterdir()] == ["notes.txt"]
