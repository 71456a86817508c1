"""The tenth hostile-input trial's findings (docs/bad-input.md), through the command line.

B1: ``diagnose`` rated a map with a 30 cm (or 30 deg) pose step as clean -- 0 regions, 0 % doubled, no change
point, drift 0, verdict valid -- better than the same map with a 3 cm step. The revisit check
(:mod:`driftmap.diagnostics.revisits`) now measures the step and the figures say they cannot judge.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli


@pytest.fixture(scope="module")
def stepped(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A 60-frame synthetic room stored with its ground-truth poses (revision 0), then corrected to poses with a step
    at frame 30: revision 1 a 3 cm step, 2 a 30 cm step, 3 a 30 deg yaw step, 4 a 3 m step, 5 a 180 deg turn (perturb
    + correct, as a user would)."""
    root = tmp_path_factory.mktemp("trial10_b1")
    log, store = root / "log", root / "store"
    assert run_cli("synth", log, "--seed", 3).returncode == 0
    built = run_cli("build", log, "--out", store, "--poses", log / "groundtruth.txt", "--no-loop-closure")
    assert built.returncode == 0, built.stderr[-2000:]
    for name, step in (("3cm", ("--step-m", "0.03,0,0")), ("30cm", ("--step-m", "0.3,0,0")),
                       ("30deg", ("--step-deg", "0,0,30")), ("3m", ("--step-m", "3,0,0")),
                       ("180deg", ("--step-deg", "0,0,180"))):
        poses = root / f"gt_{name}.txt"
        assert run_cli("perturb", log / "groundtruth.txt", poses, "--step-frame", 30, *step).returncode == 0
        corrected = run_cli("correct", store, "--poses", poses)
        assert corrected.returncode == 0, corrected.stderr[-2000:]
    diagnoses = {}
    for rev in range(6):
        out = root / f"diag{rev}.json"
        run = run_cli("diagnose", store, "--revision", rev, "--json", out)
        assert run.returncode == 0, run.stderr[-2000:]
        diagnoses[rev] = (json.loads(out.read_text()), " ".join(run.stdout.split()))
    return diagnoses


def test_t10_b1_a_step_beyond_the_detectors_range_is_measured_and_the_figures_cannot_judge(stepped: dict) -> None:
    good, good_out = stepped[0]
    check = good["revisit_check"]
    assert good["valid"] is True, good["reasons"]
    assert check["judged"] and not check["beyond_detector"], check
    assert check["disagreement_m"] < 0.01 and check["disagreement_deg"] < 0.5, check
    assert "within the detector's range" in good_out

    small, _ = stepped[1]  # 3 cm: within range, measured by the check and flagged by the detector
    assert abs(small["revisit_check"]["disagreement_m"] - 0.03) < 0.01, small["revisit_check"]
    assert small["valid"] is True and small["double_wall"]["regions"], small["reasons"]

    for rev, (metres, degrees) in ((2, (0.3, 0.0)), (3, (None, 30.0))):
        data, out = stepped[rev]
        check = data["revisit_check"]
        assert check["judged"] and check["beyond_detector"], check
        if metres is not None:
            assert abs(check["disagreement_m"] - metres) < 0.03, check
        assert abs(check["disagreement_deg"] - degrees) < 3.0, check
        # no headline figure is a verdict, and the reason names the check and the detector's range
        assert data["valid"] is False
        measures = data["coverage"]["measures"]
        assert not any(m["valid"] for m in measures.values()), measures
        assert any("revisit check" in r and "beyond the 20 cm / 10 deg" in r for r in data["reasons"]), data["reasons"]
        assert "BEYOND the detector's range" in out and "cannot judge (" in out, out[-3000:]


def test_t10_b1_a_step_beyond_what_the_revisit_check_reaches_is_not_judged(stepped: dict) -> None:
    """Trial 11: a 3 m step and a 180 deg turn were beyond what the check's registration reaches from its 80 cm gate:
    too few revisiting frames registered, the check said nothing and the map read as valid. Frames that overlap the
    earlier map but do not fit it now make the figures say they cannot judge."""
    for rev in (4, 5):
        data, out = stepped[rev]
        check = data["revisit_check"]
        assert check["unfit"] or check["beyond_detector"], check
        assert check["n_registered"] >= 3, check
        assert data["valid"] is False and any("revisit check" in r for r in data["reasons"]), data["reasons"]
        assert "cannot judge (" in out, out[-3000:]
    assert stepped[0][0]["revisit_check"]["unfit"] is False


def _clearance_queries(path: Path, ids: tuple[str, ...] = ("c",)) -> Path:
    path.write_text(json.dumps({"queries": [{"id": i, "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]],
                                             "radius_m": 0.2} for i in ids]}))
    return path


def test_t10_w1_a_voxel_size_beyond_any_map_is_named_as_too_large(room10: dict, tmp_path: Path) -> None:
    """``[volume] voxel_size_m = 1e308`` was refused as voxels "too small for this extent"; a 50 m voxel built an
    800 m grid for a 3 m room. Now: at most 10 m, and never larger than the map (its size named)."""
    queries = _clearance_queries(tmp_path / "q.json")
    for voxel, expected in (("1e308", "volume.voxel_size_m: Input should be less than or equal to 10 (got 1e+308)"),
                            ("9", "volume.voxel_size_m = 9 m is larger than the map itself (")):
        config = tmp_path / f"v{voxel}.toml"
        config.write_text(f"[volume]\nvoxel_size_m = {voxel}\n")
        line = one_error(run_cli("decide", room10["gt"], "--queries", queries, "--json", tmp_path / "d.json",
                                 "--config", config))
        assert expected in line and "too small" not in line, line
        assert not (tmp_path / "d.json").exists()
    assert "use a voxel of at most" in line


def test_t10_w3_matching_by_stamp_refused_names_matching_by_index() -> None:
    from driftmap.errors import StoreError
    from driftmap.store.pose_match import match_trajectory
    from driftmap.trajectory import Trajectory

    traj = Trajectory(np.array([0, 100_000_000], dtype=np.int64), np.stack([np.eye(4)] * 2), None)
    with pytest.raises(StoreError, match=r"less than 1 ms apart .*driftmap correct --match index"):
        match_trajectory(traj, [0, 1, 2], [0, 100_000_000, 100_500_000], match="stamp")


def test_t10_w4_a_query_id_with_white_space_around_it_is_refused(room10: dict, tmp_path: Path) -> None:
    """Ids "c" and "c " were taken as two queries that every report line shows alike."""
    queries = _clearance_queries(tmp_path / "q.json", ("c", "c "))
    line = one_error(run_cli("decide", room10["gt"], "--queries", queries, "--json", tmp_path / "d.json"))
    assert "query #2: 'id' 'c ' begins or ends with white space" in line and "write it as 'c'" in line, line
    assert not (tmp_path / "d.json").exists()


@pytest.mark.parametrize("frames", ["\u0663:5", "0:\u00b2", "\uff11:5"])
def test_t10_w5_frames_take_ascii_digits_only(frames: str, room10: dict, tmp_path: Path) -> None:
    """``--frames "٣:5"`` (an Arabic-Indic three) was read as 3:5; superscripts and full-width digits alike."""
    line = one_error(run_cli("build", room10["log"], "--out", tmp_path / "s", "--frames", frames))
    assert f"--frames '{frames}'" in line and "digits only: ASCII 0-9" in line, line
    assert not (tmp_path / "s").exists()


def test_t10_w5_decide_compare_takes_ascii_digits_only(room10: dict, tmp_path: Path) -> None:
    queries = _clearance_queries(tmp_path / "q.json")
    for pair in ("0,\u0661", "\u00b2,0"):
        line = one_error(run_cli("decide", room10["gt"], "--queries", queries, "--json", tmp_path / "d.json",
                                 "--compare", pair))
        assert "expected two revision ids A,B" in line and "Traceback" not in line, line


@pytest.mark.parametrize(("qid", "named"), [("c\u200b", "U+200B"), ("\ufeffc", "U+FEFF"), ("c\u202e", "U+202E"),
                                           ("cafe\u0301", "composed form (NFC)")])
def test_t11_w2_a_query_id_that_prints_like_another_is_refused(qid: str, named: str, tmp_path: Path) -> None:
    """Trial 11: "c1" and "c1" + a zero-width space (or a byte-order mark, a right-to-left override, a decomposed
    accent) were two queries that every report line shows alike."""
    from driftmap.decisions.errors import QueryError
    from driftmap.decisions.query_file import load_queries

    queries = _clearance_queries(tmp_path / "q.json", ("c", qid))
    with pytest.raises(QueryError, match=r"query #2: 'id' .*" + re.escape(named)):
        load_queries(queries)
    assert load_queries(_clearance_queries(tmp_path / "ok.json", ("c", "caf\u00e9")))  # composed, one character


def test_t11_w4_view_names_a_voxel_larger_than_the_map_and_its_flag(room10: dict, tmp_path: Path) -> None:
    """``view --voxel-size-m 100`` drew nine dots without a word; 1e-6 was refused without naming the flag."""
    line = one_error(run_cli("view", room10["gt"], "--voxel-size-m", 100, "--headless", "--out", tmp_path / "v"))
    assert "--voxel-size-m 100 is larger than the map itself (" in line and "points; leave it out" in line, line
    line = one_error(run_cli("view", room10["gt"], "--voxel-size-m", "1e-6", "--headless", "--out", tmp_path / "v"))
    assert "view --voxel-size-m 1e-06: voxel coordinates" in line and "use a larger voxel size" in line, line
    assert not (tmp_path / "v").exists() or not any((tmp_path / "v").iterdir())
