"""The sixth hostile-input trial (issue 22; about 555 runs, docs/bad-input.md): the broken (B) and weak (W) cases it
found outside the readers (those are in tests/test_hostile_trial6_sources.py), through the path the user took.
B1 a coarse map calling free a sphere 0.1 m from a measured point; B2 ``decide`` on an empty store and a lenient
build that skipped every frame; B4 ``view`` hanging on an unreachable ``DISPLAY``; B5 ``--resume`` mixing two
versions of the source's poses; B7 float frame ids and revisions truncated."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli

from driftmap.errors import DriftmapError, StoreError
from driftmap.map.view import MapView
from driftmap.pipeline.build import build
from driftmap.store.frame_store import FrameStore


_cli, _error = run_cli, one_error


@pytest.fixture(scope="module")
def logs(room10: dict[str, Path]) -> dict[str, Path]:
    """A 10-frame synthetic room log and a store of it placed with the ground truth (conftest.py's ``room10``,
    built once for the trials)."""
    return room10


def _near_queries(store_path: Path, out: Path) -> list[np.ndarray]:
    """Clearance queries of radius 0.2 m whose point lies 0.1 m from a measured map point (MapView.nearest)."""
    with FrameStore.open(store_path) as store:
        view = MapView.from_store(store, 0)
        queries, points = [], []
        for k, p in enumerate(([0.5, 0.5, 1.0], [0.0, 0.0, 0.5], [1.0, -1.0, 1.0], [-1.0, 1.0, 1.2])):
            hit = np.asarray(view.nearest(p).point_world, dtype=np.float64)
            away = np.asarray(p) - hit
            c = hit + 0.1 * away / np.linalg.norm(away)
            points.append(hit)
            queries.append({"id": f"near{k}", "kind": "clearance", "points_m": [c.tolist()], "radius_m": 0.2})
    out.write_text(json.dumps({"queries": queries}))
    return points


def test_t6_b1_a_coarse_map_never_calls_free_a_sphere_holding_a_measured_point(logs: dict, tmp_path: Path) -> None:
    """Clearance was measured to each occupied voxel's mean point: at 0.5 m voxels three of four spheres of radius
    0.2 m around a point 0.1 m from a measured one were free. Now the distance is to the voxel's cube: blocked at
    every voxel size, and a collision sweep through the same point is never clear."""
    hits = _near_queries(logs["gt"], tmp_path / "q.json")
    for voxel in (0.02, 0.5, 1.0):
        cfg = tmp_path / f"v{voxel}.toml"
        cfg.write_text(f"[volume]\nvoxel_size_m = {voxel}\n")
        out = _cli("decide", logs["gt"], "--queries", tmp_path / "q.json", "--json", tmp_path / f"d{voxel}.json",
                   "--config", cfg)
        assert out.returncode == 0, out.stderr[-2000:]
        decisions = json.loads((tmp_path / f"d{voxel}.json").read_text())["decisions"]
        assert [d["decision"] for d in decisions] == ["blocked"] * 4, (voxel, decisions)
        assert all(d["details"]["clearance_m"] <= 0.1 + 1e-9 for d in decisions), voxel
    p = hits[0]
    sweep = {"queries": [{"id": "sweep", "kind": "collision", "path_m": [(p - [0.5, 0, 0]).tolist(), (p + [0.5, 0, 0]).tolist()],
                          "footprint": {"box_m": [0.1, 0.1, 0.1]}, "unknown_is": "free"}]}
    (tmp_path / "s.json").write_text(json.dumps(sweep))
    (tmp_path / "v1.toml").write_text("[volume]\nvoxel_size_m = 1.0\n")
    out = _cli("decide", logs["gt"], "--queries", tmp_path / "s.json", "--json", tmp_path / "s_out.json",
               "--config", tmp_path / "v1.toml")
    assert out.returncode == 0, out.stderr[-2000:]
    (d,) = json.loads((tmp_path / "s_out.json").read_text())["decisions"]
    assert d["decision"] == "blocked", d


def test_t6_b2_w1_a_lenient_build_that_skipped_every_frame_fails_and_decide_refuses_an_empty_store(
        logs: dict, tmp_path: Path) -> None:
    folder = tmp_path / "faces"
    folder.mkdir()
    for k in range(3):  # PLY files with a face element only: no point to read
        (folder / f"{k}.ply").write_text("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int "
                                         "vertex_indices\nend_header\n3 0 1 2\n")
    out = _cli("build", folder, "--out", tmp_path / "st", "--lenient", "--period-s", "0.1", "--no-loop-closure")
    line = _error(out)
    assert "every frame read was skipped (3" in line and "frame 0" in line, line
    assert not (tmp_path / "st").exists()  # the empty store it made is removed
    empty = FrameStore.create(tmp_path / "empty")
    empty.close()
    (tmp_path / "q.json").write_text(json.dumps({"queries": [
        {"id": "c", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": 0.2}]}))
    line = _error(_cli("decide", tmp_path / "empty", "--queries", tmp_path / "q.json", "--json", tmp_path / "o.json"))
    assert "holds no frames" in line and str(tmp_path / "empty") in line, line
    assert not (tmp_path / "o.json").exists()


def test_t6_b4_view_does_not_hang_on_a_display_nobody_answers(logs: dict, tmp_path: Path) -> None:
    """DISPLAY set to a display no X server serves (a stale ssh -X): PNG views and a warning, not a hang."""
    out = _cli("view", logs["gt"], "--out", tmp_path / "views", env={"DISPLAY": ":97"}, timeout=240)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "DISPLAY=:97 is set but no X server answers" in " ".join(out.stderr.split())
    assert list((tmp_path / "views").glob("*.png"))
    line = _error(_cli("view", logs["gt"], "--out", tmp_path / "v2", "--no-headless", env={"DISPLAY": ":97"}))
    assert "no display (DISPLAY=:97 is set but no X server answers there)" in line, line


def test_t6_b5_resume_refuses_poses_that_changed_in_the_source(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """7-Scenes frames 0-4 whose frame 1 has no pose file: the build stops after frame 0; the file comes back but
    frame 0's pose moved by 1 m. --resume --poses-from-source refuses to mix the two versions (naming the frame)."""
    log = tmp_path / "log"
    log.mkdir()
    shutil.copy(sevenscenes_dir / "camera-intrinsics.txt", log)
    for k in range(5):
        for kind in ("depth.png", "pose.txt"):
            shutil.copy(sevenscenes_dir / f"frame-{k:06d}.{kind}", log)
    pose1 = (log / "frame-000001.pose.txt").read_text()
    (log / "frame-000001.pose.txt").unlink()
    out = _cli("build", log, "--out", tmp_path / "st", "--poses-from-source", "--no-loop-closure")
    assert out.returncode == 1 and "frame-000001.pose.txt" in out.stderr, out.stderr[-1500:]
    with FrameStore.open(tmp_path / "st") as store:
        assert list(store.frame_ids) == [0]
    (log / "frame-000001.pose.txt").write_text(pose1)
    pose0 = (log / "frame-000000.pose.txt").read_text()
    T = np.loadtxt(log / "frame-000000.pose.txt")
    T[0, 3] += 1.0
    np.savetxt(log / "frame-000000.pose.txt", T)
    line = _error(_cli("build", log, "--out", tmp_path / "st", "--poses-from-source", "--no-loop-closure", "--resume"))
    assert "--resume: frame 0 is stored with another pose" in line and "1 m apart" in line, line
    (log / "frame-000000.pose.txt").write_text(pose0)  # the file as it was: the resume completes
    out = _cli("build", log, "--out", tmp_path / "st", "--poses-from-source", "--no-loop-closure", "--resume")
    assert out.returncode == 0, out.stderr[-1500:]
    with FrameStore.open(tmp_path / "st") as store:
        assert list(store.frame_ids) == [0, 1, 2, 3, 4]


def test_t6_b7_float_and_bool_ids_and_revisions_are_refused(logs: dict) -> None:
    from driftmap.decisions import decide, decide_revisions
    from driftmap.decisions.errors import QueryError

    queries = {"queries": [{"id": "c", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": 0.2}]}
    with FrameStore.open(logs["gt"]) as store:
        for bad in (2.9, -0.5, True, np.float64(4.7)):
            with pytest.raises(StoreError, match="frame_id must be an integer"):
                store.frame(bad)
            with pytest.raises(StoreError, match="frame_id must be an integer"):
                store.frame_info(bad)
        assert store.frame(np.int64(2)).frame_id == 2
        with pytest.raises(StoreError, match="revision must be an integer"):
            decide(store, queries, revision=0.9)
        with pytest.raises(QueryError, match="revisions is empty"):
            decide_revisions(store, queries, [])
        with pytest.raises(DriftmapError, match="position_m must be finite"):
            MapView.from_store(store, 0).nearest([np.inf, 0, 0])
        with pytest.raises(DriftmapError, match="position_m must be finite"):
            MapView.from_store(store, 0).nearest([1e300, 0, 0])


def test_t6_w3_outputs_inside_each_other_are_refused_before_any_work(logs: dict, tmp_path: Path) -> None:
    (tmp_path / "q.json").write_text(json.dumps({"queries": [
        {"id": "c", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": 0.2}]}))
    line = _error(_cli("decide", logs["gt"], "--queries", tmp_path / "q.json", "--json", tmp_path / "a.json",
                       "--report", tmp_path / "a.json"))
    assert "--json and --report name the same file" in line, line
    line = _error(_cli("diagnose", logs["gt"], "--json", tmp_path / "d.json", "--report", tmp_path / "d.json" / "sub"))
    assert "--report would lie inside" in line and "the file --json writes" in line, line
    line = _error(_cli("decide", logs["gt"], "--queries", tmp_path / "q.json", "--json", tmp_path / "b.json",
                       "--compare", "0,0"))
    assert "with itself" in line, line
    assert not list(tmp_path.glob("*.json.*")) and not (tmp_path / "a.json").exists() and not (tmp_path / "d.json").exists()


def test_t6_w13_a_string_store_version_is_quoted(logs: dict, tmp_path: Path) -> None:
    copy = tmp_path / "st"
    shutil.copytree(logs["gt"], copy)
    manifest = json.loads((copy / "store.json").read_text())
    manifest["version"] = str(manifest["version"])
    (copy / "store.json").write_text(json.dumps(manifest))
    line = _error(_cli("info", copy))
    assert f"store format version '{manifest['version']}' is not supported" in line, line


def test_t6_w7_w8_duplicate_keys_and_a_truncation_below_a_voxel_are_refused(logs: dict, tmp_path: Path) -> None:
    (tmp_path / "dup.json").write_text('{"volume": {"voxel_size_m": 0.05, "voxel_size_m": 0.2}}')
    line = _error(_cli("export", logs["gt"], "--mesh", tmp_path / "m.ply", "--config", tmp_path / "dup.json"))
    assert "dup.json" in line and "'voxel_size_m' appears twice" in line, line
    query = '"id": "c", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": 0.2, "radius_m": 5'
    (tmp_path / "q.json").write_text('{"queries": [{' + query + '}]}')
    (tmp_path / "q.yaml").write_text("queries:\n  - id: c\n    kind: clearance\n    points_m: [[0, 0, 1]]\n"
                                     "    radius_m: 0.2\n    radius_m: 5\n")
    for q in ("q.json", "q.yaml"):
        line = _error(_cli("decide", logs["gt"], "--queries", tmp_path / q, "--json", tmp_path / "o.json"))
        assert q in line and "'radius_m' appears twice" in line, line
    (tmp_path / "trunc.toml").write_text("[volume]\ntruncation_m = 0.001\nvoxel_size_m = 0.05\n")
    line = _error(_cli("export", logs["gt"], "--mesh", tmp_path / "m.ply", "--config", tmp_path / "trunc.toml"))
    assert "volume.truncation_m (0.001 m) must be at least one voxel" in line, line
    assert not (tmp_path / "m.ply").exists()


def test_t6_w11_w12_w14_list_lines_perturb_vectors_and_correct_sources(logs: dict, tmp_path: Path) -> None:
    log, gt = logs["log"], logs["log"] / "groundtruth.txt"
    for text, expected in ((f"{log} --poses {gt} --poses-from-source", "--poses and --poses-from-source"),
                           (f"{log} --frames 0:3 --frames 0:4", "--frames is given twice")):
        (tmp_path / "list.txt").write_text(text + "\n")
        line = _error(_cli("batch", tmp_path / "list.txt", "--out", tmp_path / "fleet"))
        assert f"{tmp_path / 'list.txt'}:1" in line and expected in line, line
    line = _error(_cli("perturb", gt, tmp_path / "p.txt", "--step-frame", 3, "--step-m", "1e12,0,0"))
    assert "--step-m: a step of 1e+12 m" in line, line
    line = _error(_cli("perturb", gt, tmp_path / "p.txt", "--drift-percent-per-m", 1, "--drift-direction", "1e-300,0,0"))
    assert line.startswith("error: --drift-direction: a drift needs a non-zero direction"), line
    assert not (tmp_path / "p.txt").exists()
    copy = tmp_path / "st"
    shutil.copytree(logs["gt"], copy)
    line = _error(_cli("correct", copy, "--poses", gt, "--source", "rollback"))
    assert "'rollback' is not one of" in line, line
    with FrameStore.open(copy) as store:
        assert store.head == 0


def test_t6_w15_decide_against_a_store_missing_frames_warns(logs: dict, tmp_path: Path) -> None:
    build(logs["log"], tmp_path / "half", poses_file=logs["log"] / "groundtruth.txt", loop_closure=False, frames="0:5")
    (tmp_path / "q.json").write_text(json.dumps({"queries": [
        {"id": "c", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": 0.2}]}))
    out = _cli("decide", logs["gt"], "--queries", tmp_path / "q.json", "--json", tmp_path / "o.json",
               "--against", tmp_path / "half")
    assert out.returncode == 0, out.stderr[-2000:]
    err = " ".join(out.stderr.split())
    assert "the stores share 5 frames" in err and "holds 10" in err and "frames are missing" in err, err


def test_t6_w16_a_diagnosis_of_another_store_is_refused(logs: dict, tmp_path: Path) -> None:
    build(logs["log"], tmp_path / "half", poses_file=logs["log"] / "groundtruth.txt", loop_closure=False, frames="0:5")
    assert _cli("diagnose", logs["gt"], "--json", tmp_path / "dg.json").returncode == 0
    (tmp_path / "q.json").write_text(json.dumps({"queries": [
        {"id": "c", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": 0.2}]}))
    line = _error(_cli("decide", tmp_path / "half", "--queries", tmp_path / "q.json", "--json", tmp_path / "o.json",
                       "--diagnosis", tmp_path / "dg.json"))
    assert "dg.json: --diagnosis is not of" in line and "frame 5 is not in the store" in line, line
    out = _cli("decide", logs["gt"], "--queries", tmp_path / "q.json", "--json", tmp_path / "o.json",
               "--diagnosis", tmp_path / "dg.json")
    assert out.returncode == 0, out.stderr[-1500:]


def test_t6_w5_w20_kitti_gaps_warn_frames_are_digits_and_same_log_needs_against(kitti_dir: Path, logs: dict,
                                                                                 tmp_path: Path) -> None:
    kit = tmp_path / "kit"
    (kit / "velodyne").mkdir(parents=True)
    for k in (0, 1, 3):  # scan 2 missing
        shutil.copy(kitti_dir / "velodyne" / f"{k:06d}.bin", kit / "velodyne")
    shutil.copy(kitti_dir / "calib.txt", kit)
    (kit / "times.txt").write_text("".join(line + "\n" for line in (kitti_dir / "times.txt").read_text().split("\n")[:4]))
    out = _cli("build", kit, "--out", tmp_path / "st", "--no-loop-closure")
    assert out.returncode == 0, out.stderr[-2000:]
    err = " ".join(out.stderr.split())
    assert "velodyne/ has no scan 000002.bin (1 missing" in err, err
    with FrameStore.open(tmp_path / "st") as store:
        assert list(store.frame_ids) == [0, 1, 3]
    line = _error(_cli("build", logs["log"], "--out", tmp_path / "st2", "--frames", "1_0:12"))
    assert "--frames '1_0:12'" in line and "digits only" in line, line
    (tmp_path / "q.json").write_text(json.dumps({"queries": [
        {"id": "c", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": 0.2}]}))
    line = _error(_cli("decide", logs["gt"], "--queries", tmp_path / "q.json", "--json", tmp_path / "o.json", "--same-log"))
    assert "--same-log needs --against" in line, line


def test_t6_w18_correct_with_a_redwood_log_naming_one_frame_twice_names_the_file_and_lines(
        icl_dir: Path, tmp_path: Path) -> None:
    build(icl_dir, tmp_path / "st", poses_from_source=True, loop_closure=False)
    lines = (icl_dir / "trajectory.log").read_text().splitlines()
    lines[5] = "0 0 1"  # block 2's header names frame 0 again
    (tmp_path / "dup.log").write_text("\n".join(lines) + "\n")
    line = _error(_cli("correct", tmp_path / "st", "--poses", tmp_path / "dup.log", "--format", "redwood"))
    assert f"{tmp_path / 'dup.log'}:6: frame id 0 is named by two pose blocks, at lines 1 and 6" in line, line
    with FrameStore.open(tmp_path / "st") as store:
        assert store.head == 0


def test_t6_w4_sevenscenes_skew_and_an_implausible_field_of_view_warn(sevenscenes_dir: Path, tmp_path: Path) -> None:
    K = np.loadtxt(sevenscenes_dir / "camera-intrinsics.txt")
    for name, change, expected in (("skew", (0, 1, 5.0), "skew 5 in the camera matrix is ignored"),
                                   ("fov", (0, 0, 5.85), "fx=5.85 px gives a 178 deg horizontal field of view")):
        log = tmp_path / name
        log.mkdir()
        for kind in ("depth.png", "pose.txt"):
            shutil.copy(sevenscenes_dir / f"frame-000000.{kind}", log)
        bad = K.copy()
        bad[change[0], change[1]] = change[2]
        np.savetxt(log / "camera-intrinsics.txt", bad)
        out = _cli("build", log, "--out", tmp_path / f"st_{name}", "--poses-from-source", "--no-loop-closure")
        err = " ".join(out.stderr.split())
        assert expected in err and "camera-intrinsics.txt" in err, err[-2000:]


def test_t6_w19_a_4x4_file_missing_a_row_in_its_first_block_names_that_block(tmp_path: Path) -> None:
    from driftmap.errors import SourceError
    from driftmap.trajectory import read_matrix4x4

    rot = "1,0,0,{x},\n0,1,0,0,\n0,0,1,0,\n"
    blocks = [rot.format(x=k) + f"0,0,0,{1630577759.0 + 0.5 * k},\n" for k in range(6)]
    blocks[0] = rot.format(x=0)  # the first block lost its 0 0 0 row
    (tmp_path / "p.csv").write_text("".join(blocks))
    with pytest.raises(SourceError, match=r"p\.csv:1: 23 matrix rows is not a multiple of 4; the block starting on "
                                          r"line 1 has no 0 0 0 last row .*line 4.*line 7"):
        read_matrix4x4(tmp_path / "p.csv")
    blocks[0] = rot.format(x=0)[: rot.format(x=0).rindex("0,0,1,0")] + "0,0,0,1630577759.0,\n"  # 3 rows, 0 0 0 early
    (tmp_path / "q.csv").write_text("".join(blocks))
    with pytest.raises(SourceError, match=r"q\.csv:1: .*the block starting on line 1 has only 3 row\(s\), its 0 0 0 "
                                          r"row on line 3"):
        read_matrix4x4(tmp_path / "q.csv")


def test_t6_w20_an_empty_log_file_says_it_is_empty(tmp_path: Path) -> None:
    (tmp_path / "empty.mcap").write_bytes(b"")
    line = _error(_cli("build", tmp_path / "empty.mcap", "--out", tmp_path / "st"))
    assert "empty.mcap: cannot tell the format (the file is empty: 0 bytes)" in line, line
    assert not (tmp_path / "st").exists()


def test_t6_w20_view_reference_without_color_revision_is_refused(logs: dict, tmp_path: Path) -> None:
    line = _error(_cli("view", logs["gt"], "--out", tmp_path / "v", "--reference", 0))
    assert "--reference applies to --color revision" in line and "not --color frame" in line, line
    assert not (tmp_path / "v").exists()
