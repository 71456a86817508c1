"""Hostile trial 29: its findings, each through the path the user took (docs/bad-input.md, trial 29)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli

from driftmap.errors import ConfigError
from driftmap.pipeline.build import build
from driftmap.store.frame_store import FrameStore
from driftmap.volume import VolumeConfig, VolumeLayers


def test_t29_b1_layers_apply_refuses_another_store(room10: dict[str, Path], tmp_path: Path) -> None:
    """``VolumeLayers.apply(revision, other_store)`` took a second build of the same log and answered for it (its
    frames, same ids, placed elsewhere); another log's store ended in a raw numpy error. The layers name their store:
    another one is a ConfigError naming both ids, and the layers are left as they were."""
    build(room10["log"], tmp_path / "second", loop_closure=False)
    with FrameStore.open(room10["gt"]) as mine, FrameStore.open(tmp_path / "second") as other:
        layers = VolumeLayers.from_store(mine, config=VolumeConfig(voxel_size_m=0.1))
        hits = layers.arrays.hits.copy()
        assert np.array_equal(sorted(other.frame_ids), sorted(mine.frame_ids))  # the frames alone cannot tell
        with pytest.raises(ConfigError, match=rf"another store \(id {mine.uuid}\).*{other.uuid}"):
            layers.apply(other.head, other)
        assert np.array_equal(layers.arrays.hits, hits) and layers.revision == mine.head
        layers.apply(mine.head, mine)  # its own store: taken (nothing moved)
        assert np.array_equal(layers.arrays.hits, hits)
        # layers that name no store (made by hand) are judged by their frames: a store without some of them is
        # another store
        anonymous = dataclasses.replace(layers, store_uuid=None)
    build(room10["log"], tmp_path / "half", loop_closure=False, frames="0:5")
    with FrameStore.open(tmp_path / "half") as half:
        with pytest.raises(ConfigError, match=r"integrate frames .* does not hold \(\[5, 6, 7, 8, 9\]\)"):
            anonymous.apply(half.head, half)



def test_t29_w2_a_batch_config_is_taken_by_every_command(room10: dict[str, Path], tmp_path: Path) -> None:
    """A batch config (a ``[fleet]`` table next to the tables of build, diagnose and export) was refused by every
    command but ``batch`` ("unknown top-level settings ['fleet']"): each takes its own tables from it and leaves
    ``[fleet]`` to batch; a file holding only ``[fleet]`` is refused where nothing in it applies."""
    cfg = tmp_path / "fleet.toml"
    cfg.write_text('[fleet]\nexports = ["trajectory", "map"]\nloop_closure = false\n\n[build]\npixel_stride = 1\n\n'
                   '[map]\nexport_voxel_size_m = 0.25\n\n[diagnose.sampling]\npoints_budget = 200000\n')
    shown = run_cli("config", "--file", cfg)
    assert shown.returncode == 0, shown.stderr[-800:]
    assert "export_voxel_size_m" in shown.stdout and "0.25" in shown.stdout
    built = run_cli("build", room10["log"], "--out", tmp_path / "store", "--config", cfg, "--no-loop-closure")
    assert built.returncode == 0, built.stderr[-800:]
    coarse, fine = tmp_path / "coarse.ply", tmp_path / "fine.ply"
    for out, extra in ((coarse, ["--config", cfg]), (fine, [])):
        done = run_cli("export", room10["gt"], "--map", out, *extra)
        assert done.returncode == 0, done.stderr[-800:]
    import open3d as o3d

    n_coarse = len(o3d.io.read_point_cloud(str(coarse)).points)
    assert 0 < n_coarse < len(o3d.io.read_point_cloud(str(fine)).points)  # the [map] table applied
    diagnosed = run_cli("diagnose", room10["gt"], "--config", cfg, "--json", tmp_path / "d.json")
    assert diagnosed.returncode == 0, diagnosed.stderr[-800:]
    only = tmp_path / "only.toml"
    only.write_text('[fleet]\nexports = ["map"]\n')
    line = one_error(run_cli("export", room10["gt"], "--config", only, "--map", tmp_path / "x.ply"))
    assert "holds only a [fleet] table" in line and "batch" in line, line


def test_t29_build_settings_are_checked_as_written(tmp_path: Path) -> None:
    """A build table's settings are checked as the file wrote them, as the other tables' are: ``loop_closure =
    false`` (a table's settings given one flag) read "environment DRIFTMAP_BUILD: build: loop_closure: expected
    LoopClosureConfig" although no environment variable was set; a number in quotes was taken as the number."""
    cases = [("[build]\nloop_closure = false\n",
              "build.loop_closure: expected a table of settings ([build.loop_closure] ...), got false"),
             ('[build]\npixel_stride = "2"\n', "build.pixel_stride: expected a number, got '2' (text, in quotes"),
             ("pixel_stride = true\n", "pixel_stride: expected a number, got true")]
    for k, (text, expected) in enumerate(cases):
        path = tmp_path / f"c{k}.toml"
        path.write_text(text)
        line = one_error(run_cli("config", "--file", path))
        assert line == f"error: {path}: {expected}" or line.startswith(f"error: {path}: {expected}"), line
        assert "environment" not in line, line


@pytest.fixture(scope="module")
def two_frames(room10: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A store of the first two frames of the room log, placed by its ground truth."""
    out = tmp_path_factory.mktemp("t29") / "two"
    build(room10["log"], out, poses_file=room10["log"] / "groundtruth.txt", loop_closure=False, frames="0:2")
    return out


def test_t29_w3_the_mesh_weight_threshold_is_settable(two_frames: Path, tmp_path: Path) -> None:
    """``export --mesh`` of a short log found "no surface": marching cubes takes voxels observed by at least 3
    frames (Open3D's default), which was neither settable nor said. ``--mesh-weight-threshold`` (and
    ``map.mesh_weight_threshold`` in a config file) sets it, for ``--mesh`` in every format and the MCAP's mesh; the
    refusal names both."""
    import open3d as o3d

    line = one_error(run_cli("export", two_frames, "--mesh", tmp_path / "m.ply"))
    assert "no surface to mesh" in line and "--mesh-weight-threshold" in line and "map.mesh_weight_threshold" in line, line
    assert not (tmp_path / "m.ply").exists()
    counts = {}
    for suffix in (".ply", ".obj", ".stl"):
        out = tmp_path / f"m1{suffix}"
        done = run_cli("export", two_frames, "--mesh", out, "--mesh-weight-threshold", "1")
        assert done.returncode == 0, done.stderr[-800:]
        counts[suffix] = len(o3d.io.read_triangle_mesh(str(out)).triangles)
    assert counts[".ply"] > 100 and len(set(counts.values())) == 1, counts
    cfg = tmp_path / "c.toml"
    cfg.write_text("[map]\nmesh_weight_threshold = 1\n")
    done = run_cli("export", two_frames, "--mesh", tmp_path / "c.ply", "--config", cfg)
    assert done.returncode == 0, done.stderr[-800:]
    assert len(o3d.io.read_triangle_mesh(str(tmp_path / "c.ply")).triangles) == counts[".ply"]
    # 2 frames at threshold 2 (both saw it) cover fewer voxels than at 1
    done = run_cli("export", two_frames, "--mesh", tmp_path / "m2.ply", "--mesh-weight-threshold", "2")
    if done.returncode == 0:
        assert len(o3d.io.read_triangle_mesh(str(tmp_path / "m2.ply")).triangles) < counts[".ply"]
    else:
        assert "no surface to mesh" in one_error(done)
    # the MCAP's mesh: left out (warned) at the default, written at 1
    plain = run_cli("export", two_frames, "--mcap", tmp_path / "a.mcap")
    assert plain.returncode == 0 and "TSDF mesh of revision" in plain.stderr, plain.stderr[-800:]
    low = run_cli("export", two_frames, "--mcap", tmp_path / "b.mcap", "--mesh-weight-threshold", "1")
    assert low.returncode == 0 and "TSDF mesh of revision" not in low.stderr, low.stderr[-800:]
    for args, expected in ((["--mesh", tmp_path / "z.ply", "--mesh-weight-threshold", "0"], "above 0"),
                           (["--map", tmp_path / "z.ply", "--mesh-weight-threshold", "1"], "give --mesh or --mcap"),
                           (["--mcap", tmp_path / "z.mcap", "--no-volume", "--mesh-weight-threshold", "1"],
                            "give --mesh or --mcap")):
        line = one_error(run_cli("export", two_frames, *args))
        assert "--mesh-weight-threshold" in line and expected in line, line


def _swap(a: Path, b: Path) -> None:
    tmp = a.with_name("tmp")
    a.rename(tmp)
    b.rename(a)
    tmp.rename(b)


@pytest.fixture(scope="module")
def rolled(room10: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """room10's store with three rollbacks: segments 1-3 hold one revision each, all of one size."""
    import shutil

    out = tmp_path_factory.mktemp("t29") / "rolled"
    shutil.copytree(room10["gt"], out)
    for to in (0, 0, 0):
        done = run_cli("rollback", out, "--to", to)
        assert done.returncode == 0, done.stderr[-500:]
    sizes = [(out / f"segment-00000{k}.mcap").stat().st_size for k in (1, 2, 3)]
    assert len(set(sizes)) == 1, sizes
    return out


def test_t29_w1_recover_names_swapped_segments_back(rolled: Path, tmp_path: Path) -> None:
    """Two intact segments swapped by name: every command sent the user to ``recover``, which said "corrected,
    nothing is lost" and failed the same way. It renames them back by what the manifest records they hold (no byte
    rewritten), and the store reads as before; the same for segments of different sizes."""
    import shutil

    originals = {p.name: p.read_bytes() for p in rolled.glob("segment-*.mcap")}
    for a, b in (("segment-000001.mcap", "segment-000003.mcap"), ("segment-000000.mcap", "segment-000002.mcap")):
        store = tmp_path / f"{a[-6]}{b[-6]}"
        shutil.copytree(rolled, store)
        _swap(store / a, store / b)
        line = one_error(run_cli("info", store))
        assert "driftmap recover" in line, line
        done = run_cli("recover", store)
        assert done.returncode == 0, done.stderr[-800:]
        out = " ".join(done.stdout.split())
        assert f"{b}: was named {a}: renamed back" in out and f"{a}: was named {b}: renamed back" in out, out
        assert {p.name: p.read_bytes() for p in store.glob("segment-*.mcap")} == originals
        assert not list(store.glob("*.damaged*")) and not (store / "recover-renames.json").exists()
        assert run_cli("info", store).returncode == 0


def test_t29_w1_a_recovery_stopped_while_renaming_is_finished(rolled: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """The renames go through a journal: a recovery that fails after some of its moves leaves files named
    ``*.renaming``; the next recovery finishes the moves and the store is as it was."""
    import os
    import shutil
    import sys

    from driftmap.errors import StoreError

    originals = {p.name: p.read_bytes() for p in rolled.glob("segment-*.mcap")}
    store = tmp_path / "s"
    shutil.copytree(rolled, store)
    _swap(store / "segment-000001.mcap", store / "segment-000002.mcap")
    module = sys.modules["driftmap.store.renamed_segments"]
    real, calls = os.replace, []

    def failing(src: object, dst: object) -> None:
        calls.append(1)
        if len(calls) == 3:
            raise OSError(5, "Input/output error", str(src))
        real(src, dst)

    monkeypatch.setattr(module.os, "replace", failing)
    with pytest.raises(StoreError):
        FrameStore.recover(store)
    monkeypatch.setattr(module.os, "replace", real)
    assert list(store.glob("*.renaming")) and (store / "recover-renames.json").exists()
    FrameStore.recover(store)
    assert {p.name: p.read_bytes() for p in store.glob("segment-*.mcap")} == originals
    with FrameStore.open(store) as s:
        assert len(s.ledger.revisions) == 4


def test_a_converted_depth_log_holds_the_points_a_build_of_its_source_stores(sevenscenes_dir: Path, kitti_dir: Path,
                                                                            tmp_path: Path) -> None:
    """``driftmap convert`` of a 640 px depth data set wrote every pixel as PointCloud2, and a build of the MCAP keeps
    every point of a cloud: 4x the points of a build of the folder (read at every second pixel). convert reads depth
    images as build does (``--pixel-stride N`` overrides; 1 keeps every pixel), on a data set folder and on a ROS log
    of depth images alike; on a source of point clouds the flag is refused."""
    from PIL import Image

    from cli_run import small_sevenscenes_log
    from driftmap.export import write_depth_image_mcap
    from driftmap.frame import PinholeIntrinsics

    log = small_sevenscenes_log(sevenscenes_dir, tmp_path / "d7", 2)
    depths = [np.array(Image.open(log / f"frame-{i:06d}.depth.png")) for i in range(2)]
    K = PinholeIntrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
    ros = write_depth_image_mcap(tmp_path / "d7-images.mcap", depths, [1_700_000_000_000_000_000 + k * 33_333_333
                                                                       for k in range(2)], K, compression="none")["out"]
    built = run_cli("build", log, "--out", tmp_path / "folder", "--no-loop-closure", "--poses-from-source")
    assert built.returncode == 0, built.stderr[-1500:]
    with FrameStore.open(tmp_path / "folder") as s:
        folder_points = s.frame(int(s.frame_ids[0])).points_sensor
    for name, src in (("from-folder", log), ("from-images", ros)):
        for stride, expected in ((None, 2), (1, 1), (4, 4)):
            out = tmp_path / f"{name}-{stride}.mcap"
            done = run_cli("convert", src, out, *(("--pixel-stride", stride) if stride else ()))
            assert done.returncode == 0, done.stderr[-1500:]
            assert f"pixel stride {expected}" in " ".join(done.stdout.split()), done.stdout
            store = tmp_path / f"{name}-{stride}"
            built = run_cli("build", out, "--out", store, "--no-loop-closure")
            assert built.returncode == 0, built.stderr[-1500:]
            with FrameStore.open(store) as s:
                points = s.frame(int(s.frame_ids[0])).points_sensor
            if stride is None:  # the points a build of the folder stores
                assert len(points) == len(folder_points) > 10_000
                assert np.allclose(points, folder_points, atol=1e-6)
            else:
                assert abs(len(points) * expected ** 2 / (len(folder_points) * 4) - 1) < 0.05, (stride, len(points))
    line = one_error(run_cli("convert", kitti_dir, tmp_path / "k.mcap", "--frames", "0:1", "--pixel-stride", "2"))
    assert "--pixel-stride" in line and "holds point clouds, not depth images" in line, line
    assert not (tmp_path / "k.mcap").exists()


def test_t30_b1_segment_files_left_mid_rename_are_never_declared_lost(rolled: Path, tmp_path: Path) -> None:
    """Hostile trial 30 B1 / W1: a segment file left as ``*.renaming`` with the rename journal gone (deleted by hand
    after a recovery was killed, or renamed so) was declared lost by ``recover`` ("file not found"), a permanent
    ``data_lost`` record although its bytes were there; an unreadable journal blocked ``recover`` for good. Files
    mid-rename are placed by what they hold; an unreadable journal is removed."""
    import shutil

    originals = {p.name: p.read_bytes() for p in rolled.glob("segment-*.mcap")}
    cases = {
        # its own name is missing
        "own": lambda s: (s / "segment-000001.mcap").rename(s / "segment-000001.mcap.renaming"),
        # killed between the two moves of a swap back: 2 holds its own bytes, 1's bytes wait under 2's name
        "other": lambda s: (s / "segment-000001.mcap").rename(s / "segment-000002.mcap.renaming"),
        # the first move of a swap, then the journal damaged
        "journal": lambda s: ((s / "segment-000000.mcap").rename(s / "segment-000000.mcap.renaming"),
                              (s / "recover-renames.json").write_text("{not json")),
        # a damaged journal and nothing mid-rename
        "stale": lambda s: (s / "recover-renames.json").write_text('{"moves": [["../x", "y"]], "next": 0}'),
    }
    for name, damage in cases.items():
        store = tmp_path / name
        shutil.copytree(rolled, store)
        damage(store)
        done = run_cli("recover", store)
        assert done.returncode == 0, (name, done.stderr[-800:])
        assert "lost" not in done.stdout, (name, done.stdout)
        assert {p.name: p.read_bytes() for p in store.glob("segment-*.mcap")} == originals, name
        assert not list(store.glob("*.renaming")) and not (store / "recover-renames.json").exists(), name
        assert run_cli("info", store).returncode == 0


def test_t30_w2_layers_refresh_refuses_another_store(room10: dict[str, Path], tmp_path: Path) -> None:
    """``VolumeLayers.refresh(other_store)`` did nothing without a word, while ``apply`` refused it."""
    build(room10["log"], tmp_path / "second", loop_closure=False, frames="0:5")
    with FrameStore.open(room10["gt"]) as mine, FrameStore.open(tmp_path / "second") as other:
        layers = VolumeLayers.from_store(mine, config=VolumeConfig(voxel_size_m=0.1))
        with pytest.raises(ConfigError, match=r"VolumeLayers.refresh: the layers are of another store"):
            layers.refresh(other)
        assert len(layers.refresh(mine).frame_ids) == 0  # its own store: nothing new


def test_t30_w4_diagnose_names_a_bare_build_config(room10: dict[str, Path], tmp_path: Path) -> None:
    """``diagnose --config`` of a bare build config (build settings, no table) said only "pixel_stride: unknown
    setting", as if a diagnose setting were misspelt: it says that the file holds build settings only, as export does;
    a bare file of diagnose settings is still taken."""
    bare = tmp_path / "bare.toml"
    bare.write_text("pixel_stride = 2\n")
    line = one_error(run_cli("diagnose", room10["gt"], "--config", bare, "--json", tmp_path / "d.json"))
    assert "holds only build settings (pixel_stride; a bare build config)" in line and "diagnose" in line, line
    assert not (tmp_path / "d.json").exists()
    own = tmp_path / "own.toml"
    own.write_text("[sampling]\npoints_budget = 200000\n")
    done = run_cli("diagnose", room10["gt"], "--config", own, "--json", tmp_path / "e.json")
    assert done.returncode == 0, done.stderr[-800:]


def test_t30_b2_depth_odometry_flags_a_slide_along_a_bare_wall(tmp_path: Path) -> None:
    """Hostile trial 30 B2: on the default synthetic room log the depth odometry's first step (no velocity known yet)
    slid 21 cm along a bare wall (the true pose fits 0.839 of the points, the slid one 0.837) and every later frame
    followed it, all "tracking ok". Along the direction the frame barely constrains, a registration that moved
    more than ``gicp_degenerate_shift_m`` from the prediction keeps the prediction's translation and the frame is
    reported degenerate: through the CLI, every step of the first 10 frames within 2 cm of the ground truth's."""
    from driftmap.trajectory import read_tum

    log, out = tmp_path / "log", tmp_path / "store"
    assert run_cli("synth", log).returncode == 0
    built = run_cli("build", log, "--out", out, "--frames", "0:10", "--no-loop-closure", "--threads", "1")
    assert built.returncode == 0, built.stderr[-2000:]
    assert "degenerate" in built.stderr + built.stdout
    per_frame = json.loads((out / "build_summary.json").read_text())["tracking"]["per_frame"]
    assert per_frame[1]["status"] == "degenerate" and "barely constrains" in per_frame[1]["reason"], per_frame[1]
    assert run_cli("export", out, "--trajectory", tmp_path / "est.tum").returncode == 0
    est = read_tum(tmp_path / "est.tum").poses
    gt = read_tum(log / "groundtruth.txt").poses[:10]
    step_error_m = [np.linalg.norm((np.linalg.inv(est[k]) @ est[k + 1])[:3, 3] - (np.linalg.inv(gt[k]) @ gt[k + 1])[:3, 3])
                    for k in range(9)]
    assert max(step_error_m) < 0.02, step_error_m
    # the same build without the bridge (a [build.odometry] setting) slides as the trial saw: the test can fail
    (tmp_path / "off.toml").write_text("[build.odometry]\ngicp_degenerate_shift_m = 1e9\n")
    off = run_cli("build", log, "--out", tmp_path / "off", "--frames", "0:2", "--no-loop-closure", "--threads", "1",
                  "--config", tmp_path / "off.toml")
    assert off.returncode == 0, off.stderr[-2000:]
    assert json.loads((tmp_path / "off" / "build_summary.json").read_text())["tracking"]["per_frame"][1]["status"] == "ok"


def test_t30_w3_a_config_file_holding_nothing_a_command_reads_is_refused(room10: dict[str, Path], tmp_path: Path) -> None:
    """Hostile trial 30 W3: a ``[map]``-only file was taken silently by build, diagnose, decide and merge, a
    ``[build]``-only one by export, while a ``[fleet]``-only one was refused. Every command refuses a file whose
    tables it never reads, naming the tables it holds and the ones the command reads; one table it reads is enough."""
    map_only, build_only = tmp_path / "map.toml", tmp_path / "build.toml"
    map_only.write_text("[map]\nexport_voxel_size_m = 0.25\n")
    build_only.write_text("[build]\npixel_stride = 1\n[depth]\nmax_depth_m = 3.0\n")
    queries = tmp_path / "q.json"
    queries.write_text('{"queries": [{"id": "c", "kind": "clearance", "points_m": [[0, 0, 0]], "radius_m": 0.2}]}')
    store = room10["gt"]
    runs = {
        "build": (map_only, ["build", room10["log"], "--out", tmp_path / "s", "--no-loop-closure"], "[build] / [depth]"),
        "diagnose": (map_only, ["diagnose", store, "--json", tmp_path / "d.json"], "[diagnose] / [volume]"),
        "decide": (map_only, ["decide", store, "--queries", queries, "--json", tmp_path / "q_out.json"],
                   "[volume] / [decide]"),
        "merge": (map_only, ["merge", store, store, "--out", tmp_path / "m"], "[build]"),
        "export": (build_only, ["export", store, "--map", tmp_path / "m.ply"], "[map] / [volume]"),
    }
    for command, (cfg, args, reads) in runs.items():
        line = one_error(run_cli(*args, "--config", cfg))
        held = "[map] table" if cfg == map_only else "[build] / [depth] tables"
        assert f"holds only the {held}, none of which driftmap {command} reads (it reads {reads})" in line, line
        assert str(cfg) in line, line
    assert not (tmp_path / "s").exists() and not (tmp_path / "m").exists() and not (tmp_path / "m.ply").exists()
    # one table the command reads is enough: the other tables are left to the commands that read them
    both = tmp_path / "both.toml"
    both.write_text("[build]\npixel_stride = 1\n[map]\nexport_voxel_size_m = 0.25\n")
    done = run_cli("export", store, "--map", tmp_path / "m.ply", "--config", both)
    assert done.returncode == 0, done.stderr[-800:]
    # diagnose reads [volume] too (its report's volumetric layers, as export builds them; before, the table was
    # silently ignored there)
    volume = tmp_path / "volume.toml"
    volume.write_text("[volume]\nvoxel_size_m = 0.2\n")
    diagnosed = run_cli("diagnose", store, "--json", tmp_path / "d.json", "--report", tmp_path / "r", "--config", volume)
    assert diagnosed.returncode == 0, diagnosed.stderr[-800:]
    assert json.loads((tmp_path / "d.json").read_text())["volume"]["voxel_size_m"] == 0.2


def test_t30_b2_a_depth_store_built_before_the_bridge_resumes_without_it(room10: dict[str, Path], tmp_path: Path) -> None:
    """``--resume`` of a depth store whose recorded odometry settings predate ``gicp_degenerate_shift_m`` (or that
    recorded none) continues as it was built: without the bridge."""
    from driftmap.pipeline.resume import recorded_odometry

    store = tmp_path / "store"
    first = build(room10["log"], store, frames="0:3", loop_closure=False)
    assert first.odometry_config["method"] == "gicp_map" and first.odometry_config["gicp_degenerate_shift_m"] == 0.1
    summary_file = store / "build_summary.json"
    summary = json.loads(summary_file.read_text())
    old = {k: v for k, v in summary["odometry_config"].items() if k != "gicp_degenerate_shift_m"}
    summary_file.write_text(json.dumps({**summary, "odometry_config": old}))
    with FrameStore.open(store) as opened:
        recorded = recorded_odometry(opened)
    assert recorded is not None and recorded.gicp_degenerate_shift_m is None
    assert recorded.gicp_map_voxel_m == old["gicp_map_voxel_m"]
    del summary["odometry_config"]
    summary_file.write_text(json.dumps(summary))
    with FrameStore.open(store) as opened:
        legacy = recorded_odometry(opened)
    assert legacy is not None and legacy.method.value == "gicp_map" and legacy.gicp_degenerate_shift_m is None
    resumed = build(room10["log"], store, frames="0:5", resume=True, loop_closure=False)
    assert resumed.n_frames_new == 2 and resumed.odometry_config["gicp_degenerate_shift_m"] is None
