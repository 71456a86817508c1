"""Hostile trial 18's findings, each through the path the user took (docs/bad-input.md, trial 18): resumes,
corrections, rollbacks and merges over heads that do not place every stored frame."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_run import one_error, run_cli

from driftmap.trajectory import read_tum


def _ok(out):  # noqa: ANN001, ANN202 - a CompletedProcess
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])
    return out


def _steps(trajectory: Path) -> tuple[int, float, float]:
    """Rows, largest and median step between consecutive positions of a TUM file."""
    p = read_tum(trajectory).poses[:, :3, 3]
    d = np.linalg.norm(np.diff(p, axis=0), axis=1)
    return len(p), float(d.max()), float(np.median(d))


@pytest.fixture(scope="module")
def stores(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The trial's room (seed 3, 60 frames): ``s2`` built over frames 0:20 with loop closure, corrected to the ground
    truth, resumed to 0:40 (loop closure on, no loop in reach); ``s5`` a copy resumed to 0:60 and rolled back to
    revision 1 (it places 20 of its 60 frames)."""
    root = tmp_path_factory.mktemp("trial18")
    log = root / "room"
    _ok(run_cli("synth", log, "--seed", 3, "--frames", 60))
    s2 = root / "s2"
    _ok(run_cli("build", log, "--out", s2, "--frames", "0:20"))
    _ok(run_cli("correct", s2, "--poses", log / "groundtruth.txt"))
    resumed = _ok(run_cli("build", log, "--out", s2, "--frames", "0:40", "--resume"))
    s5 = root / "s5"
    shutil.copytree(s2, s5)
    _ok(run_cli("build", log, "--out", s5, "--frames", "0:60", "--resume"))
    _ok(run_cli("rollback", s5, "--to", 1))
    return {"root": root, "log": log, "s2": s2, "s5": s5, "resume_stderr": resumed.stderr}


def test_t18_b1_a_resume_whose_loop_closure_accepts_no_loop_carries_the_heads_correction(stores: dict) -> None:
    """B1: `build --resume` on a corrected store whose loop closure ran and accepted no loop wrote no revision, and the
    head placed the 20 new frames at their uncorrected poses beside 20 ground-truth ones (a 1.44 m / 100 deg seam),
    without a word. The head's correction is now carried on to them whenever the resume makes no revision of its own."""
    assert "correction on to them" in " ".join(stores["resume_stderr"].split())
    _ok(run_cli("export", stores["s2"], "--trajectory", stores["root"] / "s2.txt"))
    rows, largest, median = _steps(stores["root"] / "s2.txt")
    assert rows == 40 and largest < 2 * median, (largest, median)  # the seam was 1.44 m against 0.12 m steps
    # W1: `revisions` says which frames each revision places: the carry revision adds the 20 new ones
    table = _ok(run_cli("revisions", stores["s2"])).stdout
    rows_of = [[c.strip() for c in line.split("\u2502") if c.strip()] for line in table.splitlines()
               if line.startswith("\u2502") and line.split("\u2502")[1].strip().isdigit()]
    assert [r[-1] for r in rows_of] == ["40", "20", "40 (+20)"], table


def test_t18_b4_merge_refuses_a_session_whose_head_leaves_frames_out(stores: dict) -> None:
    """B4: `merge` took every stored frame of a session at its head's poses, also those a rollback left out (at the
    poses of a revision the head does not hold: a 1.41 m seam in the merged session). Such a source is refused,
    naming the frames left out and the rollback that places them all."""
    root = stores["root"]
    other = root / "B"
    _ok(run_cli("build", stores["log"], "--out", other, "--frames", "25:55", "--no-loop-closure"))
    line = one_error(run_cli("merge", stores["s5"], other, "--out", root / "M"))
    assert f"{stores['s5']}: its head (revision 4, rollback) places 20 of the 60 frames it stores" in line, line
    assert "40 left out, 20..59" in line and f"driftmap rollback {stores['s5']} --to 3" in line, line
    assert not (root / "M").exists()


def test_t18_b5_a_correction_of_frames_the_head_leaves_out_does_not_move_the_heads_frames(stores: dict) -> None:
    """B5: `correct` with rows only for frames the head does not place took their stored poses (another revision's,
    another world frame) as the head's and propagated the difference: frames at the ground truth moved 1.25-1.58 m.
    Only frames the head places carry a correction now; the others are set, the head's frames keep their poses."""
    root = stores["root"]
    s7 = root / "s7"
    shutil.copytree(stores["s5"], s7)
    gt_lines = [line for line in (stores["log"] / "groundtruth.txt").read_text().splitlines() if not line.startswith("#")]
    (root / "gt_40_59.txt").write_text("\n".join(gt_lines[40:60]) + "\n")
    _ok(run_cli("export", s7, "--trajectory", root / "s7_before.txt"))
    out = _ok(run_cli("correct", s7, "--poses", root / "gt_40_59.txt"))
    assert "none of its 20 frames is placed by revision 4" in " ".join(out.stderr.split()), out.stderr[-2000:]
    _ok(run_cli("export", s7, "--trajectory", root / "s7_after.txt"))
    before, after = read_tum(root / "s7_before.txt"), read_tum(root / "s7_after.txt")
    assert len(before) == 20 and len(after) == 40
    np.testing.assert_allclose(after.poses[:20], before.poses, atol=1e-9)  # the head's frames did not move
    gt = read_tum(stores["log"] / "groundtruth.txt")
    np.testing.assert_allclose(after.poses[20:, :3, 3], gt.poses[40:60, :3, 3], atol=1e-6)


def test_t18_w4_a_resume_over_a_rollback_says_it_places_the_frames_left_out_again(stores: dict) -> None:
    """W4: a resume over a rollback that left frames out placed them again without a word (the warning named only
    the new frames). It now counts them, and carries the head's correction on to them as to the new frames."""
    root = stores["root"]
    s3 = root / "s3"
    shutil.copytree(stores["s2"], s3)
    _ok(run_cli("rollback", s3, "--to", 1))  # 20 of the 40 stored frames
    assert "20 (-20)" in _ok(run_cli("revisions", s3)).stdout  # W1: the rollback leaves 20 out
    out = _ok(run_cli("build", stores["log"], "--out", s3, "--frames", "0:60", "--resume", "--no-loop-closure"))
    said = " ".join(out.stderr.split())
    assert "the 40 frames it does not place (20..59: 20 new frames, 20 stored frames it leaves out)" in said, said
    _ok(run_cli("export", s3, "--trajectory", root / "s3.txt"))
    rows, largest, median = _steps(root / "s3.txt")
    assert rows == 60 and largest < 2 * median, (largest, median)


def test_t18_w5_decide_against_warns_when_the_decided_revisions_place_other_frames(stores: dict) -> None:
    """W5: `decide --revision 1 --against OTHER` compared the stores' frames (the same 40) and did not say that
    revision 1 places 20 of them: "2 of 3 decisions flipped" read as a pose change. It warns now, as it does for stores
    that hold other frames."""
    root = stores["root"]
    other = root / "s2_copy"
    shutil.copytree(stores["s2"], other)
    queries = root / "q.json"
    queries.write_text('{"queries": [{"id": "c", "kind": "clearance", "points_m": [[0.0, 0.0, 1.0]], "radius_m": 0.1}]}')
    out = _ok(run_cli("decide", stores["s2"], "--queries", queries, "--revision", 1, "--json", root / "d.json",
                      "--against", other))
    said = " ".join(out.stderr.split())
    assert "the revisions decided place different frames (20 in both; revision 1 of" in said, said
    out = _ok(run_cli("decide", stores["s2"], "--queries", queries, "--json", root / "d2.json", "--against", other))
    assert "place different frames" not in " ".join(out.stderr.split())  # both heads place the 40


def _cut_segment_at(store: Path, frame_id: int) -> Path:
    """Truncate the segment holding ``frame_id`` in the middle of that frame's points (what follows -- later frames,
    a revision record, the segment's summary -- is cut off); returns the segment."""
    from driftmap.store.frame_store import FrameStore

    with FrameStore.open(store) as s:
        ref = s._refs[frame_id]
        segment, offset = ref.segment, ref.payload_offset
    with open(segment, "r+b") as fh:
        fh.truncate(offset + 100)
    return segment


def test_t18_b8_a_resumes_revision_cut_off_its_segment_is_named_lost_and_the_head_shows_no_seam(stores: dict) -> None:
    """B8: damage that cut the resume's carry revision (the last record of its segment) off went unnoticed: `recover`
    kept the frames before the cut, said nothing of revision 2, and the head (revision 1) showed the resumed frames at
    their uncorrected poses (the 1.44 m seam of B1). The manifest records what each closed segment holds, so `recover`
    names what was cut off, and the stand-in for revision 2 places the frames revision 1 places (W7)."""
    root = stores["root"]
    store = root / "b8"
    shutil.copytree(stores["s2"], store)
    _cut_segment_at(store, 35)
    out = _ok(run_cli("recover", store))
    text = " ".join(out.stdout.split())
    assert "frames [35" in text and "revisions [2] are lost" in text, text
    exported = _ok(run_cli("export", store, "--trajectory", root / "b8.txt"))
    assert "revisions [2] are lost" in " ".join(exported.stderr.split()), exported.stderr[-2000:]
    rows, largest, median = _steps(root / "b8.txt")
    # the head is the stand-in for revision 2: revision 1's 20 frames at their corrected poses, no resumed frame at
    # an uncorrected one
    assert rows == 20 and largest < 2 * median, (rows, largest, median)
    from driftmap.store.frame_store import FrameStore

    with FrameStore.open(store) as s:
        assert s.head == 2 and s.loss.revision_ids == (2,) and 35 in s.loss.frame_ids
    # trial 19 W1, W4: `info` says why the head leaves frames out, and lost frames do not read as an interrupted build
    info = " ".join(_ok(run_cli("info", store)).stdout.replace("\u2502", " ").split())
    assert "stands in for revision 2" in info and "build interrupted" not in info, info
    # trial 20 W3: merging it is refused with the way out that keeps the correction (the resume), not only a rollback
    other = root / "b8_other"
    _ok(run_cli("build", stores["log"], "--out", other, "--frames", "0:6", "--no-loop-closure"))
    refusal = one_error(run_cli("merge", store, other, "--out", root / "b8_merged"))
    assert "the stand-in for a revision lost to damage" in refusal and "build --resume" in refusal, refusal
    # trial 19 W4: a resume after the recovery stores the lost frames 35..39 again, and its note says so (it called
    # all 20 frames the stand-in leaves out "new"); the head is named as the stand-in it is
    resumed = _ok(run_cli("build", stores["log"], "--out", store, "--frames", "0:40", "--resume"))
    said = " ".join(resumed.stderr.split())
    assert "head was revision 2 (the stand-in for a lost revision, with revision 1's poses (external_file))" in said, (
        said[-2000:])  # trial 20 W4: it said "(none), a correction"
    assert ("the 20 frames it does not place (20..39: 0 new frames, 5 frames stored again after a loss, 15 stored "
            "frames it leaves out)") in said, said[-2000:]
    with FrameStore.open(store) as s:  # the carry revision takes the source of the poses it carries, not "none"
        assert s.revisions[s.head].source.value == "external_file", s.revisions[s.head]


def test_t18_w7_the_stand_in_for_a_lost_revision_places_its_predecessors_frames(stores: dict) -> None:
    """W7: a stand-in placed every frame stored before it, so `export --revision` of a lost carry revision showed
    frames 20..29 at odometry poses beside ground-truth ones (a 1.44 m seam). It places its predecessor's frames now."""
    root = stores["root"]
    store = root / "w7"
    shutil.copytree(stores["s2"], store)
    _ok(run_cli("build", stores["log"], "--out", store, "--frames", "0:60", "--resume"))  # revision 3 after it
    _cut_segment_at(store, 30)  # frames 30..39 and revision 2's record lost; revision 3 survives
    text = " ".join(_ok(run_cli("recover", store)).stdout.split())
    assert "revisions [2] are lost" in text, text
    _ok(run_cli("export", store, "--revision", 2, "--trajectory", root / "w7_2.txt"))
    rows, largest, median = _steps(root / "w7_2.txt")
    assert rows == 20 and largest < 2 * median, (rows, largest, median)


def test_t18_b8_build_resume_on_a_missing_folder_says_it_builds_a_new_store(stores: dict) -> None:
    """`build --resume` on a folder that does not exist built from scratch without a word (a mistyped --out)."""
    out = _ok(run_cli("build", stores["log"], "--out", stores["root"] / "typo", "--frames", "0:6", "--resume",
                      "--no-loop-closure"))
    assert "nothing to resume" in " ".join(out.stderr.split()), out.stderr[-2000:]


def test_t19_w3_a_resume_with_no_new_frames_places_the_frames_the_head_leaves_out(stores: dict) -> None:
    """Hostile trial 19 W3: `build --resume` over a rollback that left 40 of 60 frames out placed them again when the
    resume added a frame, but not when it added none (0 / 60 new: no revision, the head still placed 20)."""
    root = stores["root"]
    store = root / "w3"
    shutil.copytree(stores["s5"], store)
    _ok(run_cli("build", stores["log"], "--out", store, "--frames", "0:60", "--resume"))
    _ok(run_cli("export", store, "--trajectory", root / "w3.txt"))
    rows, largest, median = _steps(root / "w3.txt")
    assert rows == 60 and largest < 2 * median, (rows, largest, median)


def test_t20_w6_diagnose_samples_only_the_frames_the_head_places(stores: dict) -> None:
    """Hostile trial 20 W6: `diagnose` of a head that places 20 of 60 stored frames (a rollback) sampled all 60
    ("sampling frames 60/60") and diagnosed 20. It samples the 20 it diagnoses."""
    import json

    out = _ok(run_cli("diagnose", stores["s5"], "--json", stores["root"] / "w6.json"))
    said = " ".join(out.stderr.split())
    assert "sampling frames" in said and "20/20" in said and "60/60" not in said, said[-2000:]
    data = json.loads((stores["root"] / "w6.json").read_text())
    assert data["n_frames"] == 20, {k: data[k] for k in ("n_frames", "revision") if k in data}
