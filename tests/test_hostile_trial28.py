"""Hostile trial 28: its findings, each through the path the user took (docs/bad-input.md, trial 28)."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli, small_sevenscenes_log


def _md5(path: Path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


def test_t28_b1_diagnose_never_writes_over_what_the_store_was_built_from(room10: dict[str, Path],
                                                                        tmp_path: Path) -> None:
    """``diagnose --json LOG/groundtruth.txt --overwrite`` replaced the log's ground truth by the diagnosis, and
    ``--json POSES`` the ``--poses`` file the store was built with (a later ``build --resume`` could not read it):
    refused as ``decide`` and ``export`` refuse them, --overwrite or not, nothing written."""
    gt = room10["log"] / "groundtruth.txt"
    before = _md5(gt)
    for out in (gt, room10["log"] / "new.json"):
        line = one_error(run_cli("diagnose", room10["gt"], "--json", out, "--overwrite"))
        assert line.startswith(f"error: --json {out}: would replace"), line
    assert _md5(gt) == before and not (room10["log"] / "new.json").exists()
    line = one_error(run_cli("diagnose", room10["gt"], "--json", tmp_path / "d.json", "--report", room10["log"] / "r"))
    assert "--report" in line and "would replace" in line, line
    assert not (room10["log"] / "r").exists()


def test_t28_b2_export_never_writes_over_its_config(room10: dict[str, Path], tmp_path: Path) -> None:
    """``export --config F --trajectory F --overwrite`` read the config, then wrote the trajectory over it: refused
    naming both flags, the config unchanged."""
    cfg = tmp_path / "vol.toml"
    cfg.write_text("[volume]\nvoxel_size_m = 0.1\n")
    line = one_error(run_cli("export", room10["gt"], "--config", cfg, "--trajectory", cfg, "--overwrite"))
    assert "--trajectory and --config name the same file" in line, line
    assert cfg.read_text() == "[volume]\nvoxel_size_m = 0.1\n"


@pytest.mark.parametrize(("intrinsics", "said"), [
    ("585,58500,320,240", "fy=58500 px gives a 0.47 deg vertical field of view over 480 px"),
    ("585,50,320,240", "fy=50 px gives a 156 deg vertical field of view over 480 px"),
    ("585,585,-300,-300", "the principal point cx=-300, cy=-300 px lies on the edge of or outside the 640x480 image"),
    ("585,585,0,0", "the principal point cx=0, cy=0 px lies"),
])
def test_t28_b3_w2_a_vertical_focal_length_or_principal_point_no_camera_has_is_warned_about(
        sevenscenes_dir: Path, tmp_path: Path, intrinsics: str, said: str) -> None:
    """The field-of-view check of trial 27 looked at fx only: fy 100x too large (a 0.47 deg vertical view, every cloud
    a flat sheet) or far too small built "tracking ok" without a word, and so did a principal point outside the image
    (trial 28 W2). Each is warned about; the true intrinsics are not."""
    log = small_sevenscenes_log(sevenscenes_dir, tmp_path / "d7", 2)
    out = run_cli("build", log, "--out", tmp_path / "s", "--intrinsics", intrinsics, "--poses-from-source",
                  "--no-loop-closure")
    err = " ".join(out.stderr.split())
    assert said in err and err.count(said) == 1, err[-2000:]  # once (W10: the source is opened twice)
    if "fy=" in said:
        assert "fx=585 and fy=" in err and "differ" in err, err[-2000:]
    out = run_cli("build", log, "--out", tmp_path / "ok", "--intrinsics", "585,585,320,240", "--poses-from-source",
                  "--no-loop-closure")
    err = " ".join(out.stderr.split())
    assert out.returncode == 0 and "field of view" not in err and "principal point" not in err and "differ" not in err


def test_t28_b4_a_pose_graph_key_beyond_2_63_is_refused_when_added() -> None:
    """``PoseGraph.add_node(2**64, ...)`` was taken and ``optimize()`` raised GTSAM's raw ``TypeError``: refused with
    a PoseGraphError as the g2o reader refuses such ids; the largest key GTSAM takes still optimises."""
    from driftmap.errors import PoseGraphError
    from driftmap.posegraph.graph import PoseGraph

    graph = PoseGraph()
    for bad in (2**64, 2**63, -1):
        with pytest.raises(PoseGraphError, match=r"add_node: node keys must be integers 0 \.\. 2\*\*63 - 1"):
            graph.add_node(bad, np.eye(4))
    T = np.eye(4)
    T[0, 3] = 1.0
    graph.add_node(2**63 - 2, np.eye(4))
    graph.add_node(2**63 - 1, T)
    graph.add_odometry(2**63 - 2, 2**63 - 1, T, np.eye(6))
    result = graph.optimize()
    assert np.allclose(result.poses[2**63 - 1], T, atol=1e-9)


def test_t28_w1_w5_w7_near_duplicate_scales_a_trajectory_named_for_another_format_and_a_two_frame_demo(
        room10: dict[str, Path], tmp_path: Path) -> None:
    """W1 ``voxel_sizes_m = [0.1, 0.10000000001]`` still counted one scale twice: sizes within 1e-6 m are refused as
    one. W5 ``export --trajectory X.kitti`` wrote TUM without a word: refused naming the format, nothing written (with
    ``--format kitti`` written). W7 ``demo --frames 2`` built and then failed on the ATE: the option's minimum is 3."""
    cfg = tmp_path / "near.toml"
    cfg.write_text("[diagnose.double_wall]\nvoxel_sizes_m = [0.1, 0.10000000001]\n")
    line = one_error(run_cli("diagnose", room10["gt"], "--json", tmp_path / "d.json", "--config", cfg))
    assert "each voxel size once" in line and "sizes within 1e-06 m are one" in line, line
    line = one_error(run_cli("export", room10["gt"], "--trajectory", tmp_path / "t.kitti"))
    assert "the name says kitti, but the trajectory is written as tum (--format tum); pass --format kitti" in line
    assert not (tmp_path / "t.kitti").exists()
    assert run_cli("export", room10["gt"], "--trajectory", tmp_path / "t.kitti", "--format", "kitti").returncode == 0
    assert len((tmp_path / "t.kitti").read_text().split("\n")[0].split()) == 12
    out = run_cli("demo", "--frames", 2, "--out", tmp_path / "demo")
    assert out.returncode == 2 and "--frames" in out.stderr and not (tmp_path / "demo").exists(), out.stderr[-1000:]


def test_t28_w3_decide_against_a_store_of_another_sensor_is_refused(tmp_path: Path) -> None:
    """``decide --against`` the LiDAR store of the log a depth-camera store was built from suggested ``--same-log``,
    which then read 35 of 60 decisions flipped "because frames moved" 1-4 m, no pose having changed: refused naming
    both sensors, with --same-log or not."""
    import json

    assert run_cli("synth", tmp_path / "log", "--frames", 4, "--seed", 4, "--lidar").returncode == 0
    for sensor in ("depth", "lidar"):
        out = run_cli("build", tmp_path / "log", "--out", tmp_path / sensor, "--sensor", sensor,
                      "--poses-from-source", "--no-loop-closure", "--threads", 1)
        assert out.returncode == 0, out.stderr[-2000:]
    q = tmp_path / "q.json"
    q.write_text(json.dumps({"queries": [{"id": "c", "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]],
                                          "radius_m": 0.1}]}))
    for extra in ((), ("--same-log",)):
        line = one_error(run_cli("decide", tmp_path / "depth", "--queries", q, "--json", tmp_path / "d.json",
                                 "--against", tmp_path / "lidar", *extra))
        assert "the stores hold different sensors (depth_camera in" in line and "lidar in" in line, line


@pytest.mark.parametrize(("args", "flag", "needs"), [
    (("--stop-frames", 5), "--stop-frames", "give --stops K with it"),
    (("--turn-deg-per-frame", 45), "--turn-deg-per-frame", "give --turns K or --turn-at FRACTION with it"),
    (("--turn-frames", 8), "--turn-frames", "give --turns K or --turn-at FRACTION with it"),
])
def test_t28_w8_synth_options_that_would_do_nothing_are_refused(tmp_path: Path, args: tuple, flag: str,
                                                                needs: str) -> None:
    """``synth --stop-frames 5`` without ``--stops`` (and a turn rate or length without a turn) wrote a log without
    a stop or a turn, exit 0: refused naming the option to add, nothing written."""
    out = run_cli("synth", tmp_path / "log", "--frames", 4, *args)
    err = " ".join(out.stderr.split())
    assert out.returncode == 2 and flag in err and needs in err, err[-1000:]
    assert not (tmp_path / "log").exists()


def test_t28_w6_a_batch_whose_out_holds_its_input_says_so(room10: dict[str, Path], tmp_path: Path) -> None:
    """``batch LOG --out PARENT_OF_LOG`` said "no log among the inputs" of a valid log: inputs inside --out were
    dropped as an earlier batch's folder before --out was checked. It names the input inside --out (before Ray is
    started); the contents of an earlier batch's folder matched by a glob are still skipped."""
    parent = tmp_path / "p"
    shutil.copytree(room10["log"], parent / "room")
    line = one_error(run_cli("batch", parent / "room", "--out", parent))
    assert f"the input {parent / 'room'} lies inside --out {parent}, which is no earlier batch's folder" in line, line
    assert not (parent / "fleet.json").exists()


def test_t29_b2_a_ball_query_too_large_to_square_is_refused(room10: dict[str, Path]) -> None:
    """Hostile trial 29 B2 / W4: ``MapView.query_radius`` with a radius of 1e155 m raised a raw ``OverflowError``
    (squaring it), and took a 1e200 m centre that ``nearest`` refuses: both are ConfigErrors; an infinite radius still
    takes every point."""
    from driftmap.errors import ConfigError
    from driftmap.map.view import MapView
    from driftmap.store.frame_store import FrameStore

    with FrameStore.open(room10["gt"]) as store:
        view = MapView.from_store(store, store.head)
        for center, radius in (([0.0, 0.0, 1.0], 1e155), ([1e200, 0.0, 0.0], 1.0)):
            with pytest.raises(ConfigError, match=r"query_radius: center_m and radius_m must lie within \+-1e\+150 m"):
                view.query_radius(center, radius)
        assert len(view.query_radius([0.0, 0.0, 1.0], float("inf")).points_world) == len(view.points_world)


def test_t28_w4_a_steady_turn_is_no_jump() -> None:
    """``diagnose --points-per-frame 100000000`` named a 64 cm "pose error" between frames 12 and 14 of a synthetic
    room built every other frame: turning 40 deg per step, its world-frame steps differed from their neighbours' by
    60-97 cm, every one read as a jump, and a registration that slid on one as its measure. The steps are compared in
    the frame of the frame they leave: a steady turn makes none, a 10 cm pose error still makes one of 10 cm."""
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from driftmap.diagnostics.jumps import find_jumps
    from driftmap.diagnostics.revisit_config import RevisitCheckConfig

    n, poses = 20, []
    for k in range(n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", 40 * k, degrees=True).as_matrix()
        T[:3, 3] = [1.2 * np.cos(np.radians(40 * k)), 1.2 * np.sin(np.radians(40 * k)), 0.0]
        poses.append(T)
    poses = np.array(poses)
    rows = np.arange(n)
    cfg = RevisitCheckConfig()
    assert find_jumps(SimpleNamespace(poses=poses, frame_ids=rows), rows, cfg) == []
    moved = poses.copy()
    moved[10:, :3, 3] += [0.0, 0.0, 0.1]  # a 10 cm error from frame 10 on
    jumps = find_jumps(SimpleNamespace(poses=moved, frame_ids=rows), rows, cfg)
    assert [(j.before_frame_id, j.frame_id) for _, j in jumps] == [(9, 10)], jumps
    assert abs(jumps[0][1].excess_m - 0.1) < 1e-6 and jumps[0][1].excess_deg < 1e-6


def test_t28_w4_the_revisit_cell_counts_the_group_its_verdict_rests_on() -> None:
    """The diagnose table read "NOT FIT (3 of 5 revisiting frames fit the earlier map; 3 needed)": it counted the
    pairs and the whole-map probes at once, while the verdict rests on one group (2 of 3 pairs fit)."""
    from driftmap.diagnostics.revisits import MAP, STRETCH, RevisitCheck, RevisitCheckConfig, RevisitProbe

    def probe(k: int, counted: bool, kind: str) -> RevisitProbe:
        return RevisitProbe(100 + k, 0.8, 0.6, 0.02, 0.3, 0.01, 0.2, counted, k, k, 5.0, kind)

    probes = [probe(0, True, STRETCH), probe(1, True, STRETCH), probe(2, False, STRETCH),
              probe(3, True, MAP), probe(4, False, MAP)]
    check = RevisitCheck(RevisitCheckConfig(), probes, 5, ())
    assert check.unfit and not check.judged and len(check.counted) == 3
    group = check.deciding_group()
    assert (sum(p.counted for p in group), len(group)) == (2, 3)
    assert check.reason().startswith("only 2 of 3 revisiting frames fit"), check.reason()
