"""Hostile trial 15's findings, each through the path the user took (docs/bad-input.md, trial 15)."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
from cli_run import run_cli
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.trajectory import read_trajectory, write_tum


def _ok(out) -> None:  # noqa: ANN001 - a CompletedProcess
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])


def test_t15_b1_a_room_placed_with_its_ground_truth_is_judged_consistent(tmp_path: Path) -> None:
    """B1: the 30-frame synthetic room placed with its exact ground truth read "cannot judge: revisiting frames
    disagree by 51 cm" -- its first step was screened as a jump and frame 1 registered onto frame 0 alone slid 51 cm
    along a wall (a local refinement from the poses as placed; the fit was weakly constrained). A local refinement that
    carries the probe beyond its first gate is no hypothesis any more: the check reads millimetres."""
    log = tmp_path / "room"
    _ok(run_cli("synth", log, "--door-open", "--seed", 5, "--frames", 30))
    _ok(run_cli("build", log, "--poses", log / "groundtruth.txt", "--no-loop-closure", "--out", tmp_path / "st"))
    out = run_cli("diagnose", tmp_path / "st", "--json", tmp_path / "d.json")
    assert out.returncode in (0, 3), out.stderr[-2000:]
    check = json.loads((tmp_path / "d.json").read_text())["revisit_check"]
    assert check["judged"] and not check["beyond_detector"], check
    assert check["disagreement_m"] < 0.02, check["disagreement_m"]
    for jump in check["jumps"]:
        assert jump["correction_m"] is None or jump["correction_m"] < 0.02, jump


def test_t15_w9_correct_reads_an_euroc_pose_file(room10: dict, tmp_path: Path) -> None:
    """W9: ``correct --poses FILE.csv`` of an EuRoC file said its stamps were not seconds; ``--format euroc`` reads
    it (stamps in ns, matched by stamp), the imported poses are the file's."""
    store = tmp_path / "gt"
    shutil.copytree(room10["gt"], store)
    _ok(run_cli("export", store, "--trajectory", tmp_path / "gt.txt"))
    traj = read_trajectory(tmp_path / "gt.txt", "tum")
    lines = ["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"]
    shifted = traj.poses.copy()
    shifted[:, 0, 3] += 0.5  # a world offset the import must carry
    for stamp, P in zip(traj.stamps_ns, shifted, strict=True):
        x, y, z, w = Rotation.from_matrix(P[:3, :3]).as_quat()
        lines.append(",".join([str(int(stamp))] + [repr(float(v)) for v in (*P[:3, 3], w, x, y, z)]))
    (tmp_path / "poses.csv").write_text("\n".join(lines) + "\n")
    _ok(run_cli("correct", store, "--poses", tmp_path / "poses.csv", "--format", "euroc"))
    _ok(run_cli("export", store, "--trajectory", tmp_path / "after.txt"))
    after = read_trajectory(tmp_path / "after.txt", "tum")
    assert np.abs(after.poses[:, :3, 3] - shifted[:, :3, 3]).max() < 1e-6


def test_t15_w12_one_room_with_a_door_closed_is_merged_after_its_half_turned_loops_are_refused(tmp_path: Path) -> None:
    """W12: two LiDAR sessions of the room, the door open in the first and closed in the second, the second moved 2 m
    and turned 150 deg. Six loops agree on a half-turned placement (refused: ~14 % of the points in the other's free
    space), five on the true one (3.8 %: the closed door). A second try had to pass half the bound and the room was
    reported "another place?"; it passes the same bound now and session 1 lands on the ground truth."""
    _ok(run_cli("synth", tmp_path / "Ld", "--lidar", "--door-open", "--frames", 40, "--seed", 8))
    _ok(run_cli("synth", tmp_path / "Lp", "--lidar", "--frames", 60, "--seed", 11))
    _ok(run_cli("build", tmp_path / "Ld", "--sensor", "lidar", "--poses", tmp_path / "Ld" / "groundtruth.txt",
                "--frames", "0:16", "--no-loop-closure", "--out", tmp_path / "A"))
    _ok(run_cli("build", tmp_path / "Lp", "--sensor", "lidar", "--poses", tmp_path / "Lp" / "groundtruth.txt",
                "--frames", "12:45", "--no-loop-closure", "--out", tmp_path / "B"))
    _ok(run_cli("export", tmp_path / "B", "--trajectory", tmp_path / "b.txt"))  # as the trial: moved by `correct`
    gt = read_trajectory(tmp_path / "b.txt", "tum")
    G = geometry.make_transform(Rotation.from_euler("z", 150, degrees=True), [2.0, 1.0, 0.0])
    write_tum(tmp_path / "b_moved.txt", replace(gt, poses=G @ gt.poses))
    _ok(run_cli("correct", tmp_path / "B", "--poses", tmp_path / "b_moved.txt"))
    _ok(run_cli("merge", tmp_path / "A", tmp_path / "B", "--out", tmp_path / "AB"))
    summary = json.loads((tmp_path / "AB" / "merge_summary.json").read_text())
    pair = summary["pairs"][0]
    assert pair["connected"] and pair["free_space_conflict"] < 0.06, pair
    from driftmap.pipeline.merge import SESSION_ID_STRIDE
    from driftmap.store.frame_store import FrameStore

    with FrameStore.open(tmp_path / "AB") as store:
        ids, poses, stamps = store.frame_ids, store.poses(), store.ledger.stamps_ns
    b = ids >= SESSION_ID_STRIDE
    truth = gt.poses[np.searchsorted(gt.stamps_ns, stamps[b])]
    assert np.linalg.norm(poses[b, :3, 3] - truth[:, :3, 3], axis=1).max() < 0.05
