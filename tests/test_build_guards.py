"""``build`` guards on real data: ``--resume`` refuses another source, pose mode or depth settings, a build that
fails before storing a frame removes the store it created (and only that), an empty ``--frames`` selection says
so, the ``depth.*`` settings reach the source in their documented order.

Broken inputs are made in ``tmp_path`` from symlinks to the shared 7-Scenes files (nothing is copied) plus
files the tests write themselves (an unreadable depth image, pose files)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from driftmap.errors import ConfigError, SourceError
from driftmap.pipeline.build import BUILD_SOURCE_FILE, BuildConfig, build
from driftmap.sources.kitti import KittiOdometry
from driftmap.sources.sevenscenes import SevenScenes
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import Trajectory, write_kitti, write_tum


def _stored(path: Path) -> tuple[list[int], set[str]]:
    """Frame ids and sensor kinds of a store."""
    with FrameStore.open(path) as store:
        ids = [int(i) for i in store.frame_ids]
        return ids, {store.frame_info(i)["sensor_kind"] for i in ids}


def _linked_7scenes(sevenscenes_dir: Path, folder: Path, ids: list[int], *, poses: bool = True,
                    unreadable: int | None = None) -> Path:
    """A 7-Scenes folder of symlinks to the shared frames ``ids``; frame ``unreadable`` gets a depth file that
    is not an image."""
    folder.mkdir()
    (folder / "camera-intrinsics.txt").symlink_to(sevenscenes_dir / "camera-intrinsics.txt")
    for i in ids:
        name = f"frame-{i:06d}"
        if i == unreadable:
            (folder / f"{name}.depth.png").write_bytes(b"not a png")
        else:
            (folder / f"{name}.depth.png").symlink_to(sevenscenes_dir / f"{name}.depth.png")
        if poses:
            (folder / f"{name}.pose.txt").symlink_to(sevenscenes_dir / f"{name}.pose.txt")
    return folder


# ------------------------------------------------------------------------------------ 1. --resume, another source


def test_resume_refuses_a_different_source(sevenscenes_dir: Path, kitti_dir: Path, tmp_path: Path) -> None:
    built = tmp_path / "s"
    build(sevenscenes_dir, built, poses_from_source=True, loop_closure=False, frames="0:20:5")
    record = json.loads((built / BUILD_SOURCE_FILE).read_text())
    assert record["path"] == str(sevenscenes_dir.resolve()) and record["format"] == "7scenes"
    assert json.loads((built / "build_summary.json").read_text())["source"] == record
    store = tmp_path / "t"
    shutil.copytree(built, store)
    before = _stored(store)
    assert before == ([0, 5, 10, 15], {"depth_camera"})

    with pytest.raises(ConfigError, match="different source") as err:
        build(kitti_dir, store, resume=True, poses_from_source=True, frames="0:3")
    message = str(err.value)
    assert str(store) in message and str(sevenscenes_dir.resolve()) in message and str(kitti_dir.resolve()) in message
    assert "kitti" in message and "7scenes" in message
    assert _stored(store) == before, "the refused resume must not touch the store"

    # the same source continues, also when given through a symlink (the resolved path is compared)
    link = tmp_path / "link"
    link.symlink_to(sevenscenes_dir)
    result = build(link, store, resume=True, poses_from_source=True, loop_closure=False, frames="0:40:5")
    assert (result.n_frames_new, result.n_frames) == (4, 8)
    assert _stored(store) == ([0, 5, 10, 15, 20, 25, 30, 35], {"depth_camera"})


def test_resume_of_a_store_without_a_source_record_checks_its_frames(sevenscenes_dir: Path, kitti_dir: Path,
                                                                     tmp_path: Path) -> None:
    """A store from before the record (or made without ``build``): its stored frames' sensor kind and file
    decide; a resume that passes writes the record."""
    store = tmp_path / "s"
    build(sevenscenes_dir, store, poses_from_source=True, loop_closure=False, frames="0:20:5")
    (store / BUILD_SOURCE_FILE).unlink()
    with pytest.raises(ConfigError, match="different source") as err:
        build(kitti_dir, store, resume=True, poses_from_source=True, frames="0:3")
    assert "depth_camera" in str(err.value) and "lidar" in str(err.value) and str(store) in str(err.value)
    assert _stored(store) == ([0, 5, 10, 15], {"depth_camera"})
    assert not (store / BUILD_SOURCE_FILE).exists()

    result = build(sevenscenes_dir, store, resume=True, poses_from_source=True, loop_closure=False, frames="0:30:5")
    assert (result.n_frames_new, result.n_frames) == (2, 6)
    assert json.loads((store / BUILD_SOURCE_FILE).read_text())["path"] == str(sevenscenes_dir.resolve())


# ------------------------------------------------------------------ 2. a failed build leaves no empty store behind


def _pose_file(tmp_path: Path, case: str) -> Path:
    if case == "missing":
        return tmp_path / "nope.tum"
    if case == "empty":
        (tmp_path / "empty.tum").write_text("")
        return tmp_path / "empty.tum"
    # readable, but its stamps (100 s and later) match no 7-Scenes frame of 0:3 (stamps < 0.1 s)
    write_tum(tmp_path / "far.tum", Trajectory(np.array([100_000_000_000, 101_000_000_000]), np.stack([np.eye(4)] * 2)))
    return tmp_path / "far.tum"


@pytest.mark.parametrize("case", ["missing", "empty", "unmatched"])
def test_a_pose_file_that_cannot_be_used_leaves_no_store(sevenscenes_dir: Path, tmp_path: Path, case: str) -> None:
    poses = _pose_file(tmp_path, case)
    expected = {"missing": "cannot read trajectory file", "empty": "no data lines",
                "unmatched": "no pose within 20 ms of frame 0"}
    out = tmp_path / "x"
    with pytest.raises(SourceError, match=expected[case]) as err:
        build(sevenscenes_dir, out, frames="0:3", poses_file=poses, loop_closure=False)
    assert poses.name in str(err.value)
    assert not out.exists()
    result = build(sevenscenes_dir, out, frames="0:3", poses_from_source=True, loop_closure=False)  # the retry
    assert result.n_frames == 3


def test_the_pose_stamp_tolerance_is_an_option(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """A TUM pose file 15 ms late matches within the default 20 ms (the poses are used as given) and is refused
    with --max-dt-ms 10, the error naming the tolerance and the offset."""
    from typer.testing import CliRunner

    from driftmap.cli import app

    frames = list(SevenScenes(sevenscenes_dir, frames="0:3"))
    late = tmp_path / "late.tum"
    poses = np.stack([f.pose.T_world_sensor for f in frames])
    write_tum(late, Trajectory(np.array([f.stamp_ns + 15_000_000 for f in frames]), poses))
    result = build(sevenscenes_dir, tmp_path / "ok", frames="0:3", poses_file=late, loop_closure=False)
    assert result.n_frames == 3
    with FrameStore.open(tmp_path / "ok") as store:
        np.testing.assert_allclose(store.poses(0), poses, atol=1e-9)
    with pytest.raises(SourceError, match=r"no pose within 10 ms of frame 0 .*\+15000000 ns away"):
        build(sevenscenes_dir, tmp_path / "strict", frames="0:3", poses_file=late, loop_closure=False,
              poses_max_dt_ns=10_000_000)
    assert not (tmp_path / "strict").exists()
    out = CliRunner().invoke(app, ["build", str(sevenscenes_dir), "--out", str(tmp_path / "cli"), "--frames", "0:3",
                                   "--poses", str(late), "--no-loop-closure", "--max-dt-ms", "10"])
    assert out.exit_code != 0 and "within 10 ms" in " ".join(str(out.exception).split())


def test_a_kitti_pose_file_without_the_rows_leaves_no_store(kitti_dir: Path, tmp_path: Path) -> None:
    short = tmp_path / "short.txt"
    write_kitti(short, Trajectory(np.arange(2), np.stack([np.eye(4)] * 2), np.arange(2)))
    out = tmp_path / "k"
    with pytest.raises(SourceError, match="2 rows, no pose for frame 4"):
        build(kitti_dir, out, frames="4:8", poses_file=short, loop_closure=False, kitti_frame="velodyne")
    assert not out.exists()
    result = build(kitti_dir, out, frames="4:8", poses_file=kitti_dir / "poses.txt", loop_closure=False)
    assert result.n_frames == 4


def test_poses_from_a_source_without_poses_leaves_no_store(sevenscenes_dir: Path, tmp_path: Path) -> None:
    folder = _linked_7scenes(sevenscenes_dir, tmp_path / "no-poses", [0, 1, 2], poses=False)
    out = tmp_path / "x"
    with pytest.raises(SourceError, match="pose of frame 0 not found"):
        build(folder, out, poses_from_source=True, loop_closure=False)
    assert not out.exists()
    result = build(folder, out, loop_closure=False)  # the retry, with our own odometry
    assert result.n_frames == 3 and result.pose_source == "odometry"


def test_a_failure_before_the_first_frame_removes_only_what_the_build_created(sevenscenes_dir: Path,
                                                                              tmp_path: Path) -> None:
    """The safety net behind the input checks: frame 0 cannot be read once the store exists (pixel_stride
    given, so nothing reads a frame before)."""
    folder = _linked_7scenes(sevenscenes_dir, tmp_path / "broken", [0, 1], unreadable=0)
    config = BuildConfig(pixel_stride=4)
    nested = tmp_path / "a" / "b" / "store"  # build creates a, a/b and the store
    with pytest.raises(SourceError, match="cannot read depth image of frame 0"):
        build(folder, nested, config=config, loop_closure=False)
    assert not (tmp_path / "a").exists()
    assert tmp_path.exists() and folder.exists()

    empty = tmp_path / "empty"  # a folder that was there (empty) before stays, empty
    empty.mkdir()
    with pytest.raises(SourceError, match="cannot read depth image of frame 0"):
        build(folder, empty, config=config, loop_closure=False)
    assert empty.is_dir() and not any(empty.iterdir())

    result = build(sevenscenes_dir, nested, config=config, frames="0:2", loop_closure=False)  # the retry
    assert result.n_frames == 2


def test_a_lidar_place_descriptor_on_depth_frames_is_refused_before_anything_is_stored(sevenscenes_dir: Path,
                                                                                        tmp_path: Path) -> None:
    """Scan Context needs a z-up LiDAR frame; asked for on a depth camera's frames it is a ConfigError at the
    first frame, naming the setting and the sensor, and no store is left behind."""
    from driftmap.registration.loops import LoopClosureConfig

    out = tmp_path / "x"
    config = BuildConfig(loop_closure=LoopClosureConfig(place_descriptor="scan_context"))
    with pytest.raises(ConfigError, match=r"place_descriptor = 'scan_context' needs LiDAR scans.*frame 0 .*depth"):
        build(sevenscenes_dir, out, config=config, frames="0:3")
    assert not out.exists()
    build(sevenscenes_dir, out, config=config, frames="0:3", loop_closure=False)  # without loop closure it is unused


def test_a_store_with_frames_or_a_resumed_store_is_never_deleted(sevenscenes_dir: Path, tmp_path: Path) -> None:
    folder = _linked_7scenes(sevenscenes_dir, tmp_path / "broken", [0, 1, 2], unreadable=2)
    config = BuildConfig(pixel_stride=4)
    # a new store that failed after two frames: kept, with them
    kept = tmp_path / "kept"
    with pytest.raises(SourceError, match="frame 2"):
        build(folder, kept, config=config, poses_from_source=True, loop_closure=False)
    assert _stored(kept)[0] == [0, 1]

    # a resumed store, with frames or without, is not removed when the resume fails before storing a frame
    with pytest.raises(SourceError, match="frame 2"):
        build(folder, kept, config=config, poses_from_source=True, loop_closure=False, resume=True)
    assert _stored(kept)[0] == [0, 1]
    empty = tmp_path / "empty-store"
    FrameStore.create(empty).close()
    with pytest.raises(SourceError, match="frame 2"):
        build(folder, empty, config=config, frames="2:3", loop_closure=False, resume=True)
    assert (empty / "store.json").exists() and _stored(empty)[0] == []


# ------------------------------------------------------------------------------------ 3. an empty --frames selection


@pytest.mark.parametrize("frames", ["5:5", "2000:2010"])
def test_an_empty_frame_selection_says_so(sevenscenes_dir: Path, tmp_path: Path, frames: str) -> None:
    n = len(SevenScenes(sevenscenes_dir))
    with pytest.raises(ConfigError) as err:
        build(sevenscenes_dir, tmp_path / "x", frames=frames)
    assert str(err.value).startswith(f"--frames {frames} selects no frame")
    assert f"the source has {n} frames" in str(err.value) and str(sevenscenes_dir) in str(err.value)
    assert "out of range" not in str(err.value)
    assert not (tmp_path / "x").exists()


def test_an_empty_frame_selection_on_a_lidar_source(kitti_dir: Path, tmp_path: Path) -> None:
    """KITTI reads no frame while opening (no pixel stride to pick): the selection is checked by its length."""
    n = len(KittiOdometry(kitti_dir))
    with pytest.raises(ConfigError, match=f"--frames {n}:{n + 10} selects no frame .*the source has {n} frames"):
        build(kitti_dir, tmp_path / "k", frames=f"{n}:{n + 10}")
    assert not (tmp_path / "k").exists()


def test_a_run_too_short_for_loop_closure_says_so(sevenscenes_dir: Path, tmp_path: Path,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    import logging

    with caplog.at_level(logging.WARNING, logger="driftmap.pipeline.build"):
        result = build(sevenscenes_dir, tmp_path / "s", poses_from_source=True, frames="0:3")
    assert result.loop_revision is None
    skipped = [r.getMessage() for r in caplog.records if "loop closure skipped" in r.getMessage()]
    assert len(skipped) == 1
    # the summary counts the keyframes the warning names (it said 0 before), and the gap is in seconds
    assert result.n_keyframes >= 1 and f"the {result.n_keyframes} keyframes (of 3 stored frames" in skipped[0]
    assert "source frames 0..2)" in skipped[0] and "span source frames 0..0 (0.00 s)" in skipped[0]
    assert "min_gap_s = 2 s" in skipped[0]
    assert json.loads((tmp_path / "s" / "build_summary.json").read_text())["n_keyframes"] == result.n_keyframes


# ------------------------------------------------------------------------ 4. --resume, another pose mode or depth


def test_resume_refuses_a_different_pose_mode(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """Odometry, --poses FILE (and which file) and --poses-from-source put revision 0 in different coordinate
    frames: a resume with another mode is refused, naming both, and leaves the store as it was."""
    store = tmp_path / "s"
    build(sevenscenes_dir, store, frames="0:9:3", loop_closure=False)  # our odometry: frame 0 at the origin
    before = _stored(store)
    with pytest.raises(ConfigError, match="different poses") as err:
        build(sevenscenes_dir, store, frames="0:10", poses_from_source=True, loop_closure=False, resume=True)
    assert "odometry" in str(err.value) and "--poses-from-source" in str(err.value) and str(store) in str(err.value)
    gt = SevenScenes(sevenscenes_dir, frames="0:12", poses_from_ground_truth=True)
    first = tmp_path / "first.tum"
    write_tum(first, Trajectory(np.array([f.stamp_ns for f in gt]), np.stack([f.pose.T_world_sensor for f in gt])))
    with pytest.raises(ConfigError, match="different poses") as err:
        build(sevenscenes_dir, store, frames="0:12:3", poses_file=first, loop_closure=False, resume=True)
    assert f"--poses {first}" in str(err.value)
    assert _stored(store) == before
    result = build(sevenscenes_dir, store, frames="0:12:3", loop_closure=False, resume=True)  # the same mode continues
    assert (result.n_frames_new, result.n_frames) == (1, 4)

    # a store placed with one pose file refuses another file, and the source's own poses
    placed = tmp_path / "p"
    build(sevenscenes_dir, placed, frames="0:6:3", poses_file=first, loop_closure=False)
    second = tmp_path / "second.tum"
    second.write_bytes(first.read_bytes())
    with pytest.raises(ConfigError, match="different poses") as err:
        build(sevenscenes_dir, placed, frames="0:12:3", poses_file=second, loop_closure=False, resume=True)
    assert str(first) in str(err.value) and str(second) in str(err.value)
    with pytest.raises(ConfigError, match="different poses"):
        build(sevenscenes_dir, placed, frames="0:12:3", poses_from_source=True, loop_closure=False, resume=True)
    assert build(sevenscenes_dir, placed, frames="0:12:3", poses_file=first, loop_closure=False, resume=True).n_frames == 4


def test_resume_of_a_store_recorded_without_the_pose_mode_checks_revision_0(sevenscenes_dir: Path,
                                                                             tmp_path: Path) -> None:
    """A record from before the pose mode was recorded: revision 0's pose source decides (ground truth is not
    odometry); a resume that passes completes the record."""
    store = tmp_path / "s"
    build(sevenscenes_dir, store, frames="0:6:3", poses_from_source=True, loop_closure=False)
    record = json.loads((store / BUILD_SOURCE_FILE).read_text())
    assert record["poses"] == {"mode": "source"} and record["depth"] == {}
    old = {k: record[k] for k in ("path", "format", "given")}
    (store / BUILD_SOURCE_FILE).write_text(json.dumps(old))
    with pytest.raises(ConfigError, match="different poses.*ground_truth"):
        build(sevenscenes_dir, store, frames="0:9:3", loop_closure=False, resume=True)
    assert build(sevenscenes_dir, store, frames="0:9:3", poses_from_source=True, loop_closure=False, resume=True).n_frames == 3
    assert json.loads((store / BUILD_SOURCE_FILE).read_text()) == record


def test_depth_settings_reach_the_source_and_resume_checks_them(sevenscenes_dir: Path, kitti_dir: Path,
                                                                tmp_path: Path) -> None:
    from driftmap.config import DepthConfig

    plain = build(sevenscenes_dir, tmp_path / "plain", frames="0:2", poses_from_source=True, loop_closure=False)
    near = tmp_path / "near"
    build(sevenscenes_dir, near, frames="0:2", poses_from_source=True, loop_closure=False,
          depth=DepthConfig(max_depth_m=1.5))
    with FrameStore.open(tmp_path / "plain") as a, FrameStore.open(near) as b:
        for fid in (0, 1):
            p, q = a.frame(fid).points_sensor, b.frame(fid).points_sensor
            assert len(q) < 0.5 * len(p) and q[:, 2].max() < 1.5 <= p[:, 2].max()
            # exactly the plain frame's points nearer than 1.5 m
            assert len(q) == int(np.sum(p[:, 2] < 1.5))
    assert plain.n_frames == 2
    assert json.loads((near / BUILD_SOURCE_FILE).read_text())["depth"] == {"max_depth_m": 1.5}
    with pytest.raises(ConfigError, match="different depth settings.*max_depth_m=1.5"):
        build(sevenscenes_dir, near, frames="0:3", poses_from_source=True, loop_closure=False, resume=True)
    with pytest.raises(ConfigError, match=r"depth\.max_depth_m: does not apply .*format kitti"):
        build(kitti_dir, tmp_path / "k", frames="0:2", depth=DepthConfig(max_depth_m=1.5))
    assert not (tmp_path / "k").exists()


def test_build_applies_the_depth_table_environment_and_flag_in_order(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """defaults < [depth] table of --config < DRIFTMAP_DEPTH__* < --depth-scale; a typo in the table is refused
    naming the file and the key, before any store is made."""
    import os
    import subprocess
    import sys

    def run(out: str, *args: object, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
        clean = {k: v for k, v in os.environ.items() if not k.startswith("DRIFTMAP_DEPTH")}
        return subprocess.run([sys.executable, "-m", "driftmap.cli", "build", str(sevenscenes_dir), "--out",
                               str(tmp_path / out), "--frames", "0:1", "--no-loop-closure", "--poses-from-source",
                               *map(str, args)], capture_output=True, text=True, timeout=300,
                              env={**clean, "COLUMNS": "200", **(env or {})})

    def max_z(out: str) -> float:
        with FrameStore.open(tmp_path / out) as store:
            return float(store.frame(0).points_sensor[:, 2].max())

    config = tmp_path / "d.toml"
    config.write_text("[depth]\nmax_depth_m = 1.5\n")
    assert run("file", "--config", config).returncode == 0
    assert run("env", "--config", config, env={"DRIFTMAP_DEPTH__MAX_DEPTH_M": "2.5"}).returncode == 0
    assert run("default").returncode == 0
    assert max_z("file") < 1.5 and 1.5 < max_z("env") < 2.5 and max_z("default") > 2.5
    # --depth-scale above the environment: 2000 units/m halves every depth
    assert run("flag", "--depth-scale", 2000, env={"DRIFTMAP_DEPTH__DEPTH_SCALE": "1000"}).returncode == 0
    with FrameStore.open(tmp_path / "default") as a, FrameStore.open(tmp_path / "flag") as b:
        p, q = a.frame(0).points_sensor, b.frame(0).points_sensor
        # every point at half the range (depths halved below the 0.2 m minimum would be rejected)
        np.testing.assert_allclose(q, 0.5 * p[p[:, 2] >= 0.4], rtol=1e-6)
    typo = tmp_path / "typo.toml"
    typo.write_text("[depth]\nmax_depth_mm = 1.5\n\n[build]\npixel_stride = 2\n")
    out = run("typo", "--config", typo)
    assert out.returncode == 1 and not (tmp_path / "typo").exists()
    assert f"{typo}: depth.max_depth_mm: unknown setting" in " ".join(out.stderr.split()), out.stderr


def test_intrinsics_reach_the_sources_that_take_them(datasets_dir: Path, kitti_dir: Path, tmp_path: Path) -> None:
    """--intrinsics / depth.intrinsics: the data set's own values give the same frames; a focal length 10 % longer
    pulls every point 10 % closer to the optical axis (x/z and y/z shrink by 1/1.1); a LiDAR source takes none."""
    import subprocess
    import sys

    from driftmap.config import DepthConfig

    icl = datasets_dir / "icl-nuim-livingroom1-5frames"
    runs = {"own": None, "same": "525,525,319.5,239.5", "longer": "577.5,577.5,319.5,239.5,640,480"}
    for name, value in runs.items():
        build(icl, tmp_path / name, frames="0:2", poses_from_source=True, loop_closure=False,
              depth=DepthConfig(intrinsics=value))
    with FrameStore.open(tmp_path / "own") as a, FrameStore.open(tmp_path / "same") as b, \
            FrameStore.open(tmp_path / "longer") as c:
        for fid in a.frame_ids:
            p, q, r = (s.frame(int(fid)).points_sensor for s in (a, b, c))
            assert np.array_equal(p, q)
            assert len(r) == len(p)
            np.testing.assert_allclose(r[:, 2], p[:, 2], rtol=1e-6)
            np.testing.assert_allclose(r[:, :2] * 1.1, p[:, :2], atol=2e-6)
            assert c.frame(int(fid)).intrinsics.fx == pytest.approx(1.1 * a.frame(int(fid)).intrinsics.fx)  # (pixel stride 2)
    with pytest.raises(ConfigError, match=r"depth\.intrinsics \(--intrinsics\): does not apply .*format kitti"):
        build(kitti_dir, tmp_path / "k", frames="0:1", depth=DepthConfig(intrinsics="fr1"))
    bad = subprocess.run([sys.executable, "-m", "driftmap.cli", "build", str(icl), "--out", str(tmp_path / "bad"),
                          "--intrinsics", "525,525,319.5"], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and "depth.intrinsics" in bad.stderr and "3 numbers" in bad.stderr, bad.stderr
    assert not (tmp_path / "bad").exists()


def test_source_options_choose_the_stream_and_resume_checks_them(tmp_path: Path) -> None:
    """--sensor reads the synthetic log's LiDAR (build and convert); an option the format does not take is
    refused naming the flag, before a store is made; a resume must read the same stream."""
    import subprocess
    import sys

    from driftmap.sources.base import open_source
    from driftmap.sources.synthetic import SyntheticLog, SyntheticLogConfig, generate_synthetic_log

    log = generate_synthetic_log(tmp_path / "log", SyntheticLogConfig(n_frames=4, width=80, height=60, fx=65.6,
                                                                      fy=65.6, cx=39.5, cy=29.5, lidar=True))

    def cli(*args: object) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                              timeout=300, env={**os.environ, "COLUMNS": "250"})

    out = cli("build", log, "--out", tmp_path / "s", "--sensor", "lidar", "--poses-from-source", "--no-loop-closure")
    assert out.returncode == 0, out.stderr
    lidar = SyntheticLog(log, sensor="lidar")
    with FrameStore.open(tmp_path / "s") as store:
        assert store.frame_info(0)["sensor_kind"] == "lidar"
        assert store.frame(2).points_sensor.tobytes() == lidar.frame(2).points_sensor.tobytes()
        np.testing.assert_allclose(store.poses(0), lidar.odometry().poses, atol=1e-12)
    assert json.loads((tmp_path / "s" / BUILD_SOURCE_FILE).read_text())["source_options"] == {"sensor": "lidar"}
    again = cli("build", log, "--out", tmp_path / "s", "--poses-from-source", "--no-loop-closure", "--resume")
    assert again.returncode == 1 and "different source options" in again.stderr and "--sensor lidar" in again.stderr
    bad = cli("build", log, "--out", tmp_path / "t", "--topic", "/points")
    assert bad.returncode == 1 and "--topic: does not apply" in bad.stderr and "--sensor" in bad.stderr
    assert not (tmp_path / "t").exists()
    mcap = tmp_path / "lidar.mcap"
    assert cli("convert", log, mcap, "--sensor", "lidar").returncode == 0
    back = open_source(mcap)
    assert [f.sensor_kind.value for f in back] == ["lidar"] * 4
    assert back.frame(1).points_sensor.tobytes() == lidar.frame(1).points_sensor.tobytes()


def test_a_pose_file_that_ends_before_the_log_says_so_and_the_way_out(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """Trial 13 (F8): a pose file ending before the log failed at the first frame past its end with only a signed
    nanosecond distance. The error now gives the distance in seconds, the file's span and, for a frame outside it, the
    way out (--frames, or odometry and `driftmap correct`); a frame inside the span with no row near it gets the
    tolerance's hint instead."""
    frames = list(SevenScenes(sevenscenes_dir, frames="0:3"))
    short = tmp_path / "short.tum"
    write_tum(short, Trajectory(np.array([f.stamp_ns for f in frames[:2]]),
                                np.stack([f.pose.T_world_sensor for f in frames[:2]])))
    with pytest.raises(SourceError, match=r"no pose within 20 ms of frame 2 .* s (after|before) it\)") as err:
        build(sevenscenes_dir, tmp_path / "a", frames="0:3", poses_file=short, loop_closure=False)
    text = str(err.value)
    assert "the file's 2 rows span stamps" in text and "the frame lies outside them" in text, text
    assert "--frames" in text and "driftmap correct" in text, text
    gap = tmp_path / "gap.tum"  # rows for frames 0 and 2 only: frame 1 lies inside the span
    write_tum(gap, Trajectory(np.array([frames[0].stamp_ns, frames[2].stamp_ns]),
                              np.stack([frames[0].pose.T_world_sensor, frames[2].pose.T_world_sensor])))
    with pytest.raises(SourceError, match=r"frame 1 .*--max-dt-ms") as err:
        build(sevenscenes_dir, tmp_path / "b", frames="0:3", poses_file=gap, loop_closure=False)
    assert "lies outside" not in str(err.value)
