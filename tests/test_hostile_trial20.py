"""Hostile trial 20's findings on resumes and rollbacks, each through the command line (docs/bad-input.md, trial 20;
its store findings B1, B2 are in tests/test_store.py, W4 in tests/test_hostile_trial18.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_run import one_error, run_cli

from driftmap.store.frame_store import FrameStore


def _ok(out):  # noqa: ANN001, ANN202 - a CompletedProcess
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])
    return out


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The trial's room (seed 3, 60 frames) and a store of its frames 0:25 (odometry, no loop closure)."""
    root = tmp_path_factory.mktemp("trial20")
    log = root / "room"
    _ok(run_cli("synth", log, "--seed", 3, "--frames", 60))
    store = root / "s25"
    _ok(run_cli("build", log, "--out", store, "--frames", "0:25", "--threads", 1, "--no-loop-closure"))
    return {"root": root, "log": log, "s25": store}


def _copy(room: dict, name: str) -> Path:
    import shutil

    shutil.copytree(room["s25"], room["root"] / name)
    return room["root"] / name


def test_t20_b3_a_resume_that_jumps_ahead_of_the_stored_frames_is_refused(room: dict) -> None:
    """B3: `build --resume --frames=-10:` on a store of frames 0..24 tracked across the 25 missing frames and stored
    frames 50..59 2-5.5 m off, exit 0, naming no gap. The odometry cannot bridge it: refused, nothing stored. A
    selection with the stored frames' own step resumes as before."""
    store = _copy(room, "b3")
    out = run_cli("build", room["log"], "--out", store, "--frames=-10:", "--threads", 1, "--resume",
                  "--no-loop-closure")
    message = one_error(out)
    assert "would add frame 50 after frame 24" in message and "skipping the frames between" in message, message
    assert "holds frame 24 and the frames after it" in message, message
    with FrameStore.open(store) as s:
        assert len(s) == 25 and len(s.revisions) == 1
    # a selection that starts right after the last stored frame is tracked on
    after = _copy(room, "b3_after")
    _ok(run_cli("build", room["log"], "--out", after, "--frames", "25:30", "--threads", 1, "--resume",
                "--no-loop-closure"))


@pytest.mark.parametrize("stored, resumed", [("0:3:3", "0:30:3"), ("0:25", "0:60:3"), ("0:20:4", "0:40:4")])
def test_t21_b1_a_selection_holding_the_last_stored_frame_resumes_whatever_its_step(room: dict, stored: str,
                                                                                  resumed: str) -> None:
    """Hostile trial 21 B1, W4: the gap check (trial 20 B3) judged the jump from the last stored frame by the stored
    frames' step, so a stepped build killed after its first frame, or a store of 0..24 resumed with step 3, could
    never be resumed. A selection that yields the last stored frame is tracked on as an uninterrupted build is."""
    store = room["root"] / f"b1_{stored.replace(':', '_')}"
    _ok(run_cli("build", room["log"], "--out", store, "--frames", stored, "--threads", 1, "--no-loop-closure"))
    _ok(run_cli("build", room["log"], "--out", store, "--frames", resumed, "--threads", 1, "--resume",
                "--no-loop-closure"))
    start, stop, step = (int(v) for v in resumed.split(":"))
    with FrameStore.open(store) as s:
        stored_ids = {int(i) for i in s.frame_ids}
    assert set(range(start, stop, step)) <= stored_ids, sorted(stored_ids)


def test_t21_b1_frames_lenient_skips_at_the_resume_point_do_not_stop_the_resume(room: dict) -> None:
    """Hostile trial 21 B1 (b): frames 25..27 unreadable, a lenient build of 0:28 stores 0..24; its resume with
    --lenient skips them again and tracks on to frame 28, as an uninterrupted lenient build does."""
    import shutil

    log = room["root"] / "room_bad"
    shutil.copytree(room["log"], log)
    pngs = sorted((log / "depth").glob("*.png"))
    for png in pngs[25:28]:
        png.write_bytes(b"garbage")
    store = room["root"] / "lenient"
    _ok(run_cli("build", log, "--out", store, "--frames", "0:28", "--threads", 1, "--no-loop-closure", "--lenient"))
    _ok(run_cli("build", log, "--out", store, "--frames", "0:35", "--threads", 1, "--no-loop-closure", "--lenient",
                "--resume"))
    with FrameStore.open(store) as s:
        assert [int(i) for i in s.frame_ids] == [*range(25), *range(28, 35)]


def test_t20_w1_a_resume_over_a_frame_lost_mid_store_names_the_loss(room: dict) -> None:
    """W1: a resume over a store that lost frame 12 to damage was refused as "frame 12 was not stored ... the
    selection skipped it". It was stored and lost: the refusal says so and what can be done."""
    store = _copy(room, "w1")
    with FrameStore.open(store) as s:
        ref = s._refs[12]
    with open(ref.segment, "r+b") as fh:  # one bit of frame 12's points
        fh.seek(ref.payload_offset + 64)
        byte = fh.read(1)
        fh.seek(ref.payload_offset + 64)
        fh.write(bytes([byte[0] ^ 1]))
    _ok(run_cli("recover", store))
    message = one_error(run_cli("build", room["log"], "--out", store, "--frames", "0:40", "--threads", 1, "--resume",
                                "--no-loop-closure"))
    assert "frame 12 was stored and lost to damage" in message and "another --out" in message, message
    assert "skipped" not in message, message


def test_t20_w5_a_refused_rollback_writes_nothing(room: dict) -> None:
    """W5: each `rollback --to 99` (no such revision) was refused but left an empty segment in the store."""
    store = _copy(room, "w5")
    before = json.loads((store / "store.json").read_text())["segments"]
    for target in ("99", "-1"):
        out = run_cli("rollback", store, "--to", target)
        assert out.returncode != 0 and "does not exist" in " ".join((out.stdout + out.stderr).split()), out
    assert json.loads((store / "store.json").read_text())["segments"] == before
    assert sorted(p.name for p in store.glob("segment-*")) == [s["name"] for s in before]


def test_t21_w5_a_comparison_across_revisions_placing_other_frames_says_so_and_keeps_its_cannot_judge(
        room: dict, tmp_path: Path) -> None:
    """Trial 21 W5: `diagnose --compare-revision 0` on a stand-in head placing 25 of 49 frames printed revision 0's
    smearing score with no qualifier (a before / after of 2.40 -> 0.00 mm) although revision 0 was measured over
    other frames and could not be judged either; the JSON's comparison held neither. Now the row and the JSON carry
    the compared revision's verdict and frame count, and say when the frames differ."""
    store = _copy(room, "t21w5")
    _ok(run_cli("correct", store, "--poses", room["log"] / "groundtruth.txt", "--source", "ground_truth"))
    _ok(run_cli("build", room["log"], "--out", store, "--frames", "0:50", "--threads", 1, "--resume",
                "--no-loop-closure"))
    with FrameStore.open(store) as s:
        head, ref = s.head, s._refs[int(s.frame_ids[-1])]
        assert len(s.members()) == 50
    with open(ref.segment, "r+b") as fh:  # inside the last frame: it and the resume's revision after it cut off
        fh.truncate(ref.payload_offset + 100)
    _ok(run_cli("recover", store))
    with FrameStore.open(store) as s:
        assert head in s.loss.revision_ids and len(s.members()) == 25 and len(s.members(0)) == 49
    out = _ok(run_cli("diagnose", store, "--json", tmp_path / "d.json", "--compare-revision", 0))
    data = json.loads((tmp_path / "d.json").read_text())
    cmp = data["comparison"]
    assert data["n_frames"] == 25 and cmp["n_frames"] == 49 and cmp["same_frames"] is False, cmp
    assert {"valid", "reasons", "smearing_score_valid"} <= set(cmp), cmp
    text = " ".join(out.stdout.replace("\u2502", " ").split())
    row = text.split("smearing score, revision 0")[1]
    assert "over the 49 frames revision 0 places" in row and "not a before / after of one map" in row, row
    assert ("cannot judge" in row.split(";")[0]) == (cmp["smearing_score_valid"] is False), (row, cmp)
    # revisions placing the same frames (the stand-in and revision 1): no note, the same frames
    out = _ok(run_cli("diagnose", store, "--json", tmp_path / "e.json", "--compare-revision", 1))
    assert json.loads((tmp_path / "e.json").read_text())["comparison"]["same_frames"] is True
    assert "not a before / after" not in " ".join(out.stdout.split())


def test_t21_w8_a_recovery_stopped_before_recording_its_rewrite_is_finished_with_the_true_cause(
        room: dict, tmp_path: Path) -> None:
    """Trial 21 W8: a recovery killed after replacing a truncated segment by its rewrite, before writing the
    manifest: the next one rewrote it again and recorded "size differs from the manifest" as the cause for good. It
    now finishes that rewrite, names the damaged copy's truncation, and declares the same loss as an uninterrupted
    recovery."""
    import shutil

    whole = _copy(room, "t21w8_whole")
    segment = whole / "segment-000000.mcap"
    cut = segment.stat().st_size // 2
    stopped = tmp_path / "stopped"
    shutil.copytree(whole, stopped)  # the state the kill leaves: the original manifest, the rewrite, the damaged copy
    with open(segment, "r+b") as fh:
        fh.truncate(cut)
    shutil.copy2(segment, stopped / "segment-000000.mcap.damaged")
    first = " ".join(_ok(run_cli("recover", whole)).stdout.split())
    assert "truncated" in first, first
    shutil.copy2(segment, stopped / "segment-000000.mcap")
    out = " ".join(_ok(run_cli("recover", stopped)).stdout.split())
    assert "rewritten by an earlier recovery that stopped before recording it" in out, out
    assert "size differs from the manifest" not in out and "truncated" in out, out
    with FrameStore.open(whole) as a, FrameStore.open(stopped) as b:
        assert a.loss.frame_ids == b.loss.frame_ids and a.loss.revision_ids == b.loss.revision_ids
        assert len(a.loss.frame_ids) > 0 and list(a.frame_ids) == list(b.frame_ids)
        assert "size differs" not in str(b.loss), str(b.loss)
