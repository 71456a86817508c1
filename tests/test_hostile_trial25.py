"""Hostile trial 25: its findings, each through the path the user took (docs/bad-input.md, trial 25).

B1 (g2o information matrices that are not positive definite, read by GTSAM as other matrices) is tested in
``tests/test_posegraph.py``. B2: a LiDAR scan whose points are all one point was tracked "ok" and stored 1.4 m /
16 deg off: one distinct point fits any surface."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from cli_run import one_error, run_cli

from driftmap.store.frame_store import FrameStore


def _ok(out):  # noqa: ANN001, ANN202 - a CompletedProcess
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])
    return out


def _xyz_pcd(path: Path, points: np.ndarray) -> None:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    assert o3d.io.write_point_cloud(str(path), cloud)


def test_t25_b2_a_scan_of_one_repeated_point_is_flagged_and_its_pose_predicted(balm_dir: Path, tmp_path: Path) -> None:
    """BALM scans 30-37 as a PCD folder, scan 4 replaced by 87,170 copies of one point: the scan is flagged (lost:
    too few points after the voxel grid, pose predicted), its pose lies between its neighbours' instead of 1.4 m below
    them, and the other scans are tracked."""
    import open3d as o3d

    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(8):
        pts = np.asarray(o3d.io.read_point_cloud(str(balm_dir / f"full{30 + k}.pcd")).points)
        if k == 4:
            pts = np.tile([3.0, 1.0, 0.5], (87_170, 1))
        _xyz_pcd(folder / f"{k:06d}.pcd", pts)
    store = tmp_path / "s"
    out = _ok(run_cli("build", folder, "--out", store, "--period-s", "0.5", "--threads", "1", "--no-loop-closure"))
    assert "frame 4" in out.stderr and "pose predicted" in out.stderr, out.stderr[-3000:]
    tracking = json.loads((store / "build_summary.json").read_text())["tracking"]
    assert [f["frame_id"] for f in tracking["flagged"]] == [4], tracking["flagged"]
    assert tracking["by_status"] == {"first": 1, "ok": 6, "lost": 1}, tracking["by_status"]
    assert "87170 measured" in tracking["flagged"][0]["reason"], tracking["flagged"][0]
    with FrameStore.open(store) as s:
        poses = s.poses()
    t = poses[:, :3, 3]
    assert np.linalg.norm(t[4] - 0.5 * (t[3] + t[5])) < 0.15, t[3:6]


def test_t25_w6_a_log_of_empty_depth_images_builds_no_store(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """Six 7-Scenes frames whose depth images are all zeros (or all 65535): build exits 1 saying no frame holds a
    point, leaves no store, and prints no raw "warning: Empty point cloud" from small_gicp. One empty image among good
    ones is still flagged and bridged, and the store builds."""
    from PIL import Image

    for fill, name in ((0, "zeros"), (65535, "saturated")):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "camera-intrinsics.txt").symlink_to(sevenscenes_dir / "camera-intrinsics.txt")
        for i in range(6):
            Image.fromarray(np.full((480, 640), fill, np.uint16)).save(folder / f"frame-{i:06d}.depth.png")
        out = run_cli("build", folder, "--out", tmp_path / f"s-{name}", "--threads", "1")
        line = one_error(out)
        assert "none of the 6 frames read holds a point" in line and "no store was kept" in line, line
        assert "Empty point cloud" not in out.stdout + out.stderr
        assert not (tmp_path / f"s-{name}").exists()
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "camera-intrinsics.txt").symlink_to(sevenscenes_dir / "camera-intrinsics.txt")
    for i in range(6):
        src = sevenscenes_dir / f"frame-{i:06d}.depth.png"
        if i == 3:
            Image.fromarray(np.zeros((480, 640), np.uint16)).save(mixed / src.name)
        else:
            (mixed / src.name).symlink_to(src)
    _ok(run_cli("build", mixed, "--out", tmp_path / "s-mixed", "--threads", "1", "--no-loop-closure"))
    tracking = json.loads((tmp_path / "s-mixed" / "build_summary.json").read_text())["tracking"]
    assert [f["frame_id"] for f in tracking["flagged"]] == [3], tracking["flagged"]


def test_t25_w6_decide_on_a_map_without_points_says_so(tmp_path: Path) -> None:
    """A store whose frames hold no point (as the API can write): the layers are refused as an empty map, not as
    "a voxel larger than the map"."""
    from driftmap.frame import Frame, PoseEstimate, SensorKind

    store = FrameStore.create(tmp_path / "s")
    for i in range(3):
        store.append(Frame(frame_id=i, stamp_ns=i * 100_000_000, points_sensor=np.zeros((0, 3), np.float32),
                           sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                           pose=PoseEstimate(np.eye(4), revision=0)))
    store.close()
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [{"id": "c", "kind": "clearance", "points_m": [[0, 0, 1]], "radius_m": 0.2}]}))
    config = tmp_path / "c.toml"
    config.write_text("[volume]\nmax_range_m = 10.0\n")  # a LiDAR store made through the API records no range
    line = one_error(run_cli("decide", tmp_path / "s", "--queries", q, "--json", tmp_path / "o.json", "--config", config))
    assert "the map of revision 0 has no point (3 frames, none with a point)" in line, line


def test_t25_b3_w7_the_layers_queries_of_a_navigation_stack_are_bounded_and_checked(room10: dict) -> None:
    """B3: ``VolumeLayers.sweep`` (docs/navigation-stack.md) made every placement of a path or every voxel of a
    footprint whatever their number: a 1e7 m path took 24 GB, a 20 m radius 3.8 GiB, a 1e6 m radius a raw
    ValueError. They are refused before any is made, as ``decide`` refuses a collision path. W7: ``states``,
    ``observers`` and ``clearance_m`` check their points alike (finite real (N, 3): a NaN read as unknown, or as a
    lattice overflow), and a bad ``unknown_is`` is a ConfigError."""
    import pytest

    from driftmap.errors import ConfigError
    from driftmap.volume import VolumeConfig, VolumeLayers

    with FrameStore.open(room10["gt"]) as store:
        layers = VolumeLayers.from_store(store, store.head, config=VolumeConfig(voxel_size_m=0.05))
    ok = layers.sweep(np.array([[0, 0, 1.0], [1.0, 0, 1.0]]), radius_m=0.1)
    for length in (1e5, 1e7):  # 1e5 m: 4 million placements at half-voxel steps
        with pytest.raises(ConfigError, match=r"sweep: path_m .* footprint placements .* more than 1,000,000"):
            layers.sweep(np.array([[0, 0, 1.0], [length, 0, 1.0]]), radius_m=0.1)
    for footprint in ({"radius_m": 20.0}, {"radius_m": 1e6}, {"box_m": (1e5, 1e5, 1e5)}):
        with pytest.raises(ConfigError, match=r"sweep: the footprint .* voxels .* more than 4,000,000"):
            layers.sweep(np.array([[0, 0, 1.0], [1.0, 0, 1.0]]), **footprint)
    with pytest.raises(ConfigError, match=r"voxel tests"):  # each bound alone passes, their product does not
        layers.sweep(np.array([[0, 0, 1.0], [20_000.0, 0, 1.0]]), radius_m=1.0)
    again = layers.sweep(np.array([[0, 0, 1.0], [1.0, 0, 1.0]]), radius_m=0.1)  # the bounds change no answer
    assert (again.outcome, again.distance_m) == (ok.outcome, ok.distance_m)
    for bad in ([[np.nan, 0, 1]], [[np.inf, 0, 1]], np.zeros((2, 2)), np.array([[1 + 1j, 0, 1]]), [["a", 0, 1]]):
        for call in (layers.states, layers.observers, layers.clearance_m):
            with pytest.raises(ConfigError, match=r"points must be finite real \(N, 3\) metres"):
                call(bad)
    with pytest.raises(ConfigError, match=r"unknown_is must be one of .*got 'maybe'"):
        layers.clearance_m([[0, 0, 1.0]], unknown_is="maybe")
    assert layers.states([0, 0, 1.0]).shape == (1,)  # one point is (1, 3)


def test_t25_w5_queries_made_in_code_take_numpy_values() -> None:
    """A navigation stack computes in numpy: numpy scalars and arrays are taken where Python numbers and lists are
    (they were "not a number"), and give the same queries; numpy bools and complex numbers are still refused. A numpy
    thread count is taken as a revision already was."""
    import pytest

    from driftmap.config import check_threads
    from driftmap.decisions import parse_queries
    from driftmap.decisions.errors import QueryError

    plain = {"queries": [{"id": "a", "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]], "radius_m": 0.25},
                         {"id": "b", "kind": "collision", "path_m": [[0, 0, 1.0], [1.0, 0, 1.0]],
                          "footprint": {"box_m": [0.2, 0.2, 0.5]}}]}
    numpy = {"queries": [{"id": np.str_("a"), "kind": "clearance", "points_m": np.array([[0.0, 0.0, 1.0]]),
                          "radius_m": np.float32(0.25)},
                         {"id": "b", "kind": "collision", "path_m": [np.zeros(3) + [0, 0, 1], np.array([1.0, 0, 1])],
                          "footprint": {"box_m": np.array([0.2, 0.2, 0.5])}}]}
    a, b = parse_queries(plain), parse_queries(numpy)
    assert a.raw == b.raw and json.dumps(b.raw)  # the records stay JSON
    for value in (np.bool_(True), np.complex64(1)):
        with pytest.raises(QueryError, match="radius_m must be a number"):
            parse_queries({"queries": [{**plain["queries"][0], "radius_m": value}]})
    assert check_threads(np.int64(2)) == 2 and isinstance(check_threads(np.int32(1)), int)


def test_t25_w2_a_g2o_file_given_as_poses_is_named_a_pose_graph(datasets_dir: Path, room10: dict,
                                                                 tmp_path: Path) -> None:
    g2o = datasets_dir / "pose-graphs" / "parking-garage.g2o"
    for args in (("correct", room10["gt"], "--poses", g2o), ("build", room10["log"], "--out", tmp_path / "s", "--poses", g2o)):
        line = one_error(run_cli(*args))
        assert "a g2o pose graph (VERTEX_/EDGE_ lines), not a trajectory" in line and "PoseGraph.from_g2o" in line, line
    assert not (tmp_path / "s").exists()


def test_t25_w4_a_store_being_written_is_not_called_interrupted(room10: dict, tmp_path: Path) -> None:
    """While a process holds the writer lock of a store with no build summary yet (a build running), `info` and
    `export` say a process is writing it (naming the pid) instead of "its build was interrupted ... --resume" (a
    --resume the lock then refuses); once the lock is gone, the same store reads as interrupted."""
    import os
    import shutil

    from driftmap.store.layout import BUILD_SUMMARY_FILE
    from driftmap.store.lock import acquire_writer_lock, release_writer_lock

    store = tmp_path / "s"
    shutil.copytree(room10["gt"], store)
    (store / BUILD_SUMMARY_FILE).unlink()
    lock = acquire_writer_lock(store)
    try:
        info = _ok(run_cli("info", store))
        text = " ".join(info.stdout.split())
        assert f"process {os.getpid()} is writing this store now" in text and "build interrupted" not in text, text
        out = _ok(run_cli("export", store, "--trajectory", tmp_path / "t.tum"))
        err = " ".join(out.stderr.split())
        assert "is writing this store now" in err and "--resume" not in err, err
    finally:
        release_writer_lock(lock)
    text = " ".join(_ok(run_cli("info", store)).stdout.split())
    assert "build interrupted" in text and "is writing this store now" not in text, text


def test_t25_w9_an_output_that_appears_meanwhile_is_not_replaced(tmp_path: Path) -> None:
    """Under ``no_clobber`` (commands run without --overwrite) a file that appeared at the output's name while it was
    being made is kept and the write fails naming it; without it (--overwrite) it is replaced, as before."""
    import pytest

    from driftmap.errors import OutputWriteError
    from driftmap.files import atomic_write, no_clobber

    path = tmp_path / "map.ply"
    with no_clobber(), pytest.raises(OutputWriteError, match="another process wrote a file of that name"):
        with atomic_write(path, "--map") as tmp:
            tmp.write_text("mine")
            path.write_text("theirs")  # the other export finished first
    assert path.read_text() == "theirs" and sorted(p.name for p in tmp_path.iterdir()) == ["map.ply"]
    with atomic_write(path, "--map") as tmp:
        tmp.write_text("mine")
    assert path.read_text() == "mine"


def test_t25_w9_two_exports_to_one_new_file_do_not_both_succeed(room10: dict, tmp_path: Path) -> None:
    """Two `export --trajectory` to one new name at once (tum and kitti): one writes it, the other exits 1 (the name
    taken meanwhile, or already there when it checked) -- before, both said they wrote it."""
    import subprocess
    import sys

    out = tmp_path / "same.txt"
    cmds = [[sys.executable, "-m", "driftmap.cli", "export", str(room10["gt"]), "--trajectory", str(out), "--format", f]
            for f in ("tum", "kitti")]
    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for c in cmds]
    results = [(p.wait(timeout=300), *p.communicate()) for p in procs]
    codes = sorted(r[0] for r in results)
    assert codes == [0, 1], results
    winner = "tum" if results[0][0] == 0 else "kitti"
    loser_err = " ".join(results[1 if winner == "tum" else 0][2].split())
    assert "another process wrote a file of that name" in loser_err or "exists" in loser_err, loser_err
    first = out.read_text().splitlines()[0]
    assert first.startswith("#") == (winner == "tum"), (winner, first)  # the file is the winner's


def test_t25_b4_decide_refuses_another_stores_layers(room10: dict, tmp_path: Path) -> None:
    """``decide(store, queries, layers=...)`` took any layers of the same revision id: another store's gave its
    frames and plausible, wrong decisions. Layers carry their store's id; another store's are refused (by id, and by
    frames for layers that carry none), and something that is not layers is a ConfigError."""
    import pytest

    from driftmap.decisions import decide, parse_queries
    from driftmap.decisions.errors import QueryError
    from driftmap.errors import ConfigError
    from driftmap.pipeline.build import build
    from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log
    from driftmap.volume import VolumeLayers

    other_log = generate_synthetic_log(tmp_path / "log", SyntheticLogConfig(n_frames=12, seed=8))
    build(other_log, tmp_path / "other", poses_file=other_log / "groundtruth.txt", loop_closure=False)
    q = parse_queries({"queries": [{"id": "a", "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]], "radius_m": 0.2}]})
    with FrameStore.open(room10["gt"]) as store, FrameStore.open(tmp_path / "other") as other:
        own = VolumeLayers.from_store(store, 0)
        assert own.store_uuid == store.uuid
        theirs = VolumeLayers.from_store(other, 0)
        with pytest.raises(QueryError, match="the layers given are of another store"):
            decide(store, q, layers=theirs)
        theirs.store_uuid = None  # layers that name no store: judged by their frames (frames 10, 11 are not here)
        with pytest.raises(QueryError, match=r"integrate frames .* does not hold \(\[10, 11\]\)"):
            decide(store, q, layers=theirs)
        with pytest.raises(ConfigError, match="layers must be the VolumeLayers of the store"):
            decide(store, q, layers="x")
        assert decide(store, q, layers=own).decisions[0].decision == decide(store, q).decisions[0].decision


def test_t25_w8_a_store_and_a_foxglove_view_name_a_way_to_read_frames_that_works(room10: dict, tmp_path: Path) -> None:
    """`convert STORE` advised `export --mcap` and "read that", but that file is a Foxglove view no reader takes. The
    advice now is the Python call that writes the store's frames as a ROS 2 log (followed here: build reads it, the
    same frames), and reading a Foxglove view says what it is."""
    from driftmap.export.mcap import export_mcap

    line = one_error(run_cli("convert", room10["gt"], tmp_path / "z.mcap"))
    assert "driftmap.export.mcap.export_mcap(" in line and "build_source.json" in line, line
    assert "and read that" not in line
    with FrameStore.open(room10["gt"]) as store:
        export_mcap((store.frame(int(i)) for i in store.frame_ids), tmp_path / "frames.mcap")
        n = len(store)
    _ok(run_cli("build", tmp_path / "frames.mcap", "--out", tmp_path / "s", "--no-loop-closure"))
    with FrameStore.open(tmp_path / "s") as rebuilt:
        assert len(rebuilt) == n
    _ok(run_cli("export", room10["gt"], "--mcap", tmp_path / "view.mcap", "--no-volume"))
    line = one_error(run_cli("build", tmp_path / "view.mcap", "--out", tmp_path / "v"))
    assert "it looks like a Foxglove view" in line and "`driftmap export --mcap`" in line, line


def test_t25_b5_decide_refuses_another_stores_diagnosis_as_the_cli_does(room10: dict, tmp_path: Path) -> None:
    """``decide(..., double_walls=FILE_OR_DICT)`` took another store's diagnosis (the CLI refused it): its walls
    dropped the one in reach and the uncertainty with it. The library checks a file, a dict and a Diagnosis alike;
    the store's own diagnosis is taken; a bare list of regions names no store and is taken as given."""
    import pytest

    from driftmap.decisions import decide, parse_queries
    from driftmap.decisions.errors import QueryError
    from driftmap.pipeline.build import build
    from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log

    other_log = generate_synthetic_log(tmp_path / "log", SyntheticLogConfig(n_frames=12, seed=8))
    build(other_log, tmp_path / "other", poses_file=other_log / "groundtruth.txt", loop_closure=False)
    _ok(run_cli("diagnose", tmp_path / "other", "--json", tmp_path / "other.json"))
    _ok(run_cli("diagnose", room10["gt"], "--json", tmp_path / "own.json"))
    q = parse_queries({"queries": [{"id": "a", "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]], "radius_m": 0.2}]})
    foreign = json.loads((tmp_path / "other.json").read_text())
    with FrameStore.open(room10["gt"]) as store:
        for given in (tmp_path / "other.json", str(tmp_path / "other.json"), foreign):
            with pytest.raises(QueryError, match=r"double_walls is not of .*: its frame 10 is not in the store"):
                decide(store, q, double_walls=given)
        same_frames = {**foreign, "frames": json.loads((tmp_path / "own.json").read_text())["frames"]}
        with pytest.raises(QueryError, match=r"it is of another store \(store_uuid "):
            decide(store, q, double_walls=same_frames)  # frames alike (two logs of one length): the id decides
        decide(store, q, double_walls=tmp_path / "own.json")
        decide(store, q, double_walls=foreign["double_wall"]["regions"])  # a list names no store


def test_t25_w10_compare_refuses_decision_sets_of_different_queries_under_one_id(room10: dict) -> None:
    import pytest

    from driftmap.decisions import compare, decide, parse_queries
    from driftmap.decisions.errors import QueryError

    def queries(point: list[float], radius: float):  # noqa: ANN202
        return parse_queries({"queries": [{"id": "a", "kind": "clearance", "points_m": [point], "radius_m": radius}]})

    with FrameStore.open(room10["gt"]) as store:
        a = decide(store, queries([0.0, 0.0, 1.0], 0.2))
        b = decide(store, queries([1.0, 0.1, 1.0], 0.9))
        same = decide(store, queries([0.0, 0.0, 1.0], 0.2))
    with pytest.raises(QueryError, match=r"query 'a' differs between the two decision sets \(points_m, radius_m\)"):
        compare(a, b)
    assert compare(a, same).flipped == []


def test_t25_b6_an_output_that_is_a_fifo_or_a_device_is_refused(room10: dict, tmp_path: Path) -> None:
    """An output path that is a FIFO (or a link to one, as /dev/stdout is to a descriptor) was replaced by a regular
    file without --overwrite: export, diagnose --json and perturb. Refused before any work now, and the atomic
    writer refuses it too (the library path); the FIFO stays."""
    import os
    import stat

    import pytest

    from driftmap.errors import OutputWriteError
    from driftmap.files import atomic_write

    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    link = tmp_path / "link.tum"
    link.symlink_to(fifo)
    tum = tmp_path / "t.tum"
    _ok(run_cli("export", room10["gt"], "--trajectory", tum))
    for args in (("export", room10["gt"], "--trajectory", fifo), ("export", room10["gt"], "--trajectory", link),
                 ("diagnose", room10["gt"], "--json", fifo), ("perturb", tum, fifo, "--drift-percent-per-m", "1")):
        line = one_error(run_cli(*args))
        assert "is a FIFO, not a file" in line, (args, line)
    with pytest.raises(OutputWriteError, match="is a FIFO, not a file"):
        with atomic_write(fifo, "test"):
            pass
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and link.is_symlink()


def test_t25_b7_to_g2o_never_writes_into_a_store(room10: dict, tmp_path: Path) -> None:
    import shutil

    import pytest

    from driftmap.errors import DriftmapError
    from driftmap.posegraph import PoseGraph

    store = tmp_path / "s"
    shutil.copytree(room10["gt"], store)
    segment = next(store.glob("segment-*.mcap"))
    before = segment.read_bytes()
    graph = PoseGraph()
    graph.add_node(0, np.eye(4))
    for target in (segment, store / "store.json", store / "new.g2o"):
        with pytest.raises(DriftmapError, match="store"):
            graph.to_g2o(target)
    assert segment.read_bytes() == before and not (store / "new.g2o").exists()
    graph.to_g2o(tmp_path / "ok.g2o")
    assert PoseGraph.from_g2o(tmp_path / "ok.g2o").nodes.keys() == {0}


def test_t25_w11_diagnose_refuses_a_kitti_file_of_one_row_per_stored_frame(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """A KITTI export of a store of frames 0, 3, ..., 57 given back as --gt: rows 0..19 were matched to the frame
    ids below 20 (ATE 6 cm for the store's own trajectory, and a depth-scale warning); `correct` refused it. diagnose
    refuses it the same way now."""
    store = tmp_path / "s"
    _ok(run_cli("build", sevenscenes_dir, "--frames", "0:60:3", "--out", store, "--threads", "1", "--no-loop-closure"))
    _ok(run_cli("export", store, "--trajectory", tmp_path / "t.kitti", "--format", "kitti"))
    for args in (("diagnose", store, "--gt", tmp_path / "t.kitti", "--gt-format", "kitti", "--json", tmp_path / "d.json"),
                 ("correct", store, "--poses", tmp_path / "t.kitti", "--format", "kitti")):
        line = one_error(run_cli(*args))
        assert "20 rows for the 20 stored frames, but matching by index takes row i as frame_id i" in line, line
    assert not (tmp_path / "d.json").exists()


def test_t25_w3_a_converted_depth_log_keeps_its_invalid_pixel_fraction(sevenscenes_dir: Path, tmp_path: Path) -> None:
    """convert writes a depth camera's valid pixels as an unorganised cloud: read back, the frames reported an
    invalid-pixel fraction of 0.000. The pixels without a point count as invalid now: the same fraction as the
    folder's (the stride difference -- the MCAP's clouds are not read at a 2-pixel stride -- is documented)."""
    _ok(run_cli("convert", sevenscenes_dir, tmp_path / "k.mcap", "--frames", "0:9:3"))
    for source, out in ((tmp_path / "k.mcap", "m"), (sevenscenes_dir, "f")):
        extra = ("--frames", "0:9:3") if out == "f" else ()
        _ok(run_cli("build", source, *extra, "--out", tmp_path / out, "--poses-from-source", "--no-loop-closure"))
    fractions = {}
    for out in ("m", "f"):
        with FrameStore.open(tmp_path / out) as s:
            fractions[out] = [1 - q["n_valid"] / q["n_measurements"] for q in
                              (s.frame_info(int(f))["quality"] for f in s.frame_ids)]
    assert np.allclose(fractions["m"], fractions["f"], atol=0.002) and min(fractions["m"]) > 0.05, fractions
