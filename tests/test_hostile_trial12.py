"""The twelfth hostile-input trial's findings on the diagnosis (docs/bad-input.md), through the command line.

Trial 12: a block of frames moved and moved back (frames 20-39 moved 50 cm, or turned 20 deg) read valid and clean --
the revisit pairs ran end-on-start and the whole-map probes fitted the unmoved majority; a 50 cm step half way along
a 20-frame log left 3 counted pairs whose 3rd largest correction was 0; a 180 deg pitch or roll step left no pair
registered and read valid; 1 deg/m of rotational drift was measured by the pairs (0.996 deg/m) while the gated drift
rate (0.18 deg/m) stayed a verdict; a 30 cm step in the second-to-last frame was never registered. The check now also
registers the frames after every jump of the trajectory (a step, a turn beyond what the neighbouring frames move)
onto the frames before it, and the drift rate is cross-checked in deg/m as in %/m.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_run import run_cli

VARIANTS = (
    ("block50", ("--step-frame", 20, "--step-m", "0.5,0,0"), ("--step-frame", 40, "--step-m", "-0.5,0,0")),
    ("blockyaw20", ("--step-frame", 20, "--step-deg", "0,0,20"), ("--step-frame", 40, "--step-deg", "0,0,-20")),
    ("pitch180", ("--step-frame", 45, "--step-deg", "0,180,0"), None),
    ("degdrift1", ("--drift-deg-per-m", 1), None),
    ("step58", ("--step-frame", 58, "--step-m", "0.3,0,0"), None),
    ("yaw5", ("--step-frame", 30, "--step-deg", "0,0,5"), None),
)


def _diagnose(store: Path, root: Path, rev: int) -> dict:
    path = root / f"diag{rev}.json"
    run = run_cli("diagnose", store, "--revision", rev, "--json", path)
    assert run.returncode == 0, run.stderr[-2000:]
    return json.loads(path.read_text())


def _store_with_variants(root: Path, synth_args: tuple, variants: tuple) -> dict:
    log, store = root / "log", root / "store"
    assert run_cli("synth", log, *synth_args).returncode == 0
    built = run_cli("build", log, "--out", store, "--poses", log / "groundtruth.txt", "--no-loop-closure")
    assert built.returncode == 0, built.stderr[-2000:]
    out = {"gt": _diagnose(store, root, 0)}
    for rev, (name, first, second) in enumerate(variants, start=1):
        poses = root / f"poses_{name}.txt"
        assert run_cli("perturb", log / "groundtruth.txt", poses, *first).returncode == 0
        if second is not None:
            again = root / f"poses_{name}_2.txt"
            assert run_cli("perturb", poses, again, *second).returncode == 0
            poses = again
        corrected = run_cli("correct", store, "--poses", poses)
        assert corrected.returncode == 0, corrected.stderr[-2000:]
        out[name] = _diagnose(store, root, rev)
    return out


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The 60-frame synthetic room (depth) with its true poses (revision 0) and one revision per :data:`VARIANTS`."""
    return _store_with_variants(tmp_path_factory.mktemp("trial12_room"), ("--seed", 3), VARIANTS)


@pytest.fixture(scope="module")
def short_log(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A 20-frame room log with its true poses and with a 50 cm step at frame 10."""
    return _store_with_variants(tmp_path_factory.mktemp("trial12_short"), ("--seed", 3, "--frames", 20),
                                (("step10", ("--step-frame", 10, "--step-m", "0.5,0,0"), None),))


def _cannot_judge(data: dict) -> None:
    assert data["valid"] is False
    assert not any(m["valid"] for m in data["coverage"]["measures"].values()), data["coverage"]["measures"]
    assert any("revisit check" in r for r in data["reasons"]), data["reasons"]


def _jump(check: dict, frame_id: int) -> dict:
    jumps = [j for j in check["jumps"] if j["frame_id"] == frame_id]
    assert jumps, check["jumps"]
    return jumps[0]


def test_t12_true_poses_read_consistent(room: dict, short_log: dict) -> None:
    for data in (room["gt"], short_log["gt"]):
        check = data["revisit_check"]
        assert data["valid"] is True, data["reasons"]
        assert not check["beyond_detector"] and not check["unfit"], check
        assert check["steps_disagreement_m"] is None or check["steps_disagreement_m"] < 0.02, check


def test_t12_a_block_moved_and_moved_back_is_measured_at_both_ends(room: dict) -> None:
    check = room["block50"]["revisit_check"]
    for frame_id in (20, 40):
        jump = _jump(check, frame_id)
        assert abs(jump["correction_m"] - 0.5) < 0.03, jump
    assert abs(check["steps_disagreement_m"] - 0.5) < 0.03 and check["beyond_detector"], check
    _cannot_judge(room["block50"])


def test_t12_a_block_turned_and_turned_back_is_measured(room: dict) -> None:
    check = room["blockyaw20"]["revisit_check"]
    assert abs(_jump(check, 20)["correction_deg"] - 20.0) < 1.5, check["jumps"]
    assert check["beyond_detector"], check
    _cannot_judge(room["blockyaw20"])


def test_t12_a_180_deg_flip_is_measured_and_no_verdict(room: dict) -> None:
    data = room["pitch180"]
    jump = _jump(data["revisit_check"], 45)
    assert jump["implausible"] and jump["excess_deg"] > 170, jump
    assert abs(jump["correction_deg"] - 180.0) < 3.0, jump  # undone by the jump's second hypothesis
    _cannot_judge(data)


def test_t12_a_step_near_the_end_is_measured(room: dict) -> None:
    jump = _jump(room["step58"]["revisit_check"], 58)
    assert abs(jump["correction_m"] - 0.3) < 0.03, jump
    _cannot_judge(room["step58"])


def test_t12_a_step_in_a_short_log_is_seen(short_log: dict) -> None:
    # 36 cm of travel per frame: frame 10 onto frames 8-9 is poorly constrained along the step (the true poses refine
    # to a 16.5 cm offset there), so the jump's size is not measured to the centimetre -- but it is seen, and the
    # figures are no verdict (the pairs and whole-map probes read 0.0 here: trial 12)
    jump = _jump(short_log["step10"]["revisit_check"], 10)
    assert jump["correction_m"] is not None and jump["correction_m"] > 0.3, jump
    _cannot_judge(short_log["step10"])


def test_t12_rotational_drift_beyond_the_gated_fit_is_no_verdict(room: dict) -> None:
    data = room["degdrift1"]
    check = data["revisit_check"]
    assert abs(check["drift_deg_per_m"] - 1.0) < 0.25, check
    drift = data["coverage"]["measures"]["drift_rate"]
    assert drift["valid"] is False, drift
    if data["drift_rate"]["deg_per_m"] < 0.5:  # the gated fit misses it: the reason says so
        assert any("turn by" in r and "deg per metre" in r for r in drift["reasons"]), drift


def test_t12_a_5_deg_yaw_step_is_located_and_measured(room: dict) -> None:
    """A 5 deg yaw step at frame 30 turns the room's 6.7 deg between frames into 11.7: at half the detectable error
    (5 deg) the jump sat on the threshold and was not checked; from a quarter it is, and measures the step. The
    revisiting frames sit 22 cm off at their sensors, beyond the detector's 20 cm, so the figures are no verdict (the
    detector flags less of the map than at 3 deg: they understate it)."""
    check = room["yaw5"]["revisit_check"]
    assert abs(_jump(check, 30)["correction_deg"] - 5.0) < 0.5, check["jumps"]
    assert 4.5 < check["disagreement_deg"] < 5.5 and check["beyond_detector"], check
    _cannot_judge(room["yaw5"])


def test_t12_when_the_pairs_do_not_fit_the_reason_names_a_measured_jump() -> None:
    """On the street a 5 deg yaw step at frame 100 leaves the loop's end 4 m from its start: no pair fits (`unfit`),
    while the frames after the jump fit the frames before it turned by 5.0 deg. The reason says where and how much
    (measured through the CLI: docs/diagnostics.md); here the verdict's wording on the check's own records."""
    from driftmap.diagnostics.revisits import STEP, STRETCH, RevisitCheck, RevisitCheckConfig, RevisitProbe, StepJump

    cfg = RevisitCheckConfig(max_detectable_m=1.0)
    pairs = [RevisitProbe(240 + k, 0.8, 0.2, 0.24, 0.3, 4.4, 5.0, False, k, k, 240.0, STRETCH) for k in range(4)]
    jump = StepJump(99, 100, 0.13, 5.0, False)
    step = RevisitProbe(100, 0.9, 0.8, 0.1, 0.33, 0.003, 5.002, True, 99, 90, 1.0, STEP)
    check = RevisitCheck(cfg, [*pairs, step], 100, (jump,))
    assert check.unfit and check.jump_correction(jump, True) == 5.002
    reason = check.reason()
    assert reason.startswith("only 0 of 4 revisiting frames fit"), reason
    assert "jumps between frames 99 and 100" in reason and "0.3 cm / 5.0 deg: a pose error there" in reason, reason
    fits = RevisitCheck(cfg, [*pairs, RevisitProbe(100, 0.9, 0.8, 0.1, 0.33, 0.0, 0.01, True, 99, 90, 1.0, STEP)], 100,
                        (jump,))
    assert "jumps between" not in fits.reason(), fits.reason()  # a jump that fits as placed is no pose error


@pytest.fixture(scope="module")
def turning_lidar(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The synthetic LiDAR room with two in-place turns of 8 x 45 deg (real jumps of the trajectory, many), built with
    its true poses, and a revision with a 3 deg yaw step at frame 12 (a straight stretch)."""
    root = tmp_path_factory.mktemp("trial13_turns")
    log, store = root / "log", root / "store"
    assert run_cli("synth", log, "--lidar", "--turns", 2, "--turn-deg-per-frame", 45, "--turn-frames", 8).returncode == 0
    built = run_cli("build", log, "--sensor", "lidar", "--out", store, "--poses", log / "groundtruth.txt",
                    "--no-loop-closure")
    assert built.returncode == 0, built.stderr[-2000:]
    assert run_cli("export", store, "--trajectory", root / "true.txt").returncode == 0
    assert run_cli("perturb", root / "true.txt", root / "yaw3.txt", "--step-frame", 12, "--step-deg",
                   "0,0,3").returncode == 0
    corrected = run_cli("correct", store, "--poses", root / "yaw3.txt")
    assert corrected.returncode == 0, corrected.stderr[-2000:]
    return {"gt": _diagnose(store, root, 0), "yaw3": _diagnose(store, root, 1)}


def test_t13_a_small_step_among_many_real_turns_is_checked_and_measured(turning_lidar: dict) -> None:
    """Trial 13 (F9): on the street a 3 deg yaw step read 0.09 deg in the revisit check: its jump (3 deg beyond the
    neighbouring turns) was crowded out of the 4 checked jumps by the street's real turns of 3-7 deg. With more jumps
    than checks, each is screened frame on frame (a real turn fits as placed, a pose error fits with the jump undone)
    and the disagreeing ones are checked first: here 16 real jump frames of 45 deg turns against one 3 deg step."""
    check = turning_lidar["yaw3"]["revisit_check"]
    step = _jump(check, 12)
    assert step["correction_deg"] == pytest.approx(3.0, abs=0.3), check["jumps"]
    assert check["steps_disagreement_deg"] == pytest.approx(3.0, abs=0.3), check
    truth = turning_lidar["gt"]["revisit_check"]  # the real turns fit as placed
    assert truth["jumps"] and all(j["correction_deg"] < 0.3 for j in truth["jumps"]), truth["jumps"]
