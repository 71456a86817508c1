"""A real LiDAR log nobody tuned for (balm-lidar-0-79: a non-repetitive Livox-like scanner, 2 Hz, a stationary
start of ~23 scans, a 43 deg turn between two scans), built with every default through the CLI."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from driftmap.diagnostics.trajectory_metrics import trajectory_errors
from driftmap.store.frame_store import FrameStore


def lio_poses(balm_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps in s, T_world_sensor) of alidarPose.csv, read independently of driftmap's readers."""
    rows = np.loadtxt(balm_dir / "alidarPose.csv", delimiter=",", usecols=range(4)).reshape(-1, 4, 4)
    stamps = rows[:, 3, 3].copy()
    poses = rows.copy()
    poses[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return stamps, poses


@pytest.fixture(scope="session")
def balm_build(tmp_path_factory: pytest.TempPathFactory, balm_dir: Path) -> Path:
    """``driftmap build balm-lidar-0-79 --out STORE``: no option, no config (read only afterwards)."""
    out = tmp_path_factory.mktemp("balm") / "store"
    proc = subprocess.run([sys.executable, "-m", "driftmap.cli", "build", str(balm_dir), "--out", str(out)],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (out / "cli_stdout.txt").write_text(proc.stdout)
    (out / "cli_stderr.txt").write_text(proc.stderr)
    return out


@pytest.mark.slow
def test_default_build_tracks_the_real_livox_log_within_10_cm_of_lio(balm_build: Path, balm_dir: Path) -> None:
    _, lio = lio_poses(balm_dir)
    store = FrameStore.open(balm_build)
    ids = store.frame_ids
    assert list(ids) == list(range(80))
    for revision in (0, store.head):
        errors = trajectory_errors(store.poses(revision), lio[ids])
        assert errors.ate_rmse_m <= 0.10, (revision, errors)  # measured 1.8 / 1.6 cm (2.4 / 2.3 before the point-to-plane refinement; it was 2.9 m)
        path = np.linalg.norm(np.diff(store.poses(revision)[:, :3, 3], axis=0), axis=1).sum()
        lio_path = np.linalg.norm(np.diff(lio[ids, :3, 3], axis=0), axis=1).sum()
        assert abs(path - lio_path) < 0.05 * lio_path  # 24.8 m, not 35 m


@pytest.mark.slow
def test_default_build_records_tracking_health_and_flags_nothing_on_the_real_log(balm_build: Path) -> None:
    summary = json.loads((balm_build / "build_summary.json").read_text())
    tracking = summary["tracking"]
    assert tracking["frames"] == 80 and tracking["flagged"] == []
    per_frame = {r["frame_id"]: r for r in tracking["per_frame"]}
    stationary = [per_frame[k] for k in range(1, 22)]  # the sensor stands still for the first ~23 scans
    assert all(r["status"] == "ok" and r["fitness"] > 0.85 for r in stationary)
    # the scan after the 43 deg turn (65 -> 66) turns only 9 deg: the constant-velocity prediction is 33 deg off
    # and its registration fits half the points; another initial guess fits and the frame is recovered, not lost
    assert per_frame[67]["status"] == "recovered" and per_frame[67]["fitness"] > 0.9
    assert "fitness" in per_frame[67]["reason"]
    assert [r["frame_id"] for r in tracking["recovered"]] == [r["frame_id"] for r in tracking["per_frame"]
                                                               if r["status"] == "recovered"]
    store = FrameStore.open(balm_build)
    assert store.frame(67).tracking is not None and store.frame(67).tracking.status.value == "recovered"
    # the lengths come from frames spread over the log, not from frame 0 alone
    reach = summary["scene_reach"]
    assert len(reach["frame_ids"]) == 15 and reach["frame_ids"][0] == 0 and reach["frame_ids"][-1] == 79
    assert summary["odometry_config"]["voxel_size_m"] == pytest.approx(reach["reach_m"] / 25.0)
    assert "tracking ok / recovered / flagged" in (balm_build / "cli_stdout.txt").read_text()


def _cli(*args: object, timeout: float = 900) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, (args, proc.stderr[-3000:])
    return proc


@pytest.fixture(scope="session")
def balm_diagnoses(tmp_path_factory: pytest.TempPathFactory, balm_dir: Path, balm_build: Path) -> dict[str, dict]:
    """``diagnose --json`` of three maps of the same scans: placed with the LIO poses (``build --poses
    alidarPose.csv``), by driftmap's own odometry (the default build), and with the LIO poses broken on purpose
    (``driftmap perturb``: a 3 deg yaw step at frame 50 and 1 %/m drift)."""
    from driftmap.trajectory import read_trajectory, write_tum

    work = tmp_path_factory.mktemp("balm_maps")
    lio_tum = work / "lio.txt"
    write_tum(lio_tum, read_trajectory(balm_dir / "alidarPose.csv"))
    _cli("perturb", lio_tum, work / "broken.txt", "--step-frame", BROKEN_STEP_FRAME, "--step-deg", "0,0,3",
         "--drift-percent-per-m", "1")
    lio = read_trajectory(balm_dir / "alidarPose.csv")  # the LIO poses of a scanner mounted turned 10 deg in yaw
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", TURNED_DEG, degrees=True).as_matrix()
    write_tum(work / "turned.txt", dataclasses.replace(lio, poses=lio.poses @ turn))
    stores = {"odometry": balm_build}
    for name, poses in (("lio", balm_dir / "alidarPose.csv"), ("broken", work / "broken.txt"),
                        ("turned", work / "turned.txt")):
        stores[name] = work / name
        _cli("build", balm_dir, "--out", stores[name], "--poses", poses, "--no-loop-closure")
    out: dict[str, dict] = {"given_poses": {}}
    for name in ("lio", "broken", "turned"):  # build --poses checks the poses against the scans (build_summary.json)
        out["given_poses"][name] = json.loads((stores[name] / "build_summary.json").read_text())["given_poses_check"]
    del stores["turned"]  # built for its given-poses check only
    for name, store in stores.items():
        _cli("diagnose", store, "--json", work / f"{name}.json")
        out[name] = json.loads((work / f"{name}.json").read_text())
    return out


BROKEN_STEP_FRAME = 50
TURNED_DEG = 10.0


@pytest.mark.slow
def test_diagnose_ranks_a_broken_map_of_the_real_log_worse_on_every_headline_figure(balm_diagnoses: dict[str, dict]) -> None:
    """The failure that discredited MOM: a broken map must not read as the more consistent one. Measured: fraction
    flagged LIO / odometry / broken 0.14 / 0.09 / 6.0 %, inconsistent 1.5 / 1.8 / 19.4 %, smearing 4.0 / 3.8 /
    7.0 mm, drift 0.22 / 0.21 / 0.72 %/m (the injected drift is 1 %/m)."""
    lio, odo, broken = (balm_diagnoses[k] for k in ("lio", "odometry", "broken"))
    for d in (lio, odo, broken):  # every map was judged, and says how much of it
        assert d["valid"] is True and d["coverage"]["fraction_evaluated"] > 0.5, d["reasons"]
        assert d["coverage"]["frames_with_refused_normals"] == 0  # the reader dropped the zero normals already
        assert d["double_wall"]["voxels_evaluated"] > 5000
    good = (lio, odo)
    assert broken["double_wall"]["fraction_flagged"] > 5 * max(d["double_wall"]["fraction_flagged"] for d in good)
    assert broken["fraction_inconsistent"] > 4 * max(d["fraction_inconsistent"] for d in good)
    assert broken["smearing_score_m"] > 1.3 * max(d["smearing_score_m"] for d in good)
    assert broken["drift_rate"]["percent_per_m"] > 2 * max(d["drift_rate"]["percent_per_m"] for d in good)
    # the step is located, as a rotation about the sensor
    near = [c for c in broken["change_points"] if abs(c["frame_id"] - BROKEN_STEP_FRAME) <= 2]
    assert near and 2.0 <= float(np.linalg.norm(near[0]["step_deg"])) <= 4.0, broken["change_points"]
    assert not [c for c in lio["change_points"] if abs(c["frame_id"] - BROKEN_STEP_FRAME) <= 2]
    # the revisit check (trial 10) registers revisiting scans onto the earlier map: the LIO and odometry maps agree
    # with themselves within a few cm (measured 4.5 cm LIO, 1.1 cm odometry), the broken one by its 3 deg step and
    # drift (53 cm, 2.7 deg); all within the detector's range at this scene's scale, so every figure stays a verdict
    checks = {k: balm_diagnoses[k]["revisit_check"] for k in ("lio", "odometry", "broken")}
    assert all(c["judged"] and not c["beyond_detector"] for c in checks.values()), checks
    assert max(checks[k]["disagreement_m"] for k in ("lio", "odometry")) < 0.08, checks
    assert 2.0 < checks["broken"]["disagreement_deg"] < 4.0, checks["broken"]
    assert checks["broken"]["disagreement_m"] > 3 * max(checks[k]["disagreement_m"] for k in ("lio", "odometry"))


@pytest.mark.slow
def test_build_with_the_lio_poses_finds_them_moving_as_the_scans_do(balm_diagnoses: dict[str, dict]) -> None:
    """``build --poses alidarPose.csv``: the LIO poses are this scanner's, so frame pairs registered onto each other
    fit as the file places them (measured: 8 of 8 pairs decide, corrections <= 1.6 cm / 0.16 deg); the broken copy
    (a 3 deg step at one frame, 1 %/m drift) moves each pair as the scans do too, so it is no other sensor's file."""
    for name in ("lio", "broken"):
        check = balm_diagnoses["given_poses"][name]
        assert check["consistent"] is True and check["n_decisive"] >= 6 and check["n_disagreeing"] == 0, check
    assert max(p["correction_m"] for p in balm_diagnoses["given_poses"]["lio"]["pairs"]) < 0.05
    for name in ("lio", "broken"):  # no mounting rotation read into registration noise (measured 0.2-0.3 deg)
        assert balm_diagnoses["given_poses"][name]["mounting_rotation"]["explains"] is False


@pytest.mark.slow
def test_build_with_lio_poses_of_a_scanner_mounted_turned_says_by_how_much(balm_diagnoses: dict[str, dict]) -> None:
    """Hostile trial 13 (F1): the LIO poses turned 10 deg about the scanner's z read "given poses fit the frames: yes".
    Each pair's error (the 24 cm step turned by 10 deg: 1.5-10.8 cm) stays within the registration's inlier distance,
    but across the pairs the scans move as the file would with the scanner mounted turned: the fitted rotation is the
    offset (measured 10.0 deg about z, leaving 0.09 of the pairs' disagreement)."""
    check = balm_diagnoses["given_poses"]["turned"]
    assert check["consistent"] is False and check["n_decisive"] >= 6, check
    mounting = check["mounting_rotation"]
    assert mounting["explains"] is True and abs(mounting["angle_deg"] - TURNED_DEG) < 1.0, mounting
    assert abs(mounting["rotvec_deg"][2] - TURNED_DEG) < 1.0, mounting  # about the scanner's z
    assert mounting["residual_after_m"] < 0.3 * mounting["residual_before_m"], mounting


@pytest.mark.slow
def test_real_log_frames_carry_the_2_hz_stamps_of_the_data(balm_build: Path, balm_dir: Path) -> None:
    stamps_s, _ = lio_poses(balm_dir)
    store = FrameStore.open(balm_build)
    stored = store.ledger.stamps_ns
    assert np.max(np.abs(stored - np.round(stamps_s[store.frame_ids] * 1e9))) < 1_000  # within 1 us of the csv
    period = np.diff(stored) * 1e-9
    assert 0.48 < period.min() and period.max() < 0.52
