"""Hostile trial 16's findings, each through the path the user took (docs/bad-input.md, trial 16)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from cli_run import one_error, run_cli

from driftmap.diagnostics import perturb
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import Trajectory, read_tum, write_tum


def _ok(out) -> None:  # noqa: ANN001 - a CompletedProcess
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])


def _with_duplicate_row(src: Path, dst: Path, line: int, dx_m: float) -> int:
    """``src`` with a copy of its ``line``-th line (1-based) inserted before it, moved ``dx_m`` in x: two rows of one
    stamp. Returns the line number of the moved copy."""
    rows = src.read_text().splitlines(keepends=True)
    words = rows[line - 1].split()
    words[1] = repr(float(words[1]) + dx_m)
    rows.insert(line - 1, " ".join(words) + "\n")
    dst.write_text("".join(rows))
    return line


def test_t16_b1_build_refuses_two_pose_rows_of_one_stamp_as_correct_does(room10: dict, tmp_path: Path) -> None:
    """B1: a pose file with two rows of one stamp 0.5 m apart: `build --poses` used whichever came first (the frame
    stored 0.5 m off, "given poses fit: yes") while `correct` refused the same file. Now build refuses it the same way,
    naming both lines, before anything is stored; the same row written twice is still fine."""
    gt = room10["log"] / "groundtruth.txt"
    first_pose_line = next(n for n, text in enumerate(gt.read_text().splitlines(), 1) if text and not text.startswith("#"))
    line = _with_duplicate_row(gt, tmp_path / "dup.txt", first_pose_line + 4, 0.5)
    err = one_error(run_cli("build", room10["log"], "--poses", tmp_path / "dup.txt", "--out", tmp_path / "st",
                            "--no-loop-closure"))
    assert f"the pose rows on lines {line} and {line + 1} share the stamp" in err and "0.5 m apart" in err, err
    assert not (tmp_path / "st").exists()
    store = tmp_path / "gt"
    shutil.copytree(room10["gt"], store)
    err = one_error(run_cli("correct", store, "--poses", tmp_path / "dup.txt"))
    assert f"the pose rows on lines {line} and {line + 1} share the stamp" in err
    _with_duplicate_row(gt, tmp_path / "same.txt", first_pose_line + 4, 0.0)
    _ok(run_cli("build", room10["log"], "--poses", tmp_path / "same.txt", "--out", tmp_path / "st2", "--no-loop-closure"))


def test_t16_b3_resume_on_a_corrected_store_carries_the_correction_on(tmp_path: Path) -> None:
    """B3: `build --resume` on a store whose head is a correction stored the new frames with revision-0 poses only, so
    the head map had a 17-22 cm / 3 deg seam where the resumed frames began. Now a new revision carries the head's
    correction on to them (as `correct` does for frames without a row), with a warning; the corrected frames keep
    their poses."""
    log = tmp_path / "room"
    _ok(run_cli("synth", log, "--frames", 30, "--seed", 11))
    gt = read_tum(log / "groundtruth.txt")
    store = tmp_path / "st"
    _ok(run_cli("build", log, "--poses", log / "groundtruth.txt", "--frames", "0:20", "--no-loop-closure", "--out", store))
    stepped = perturb.translation_step(gt.poses[:30], 15, np.array([0.15, 0.0, 0.0]))
    stepped = perturb.rotation_step(stepped, 15, np.array([0.0, 0.0, 3.0]))
    write_tum(tmp_path / "step.txt", Trajectory(gt.stamps_ns[:30], stepped))
    _ok(run_cli("correct", store, "--poses", tmp_path / "step.txt"))
    out = run_cli("build", log, "--poses", log / "groundtruth.txt", "--frames", "0:30", "--no-loop-closure", "--out",
                  store, "--resume")
    _ok(out)
    assert "carries that correction on to them" in " ".join(out.stderr.split())
    with FrameStore.open(store) as s:
        assert s.head == 2 and len(s) == 30
        head = s.poses(s.head)
        corrected = s.poses(1)
        assert np.array_equal(head[:20], corrected[:20])  # the corrected frames keep their poses
        # the new frames continue the corrected trajectory: the step at frame 15 is carried on, no seam at 20
        moved = np.linalg.norm(head[20:, :3, 3] - stepped[20:30, :3, 3], axis=1)
        assert moved.max() < 0.01, moved
        assert len(s.members(1)) == 20 and len(s.members()) == 30
    # trial 17 B1: revision 1 was made before the resumed frames: it places its own 20 frames, not the new ones at
    # their uncorrected poses beside them (the seam again, through the older revision)
    _ok(run_cli("export", store, "--revision", 1, "--trajectory", tmp_path / "r1.txt"))
    assert len(read_tum(tmp_path / "r1.txt").stamps_ns) == 20


def test_t16_b6_resume_with_loop_closure_after_a_correction_stays_in_one_frame(tmp_path: Path) -> None:
    """B6: a LiDAR store built with loop closure, re-anchored by `correct` (5 m / 30 deg), then resumed with more
    frames: the resume's loop-closure revision propagated its keyframes' poses (optimised from revision 0) to the other
    frames relative to the re-anchored head, throwing two frames 1.6 / 3.3 m off the path, and dropped the correction
    without a word. Now the revision follows revision 0 (no jump) and the warning says the correction is not in it."""
    log = tmp_path / "L"
    _ok(run_cli("synth", log, "--lidar", "--frames", 60, "--seed", 8))
    store = tmp_path / "st"
    _ok(run_cli("build", log, "--sensor", "lidar", "--frames", "0:45", "--out", store))
    _ok(run_cli("export", store, "--trajectory", tmp_path / "lc.txt"))
    built = read_tum(tmp_path / "lc.txt")
    E = np.eye(4)
    E[:3, :3] = np.array([[np.cos(np.pi / 6), -np.sin(np.pi / 6), 0.0], [np.sin(np.pi / 6), np.cos(np.pi / 6), 0.0],
                          [0.0, 0.0, 1.0]])
    E[:3, 3] = (5.0, 0.0, 0.0)
    write_tum(tmp_path / "moved.txt", Trajectory(built.stamps_ns, E @ built.poses))
    _ok(run_cli("correct", store, "--poses", tmp_path / "moved.txt"))
    out = run_cli("build", log, "--sensor", "lidar", "--frames", "0:60", "--out", store, "--resume")
    _ok(out)
    assert "so that correction is not in it" in " ".join(out.stderr.split())
    with FrameStore.open(store) as s:
        head = s.poses(s.head)
        assert len(head) == 60 and s.ledger.revision(s.head).source.value == "loop_closure"
    steps = np.linalg.norm(np.diff(head[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 2.0 * np.median(steps), steps  # no frame thrown off the path
    assert np.abs(head[:45, :3, 3] - built.poses[:, :3, 3]).max() < 0.05  # the odometry's frame, as the first build


def test_t16_b4_ground_truth_maps_are_not_read_as_broken_by_a_sliding_jump_probe(sevenscenes_dir: Path,
                                                                                 tmp_path: Path) -> None:
    """B4: 7-Scenes every 20th frame with the data set's poses read "cannot judge: 89 cm" -- a jump of the trajectory
    (frames 460 -> 480, uneven steps) was probed, neither local hypothesis counted (0.60 of the probe on the target,
    just under the bound) and the free registration slid 89 cm along the cupboards at 0.64; a rosette LiDAR room with
    exact poses read 61 cm the same way. A free registration of a jump probe now has to fit clearly better than the
    jump's own hypotheses (FREE_OVER_LOCAL) to replace them: both read valid, within centimetres."""
    store = tmp_path / "k"
    _ok(run_cli("build", sevenscenes_dir, "--poses-from-source", "--frames", "200:1000:20", "--no-loop-closure",
                "--out", store))
    _ok(run_cli("diagnose", store, "--json", tmp_path / "k.json"))
    d = json.loads((tmp_path / "k.json").read_text())
    assert d["valid"] and d["revisit_check"]["disagreement_m"] < 0.1, d["revisit_check"]["disagreement_m"]
    log = tmp_path / "R1"
    _ok(run_cli("synth", log, "--lidar-pattern", "rosette", "--frames", 30, "--seed", 21))
    _ok(run_cli("build", log, "--sensor", "lidar", "--poses", log / "groundtruth.txt", "--no-loop-closure", "--out",
                tmp_path / "r"))
    _ok(run_cli("diagnose", tmp_path / "r", "--json", tmp_path / "r.json"))
    d = json.loads((tmp_path / "r.json").read_text())
    assert d["valid"] and d["revisit_check"]["disagreement_m"] < 0.03, d["revisit_check"]["disagreement_m"]


def test_t16_w2_batch_shows_cannot_judge_instead_of_an_invalid_diagnosis_figures() -> None:
    """W2: a log whose build lost track read "drift 0.000 %/m", status ok, in the batch table and fleet.html, and the
    fleet was ranked worst first by figures its own diagnosis called unusable (``valid: false`` only in fleet.json).
    The table and the report now say "cannot judge" in place of those figures (ATE, from ground truth, stays), and such
    a log ranks first."""
    from rich.console import Console

    from driftmap.cli.batch_cmds import _summary_table
    from driftmap.fleet.report import _results_table, rank_worst_first

    def row(name: str, valid: bool | None, flagged: float) -> dict:
        return {"name": name, "input": name, "status": "ok", "error": None, "frames": 15, "time_s": 10.0,
                "ate_rmse_m": 1.921, "drift_percent_per_m": 0.0, "fraction_flagged": flagged,
                "smearing_score_m": 0.00012, "valid": valid, "folder": None}

    rows = [row("good", True, 0.02), row("lost", False, 0.0), row("undiagnosed", None, 0.01)]
    failed = {**row("broken", None, 0.0), "status": "failed", "error": "SourceError: no frames"}
    assert [r["name"] for r in rank_worst_first(rows)] == ["lost", "good", "undiagnosed"]
    console = Console(record=True, width=200)
    console.print(_summary_table([failed, *rows], Path("bt")))
    shown = [line.split()[1] for line in console.export_text(clear=False).splitlines()
             if len(line.split()) > 1 and line.split()[1] in ("good", "lost", "undiagnosed", "broken")]
    assert shown == ["lost", "good", "undiagnosed", "broken"]  # fleet.html's order (trial 17 W7), failures last
    lines = {line.split()[1]: " ".join(line.split()) for line in console.export_text().splitlines()
             if len(line.split()) > 1 and line.split()[1] in ("good", "lost", "undiagnosed")}
    assert lines["lost"].count("cannot judge") == 4 and "0.000" not in lines["lost"] and "192.10" in lines["lost"]
    assert "valid" in lines["good"] and "0.000" in lines["good"] and "cannot judge" not in lines["good"]
    html = _results_table(rows)
    lost = html[html.index(">lost<"):].split("</tr>")[0]
    assert lost.count("cannot judge") >= 4 and "0.000" not in lost and "192.10" in lost


def test_t16_w4_diagnose_reads_euroc_ground_truth(room10: dict, tmp_path: Path) -> None:
    """W4: `diagnose --gt FILE.csv` could not read an EuRoC file (`--gt-format euroc` was "not one of tum, kitti,
    redwood, 4x4") although `build --poses` and `correct --format euroc` read it. Now it does: the store placed with its
    ground truth reads an ATE of zero against the same poses as EuRoC."""
    from scipy.spatial.transform import Rotation

    traj = read_tum(room10["log"] / "groundtruth.txt")
    lines = ["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"]
    for stamp, P in zip(traj.stamps_ns, traj.poses, strict=True):
        x, y, z, w = Rotation.from_matrix(P[:3, :3]).as_quat()
        lines.append(",".join([str(int(stamp))] + [repr(float(v)) for v in (*P[:3, 3], w, x, y, z)]))
    (tmp_path / "gt.csv").write_text("\n".join(lines) + "\n")
    _ok(run_cli("diagnose", room10["gt"], "--json", tmp_path / "d.json", "--gt", tmp_path / "gt.csv", "--gt-format",
                "euroc"))
    ate = json.loads((tmp_path / "d.json").read_text())["trajectory"]["ate_rmse_m"]
    assert ate < 1e-6, ate
    # trial 17 W5: the same file without its format (read as TUM) named the stamps' unit, not the format it is
    for args in (("diagnose", room10["gt"], "--json", tmp_path / "e.json", "--gt", tmp_path / "gt.csv"),
                 ("correct", room10["gt"], "--poses", tmp_path / "gt.csv")):
        line = one_error(run_cli(*args))
        assert "looks like a euroc trajectory" in line and "give its format ('euroc')" in line, line


def test_t16_w9_rollback_counts_the_frames_it_moves(room10: dict, tmp_path: Path) -> None:
    """W9: `rollback --to 0` after a correction that moved half the frames said "(10 frames changed)" while
    `revisions` listed 5 for the same revision. It now counts as `revisions` does: the frames whose pose differs."""
    store = tmp_path / "gt"
    shutil.copytree(room10["gt"], store)
    gt = read_tum(room10["log"] / "groundtruth.txt")
    stepped = perturb.translation_step(gt.poses, 5, np.array([0.1, 0.0, 0.0]))
    write_tum(tmp_path / "step.txt", Trajectory(gt.stamps_ns, stepped))
    _ok(run_cli("correct", store, "--poses", tmp_path / "step.txt"))
    out = run_cli("rollback", store, "--to", 0)
    _ok(out)
    assert "poses of revision 0 restored (5 frames changed)" in " ".join(out.stdout.split()), out.stdout


def test_t16_w13_diagnose_gt_on_shared_stamps_names_its_own_way_out(tmp_path: Path) -> None:
    """W13: `diagnose --gt` on a store whose frames share stamps (sessions of a merged store) was refused rightly, but
    the error pointed to `driftmap correct --match index`, an option diagnose does not have. It now says what diagnose
    can do; `correct` keeps its own hint."""
    from driftmap.frame import Frame, PoseEstimate, SensorKind

    store = tmp_path / "shared"
    rng = np.random.default_rng(0)
    with FrameStore.create(store) as s:
        for fid, stamp in ((0, 0), (1, 100_000_000), (1_000_000_000, 0), (1_000_000_001, 100_000_000)):
            s.append(Frame(frame_id=fid, stamp_ns=stamp, sensor_name="lidar", sensor_kind=SensorKind.LIDAR,
                           points_sensor=rng.normal(size=(500, 3)).astype(np.float32), pose=PoseEstimate(np.eye(4))))
    write_tum(tmp_path / "gt.txt", Trajectory(np.array([0, 100_000_000]), np.stack([np.eye(4)] * 2)))
    err = one_error(run_cli("diagnose", store, "--json", tmp_path / "d.json", "--gt", tmp_path / "gt.txt"))
    assert "cannot match rows to frames by stamp" in err and "diagnose each session's own store" in err, err
    assert "--match index" not in err and not (tmp_path / "d.json").exists()
    err = one_error(run_cli("correct", store, "--poses", tmp_path / "gt.txt"))
    assert "`driftmap correct --match index`" in err, err


def test_t16_w8_decide_on_a_lidar_store_built_with_given_poses(tmp_path: Path) -> None:
    """W8: every query on a LiDAR store built with `--poses` was refused ("a LiDAR store without a max range for its
    rays ... set volume.max_range_m"). Its layers now take the range our odometry's defaults take for its frames, and
    say so; the decisions are made, and a set range still wins."""
    log = tmp_path / "L"
    _ok(run_cli("synth", log, "--lidar", "--frames", 10, "--seed", 4))
    store = tmp_path / "st"
    _ok(run_cli("build", log, "--sensor", "lidar", "--poses", log / "groundtruth.txt", "--no-loop-closure",
                "--out", store))
    origin = read_tum(log / "groundtruth.txt").poses[0][:3, 3]
    queries = tmp_path / "q.json"
    queries.write_text(json.dumps({"queries": [
        {"id": "here", "kind": "clearance", "points_m": [origin.tolist()], "radius_m": 0.1},
        {"id": "around", "kind": "explore", "min_m": (origin - 0.5).tolist(), "max_m": (origin + 0.5).tolist(),
         "max_unknown_fraction": 0.5}]}))
    out = run_cli("decide", store, "--queries", queries, "--json", tmp_path / "d.json")
    _ok(out)
    assert "volume.max_range_m" in " ".join(out.stderr.split()) and "given poses" in out.stderr, out.stderr
    decisions = {d["id"]: d for d in json.loads((tmp_path / "d.json").read_text())["decisions"]}
    assert decisions["here"]["decision"] == "free"  # the sensor stood there: observed, nothing within 10 cm
    assert decisions["around"]["decision"] == "known"  # the rays passed through it (no map point lies in it)
