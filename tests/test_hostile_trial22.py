"""Hostile trials 22 and 23: their findings on recovery evidence and the given-poses check, each through the command
line (docs/bad-input.md, trials 22 and 23)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_run import run_cli

from driftmap.store.frame_store import FrameStore


def _ok(out):  # noqa: ANN001, ANN202 - a CompletedProcess
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-2000:])
    return out


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The trials' room (seed 3, 60 frames) and store C: frames 0:25 (odometry), revision 1 (ground truth), then
    resumed to 0:50 (its last segment holds frames 25-49 and revision 2)."""
    root = tmp_path_factory.mktemp("trial22")
    log = root / "room"
    _ok(run_cli("synth", log, "--seed", 3, "--frames", 60))
    store = root / "C"
    _ok(run_cli("build", log, "--out", store, "--frames", "0:25", "--threads", 1, "--no-loop-closure"))
    _ok(run_cli("correct", store, "--poses", log / "groundtruth.txt", "--source", "ground_truth"))
    _ok(run_cli("build", log, "--out", store, "--frames", "0:50", "--threads", 1, "--resume", "--no-loop-closure"))
    return {"root": root, "log": log, "C": store}


def _last_frames_segment(store: Path) -> tuple[str, dict]:
    manifest = json.loads((store / "store.json").read_text())
    seg = next(s for s in manifest["segments"] if s.get("frames") and s["frames"][-1][-1] == 49)
    return seg["name"], seg


def test_t22_b1_a_recovery_stopped_after_its_rewrite_was_recorded_declares_the_loss(room: dict,
                                                                                   tmp_path: Path) -> None:
    """B1: a recovery killed after it rewrote an emptied segment and recorded the rewrite (store.json: the small new
    size, the record of frames 25-49 and revision 2, ``rewritten_from_bytes`` the size before), before declaring the
    loss. The manifest check took that record as malformed against the small size, the manifest was rebuilt from the
    segments and the loss went unsaid: `info` read "build interrupted" and a rollback reused revision id 2. The record
    is judged against the size before the damage now: the loss is declared, the next id is 3."""
    name, seg = _last_frames_segment(room["C"])
    rewritten = tmp_path / "rewritten"
    shutil.copytree(room["C"], rewritten)
    (rewritten / name).write_bytes(b"")
    _ok(run_cli("recover", rewritten))  # the rewrite an uninterrupted recovery makes of the emptied segment
    stopped = tmp_path / "stopped"
    shutil.copytree(room["C"], stopped)
    shutil.copy2(rewritten / name, stopped / name)
    (stopped / f"{name}.damaged").write_bytes(b"")
    manifest = json.loads((stopped / "store.json").read_text())
    entry = next(s for s in manifest["segments"] if s["name"] == name)
    entry["rewritten_from_bytes"], entry["bytes"] = seg["bytes"], (stopped / name).stat().st_size
    (stopped / "store.json").write_text(json.dumps(manifest, indent=1))
    out = " ".join(_ok(run_cli("recover", stopped)).stdout.split())
    assert "rebuilt" not in out and "revisions [2] are lost" in out, out
    with FrameStore.open(stopped) as a, FrameStore.open(rewritten) as b:
        assert a.loss.frame_ids == b.loss.frame_ids == tuple(range(25, 50)), (a.loss, b.loss)
        assert a.loss.revision_ids == b.loss.revision_ids == (2,)
    text = " ".join(_ok(run_cli("rollback", stopped, "--to", 0)).stdout.split())
    assert "revision 3" in text and "revision 2:" not in text, text


def test_t22_b4_a_resume_across_a_gap_in_its_selection_keeps_the_scale_check(room: dict, tmp_path: Path) -> None:
    """B4: `build --resume --frames=-10:` with a pose file scaled 0.769x, after frames 0:25 stored with it (which read
    "NO: ... 1.30 times the file's"), read "given poses fit the frames: yes": the pair 24 -> 50 across the gap drove the
    fitted factor negative. No pair spans a gap in the selection now, and the scale is still named."""
    scaled = tmp_path / "scaled.txt"
    with scaled.open("w") as out:
        for line in (room["log"] / "groundtruth.txt").read_text().splitlines():
            if line.startswith("#") or not line.strip():
                out.write(line + "\n")
                continue
            v = line.split()
            v[1:4] = [repr(float(x) * 0.769) for x in v[1:4]]
            out.write(" ".join(v) + "\n")
    store = tmp_path / "G2"
    _ok(run_cli("build", room["log"], "--out", store, "--frames", "0:25", "--poses", scaled, "--threads", 1,
                "--no-loop-closure"))
    out = _ok(run_cli("build", room["log"], "--out", store, "--frames=-10:", "--poses", scaled, "--threads", 1,
                      "--no-loop-closure", "--resume"))
    check = json.loads((store / "build_summary.json").read_text())["given_poses_check"]
    assert check["consistent"] is False and 1.2 < check["step_scale"]["factor"] < 1.4, check
    pairs = [(p["frame_a"], p["frame_b"]) for p in check["pairs"]]
    assert not any(a < 25 <= 50 <= b for a, b in pairs), pairs
    assert "times the file's (a depth scale?)" in " ".join(out.stdout.replace("\u2502", " ").split())


@pytest.mark.parametrize("where", ["chunk boundary", "file start"])
def test_t22_b3_one_zeroed_disk_block_loses_only_the_chunks_it_hits(room: dict, tmp_path: Path, where: str) -> None:
    """B3: one zeroed 4 KB block across a chunk boundary lost 21 frames and revision 2 although only 2 of 28 chunks
    were damaged; the same block over the file's first bytes (magic, header, the first chunk's start) lost all 25
    frames. The scan now goes on at the next chunk whose framing and CRC check, taking the channels the lost chunk
    registered from the summary: only the frames of the chunks the block hit are lost."""
    from driftmap.store.segment_scan import scan_segment

    name, _ = _last_frames_segment(room["C"])
    store = tmp_path / "zeroed"
    shutil.copytree(room["C"], store)
    payloads = sorted(ref.payload_offset for ref in scan_segment(store / name).frames)
    # from 3000 bytes before a frame's points: the end of the chunk before it and the start of its own
    start = 0 if where == "file start" else payloads[len(payloads) // 2] - 3000
    with open(store / name, "r+b") as fh:
        fh.seek(start)
        fh.write(b"\0" * 4096)
    _ok(run_cli("recover", store))
    with FrameStore.open(store) as s:
        assert 1 <= len(s.loss.frame_ids) <= 2 and 2 not in s.loss.revision_ids, s.loss
        assert len(s) + len(s.loss.frame_ids) == 50


def test_t21_w2_true_7scenes_poses_read_no_mounting_rotation_a_turned_file_still_does(sevenscenes_dir: Path,
                                                                                    tmp_path: Path) -> None:
    """Trial 21 W2 (b): 7-Scenes 920:1000 with the data set's own poses read "NO: ... mounted turned by 6.0 deg"
    (F 13.9): every pair's step is off by a steady ~1.5 cm, which one constant offset of the steps fits better than a
    turn. A turn is named only where the offset does not fit clearly better; the same frames' poses turned 10 deg
    about the camera's y axis are still named."""
    from scipy.spatial.transform import Rotation

    true = tmp_path / "true"
    _ok(run_cli("build", sevenscenes_dir, "--out", true, "--frames", "920:1000", "--poses-from-source", "--threads", 1,
                "--no-loop-closure"))
    check = json.loads((true / "build_summary.json").read_text())["given_poses_check"]
    assert check["consistent"] is True, check["mounting_rotation"]
    mounting = check["mounting_rotation"]
    assert mounting["residual_offset_m"] < mounting["residual_after_m"], mounting  # the offset fits better
    _ok(run_cli("export", true, "--trajectory", tmp_path / "t.tum"))
    turn = Rotation.from_euler("y", 10, degrees=True)
    rows = []
    for line in (tmp_path / "t.tum").read_text().splitlines():
        if line.startswith("#"):
            continue
        v = line.split()
        q = (Rotation.from_quat([float(x) for x in v[4:8]]) * turn).as_quat()
        rows.append(" ".join(v[:4] + [repr(float(x)) for x in q]))
    (tmp_path / "turned.tum").write_text("\n".join(rows) + "\n")
    turned = tmp_path / "turned"
    out = _ok(run_cli("build", sevenscenes_dir, "--out", turned, "--frames", "920:1000", "--poses",
                      tmp_path / "turned.tum", "--threads", 1, "--no-loop-closure"))
    check = json.loads((turned / "build_summary.json").read_text())["given_poses_check"]
    assert check["consistent"] is False and check["mounting_rotation"]["explains"] is True, check["mounting_rotation"]
    assert "mounted turned by" in " ".join(out.stdout.split())


def test_t22_w6_true_poses_at_every_4th_frame_cannot_judge_rather_than_disagree(room: dict, tmp_path: Path) -> None:
    """W6: correct synthetic ground truth at every 4th frame (0.47 m and 27 deg per step, half the points on each other)
    read "NO: 3 of 4 frame pairs disagree" with the advice to take another sensor's poses: three registrations slid
    1.2-1.7 m along the room's walls keeping the file's turn. Such a pair cannot judge now: the row says so and no
    warning is given; the pairs that slid are marked in build_summary.json. (Files that are wrong still read NO:
    tests/test_hostile_trial12_poses.py, tests/test_given_poses_scale.py, tests/test_real_lidar.py.)"""
    store = tmp_path / "every4th"
    out = _ok(run_cli("build", room["log"], "--out", store, "--frames", "0:60:4", "--poses",
                      room["log"] / "groundtruth.txt", "--threads", 1, "--no-loop-closure"))
    row = " ".join(out.stdout.replace("\u2502", " ").split())
    assert "given poses fit the frames cannot judge (2 of 8 pairs decide, 2 slid along repeated structure)" in row, row
    assert "do not move the way the frames do" not in " ".join(out.stderr.split()), out.stderr[-2000:]
    check = json.loads((store / "build_summary.json").read_text())["given_poses_check"]
    assert check["consistent"] is None and any(p["slid"] for p in check["pairs"]), check
    assert all(not p["decisive"] for p in check["pairs"] if p["slid"])


@pytest.mark.parametrize("offset", [20, 27], ids=["length-field", "library-text"])
def test_t22_w5_a_flipped_bit_in_a_segment_header_is_damage_recover_rewrites(room: dict, tmp_path: Path,
                                                                              offset: int) -> None:
    """W5: a flipped bit in a segment's MCAP header (its profile string's length, or a byte of the library name made
    non-UTF-8) went unnoticed: driftmap never reads the header, `recover` called the store intact, and other MCAP
    tools could not open the segment. It is damage now: opening names the file and the header, `recover` rewrites the
    segment with every frame kept, and the mcap library reads the header of the rewrite."""
    from mcap.reader import make_reader

    name, _ = _last_frames_segment(room["C"])
    store = tmp_path / "flipped"
    shutil.copytree(room["C"], store)
    raw = bytearray((store / name).read_bytes())
    assert raw[8] == 0x01 and offset < 17 + int.from_bytes(raw[9:17], "little")  # the header record's bytes
    raw[offset] ^= 0x10 if offset == 20 else 0x80
    (store / name).write_bytes(bytes(raw))
    out = run_cli("info", store)
    assert out.returncode == 1, out.stdout
    said = " ".join(out.stderr.split())
    assert f"{name}: damaged at offset 8: damaged MCAP header record" in said and "driftmap recover" in said, said
    done = " ".join(_ok(run_cli("recover", store)).stdout.split())
    assert f"recovered {name}: rewritten" in done and "kept 25 frames" in done, done
    with open(store / name, "rb") as fh:
        header = make_reader(fh).get_header()
    assert header.profile == "" and header.library.startswith("driftmap "), header
    with FrameStore.open(store) as fixed, FrameStore.open(room["C"]) as original:
        assert not fixed.loss and list(fixed.frame_ids) == list(original.frame_ids)
        assert (fixed.poses() == original.poses()).all() and fixed.head == original.head
    assert "nothing to do" in _ok(run_cli("recover", store)).stdout


def test_t22_b1b_a_damaged_store_json_and_a_cut_segment_in_one_event_declare_the_loss(room: dict,
                                                                                       tmp_path: Path) -> None:
    """B1 (b): `store.json` damaged (its store_uuid a number) and the segment holding frames 25-49 and revision 2
    cut to about half in one event (a power cut). The manifest was rebuilt from the segments without reading the old
    one's records, so the cut-off frames and revision 2 went unsaid and a rollback reused id 2. The records the
    damaged manifest still holds are evidence now: the loss is declared and the next id is 3."""
    name, seg = _last_frames_segment(room["C"])
    store = tmp_path / "power-cut"
    shutil.copytree(room["C"], store)
    with open(store / name, "r+b") as fh:
        fh.truncate(int(seg["bytes"] * 0.52))
    manifest = json.loads((store / "store.json").read_text())
    manifest["store_uuid"] = 5
    (store / "store.json").write_text(json.dumps(manifest, indent=1))
    done = " ".join(_ok(run_cli("recover", store)).stdout.split())
    assert f"store.json: rebuilt from {len(manifest['segments'])} segments" in done and "recorded the loss" in done, done
    recorded = set(range(seg["frames"][0][0], seg["frames"][-1][-1] + 1))
    with FrameStore.open(store) as s:
        held = set(map(int, s.frame_ids))
        assert held < set(range(50)) and len(held) > 25, sorted(held)  # a part of the segment survived
        assert set(s.loss.frame_ids) == recorded - held and s.loss.revision_ids == tuple(seg["revisions"])
    out = _ok(run_cli("rollback", store, "--to", 0))
    assert f"revision {max(seg['revisions']) + 1}: poses of revision 0 restored" in out.stdout, out.stdout


def test_carry_records_takes_only_this_stores_well_formed_records(tmp_path: Path) -> None:
    """The records a rebuilt manifest takes from the one it replaces (store/manifest.py carry_records): each well
    formed entry of a manifest whose store id is this store's or damaged; none of another store's manifest."""
    from driftmap.store.manifest import carry_records

    for n in range(3):
        (tmp_path / f"segment-00000{n}.mcap").write_bytes(b"\0" * 20000)
    me = "0123456789abcdef0123456789abcdef"
    rebuilt = {"store_uuid": me, "segments": [{"name": f"segment-00000{n}.mcap", "state": "closed" if n else "open",
                                               "bytes": 20000 if n else None} for n in range(3)]}
    old = {"store_uuid": 5, "segments": [
        {"name": "segment-000000.mcap", "state": "closed", "bytes": 90000, "frames": [[0, 9]], "revisions": [1]},
        {"name": "segment-000001.mcap", "state": "closed", "bytes": 20000, "frames": [[10, 10**6]], "revisions": []},
        {"name": "segment-000002.mcap", "state": "closed", "bytes": "x", "frames": [[11, 12]], "revisions": [2]}]}
    file = tmp_path / "store.json"
    for uuid_old, expected in ((5, ["segment-000000.mcap"]), (me, ["segment-000000.mcap"]),
                               (me[:-1] + "g", ["segment-000000.mcap"]), ("f" * 32, [])):
        file.write_text(json.dumps(old | {"store_uuid": uuid_old}))
        fresh = json.loads(json.dumps(rebuilt))
        assert carry_records(file, fresh) == expected, uuid_old
        first = fresh["segments"][0]
        if expected:  # the cut segment (open, smaller than it was) keeps its old size as the evidence's yardstick
            assert first["frames"] == [[0, 9]] and first["revisions"] == [1] and first["rewritten_from_bytes"] == 90000
        assert all("frames" not in e for e in fresh["segments"][1:])  # 10**6 frames in 20 kB; a size "x"
    file.write_text("{not json")
    assert carry_records(file, json.loads(json.dumps(rebuilt))) == []


def test_t22_b2_a_recovery_stopped_with_its_size_record_lost_still_declares_a_large_cut(room: dict,
                                                                                         tmp_path: Path) -> None:
    """B2: the segment holding frames 25-49 and revision 2 cut to 13 % of its size; a recovery rewrote it and
    recorded the rewrite, then stopped before declaring the loss, and the manifest's ``rewritten_from_bytes`` was
    lost (a flipped bit in the key). Only the damaged copy's size was left as the size before the damage: a lower
    bound, against which the record of 25 frames read as implausible, and the loss went unsaid. The note recovery now
    keeps beside the copy (``NAME.before-damage.json``) holds the size: the loss is declared, the next id is 3."""
    name, seg = _last_frames_segment(room["C"])
    full = tmp_path / "full"
    shutil.copytree(room["C"], full)
    with open(full / name, "r+b") as fh:
        fh.truncate(int(seg["bytes"] * 0.13))
    _ok(run_cli("recover", full))  # what the stopped recovery had done to the segment before it stopped
    note = json.loads((full / f"{name}.before-damage.json").read_text())
    assert note["bytes"] == seg["bytes"] and note["frames"] == seg["frames"], note

    def stopped(keep_note: bool) -> Path:
        store = tmp_path / f"stopped-{keep_note}"
        shutil.copytree(room["C"], store)
        for suffix in ("", ".damaged") + ((".before-damage.json",) if keep_note else ()):
            shutil.copy2(full / f"{name}{suffix}", store / f"{name}{suffix}")
        manifest = json.loads((store / "store.json").read_text())
        entry = next(s for s in manifest["segments"] if s["name"] == name)
        entry["bytes"] = (store / name).stat().st_size  # the rewrite recorded; rewritten_from_bytes lost
        (store / "store.json").write_text(json.dumps(manifest, indent=1))
        return store

    recorded = set(range(seg["frames"][0][0], seg["frames"][-1][-1] + 1))
    without = stopped(False)  # the evidence the trial had: the record is judged against the copy's size
    out = _ok(run_cli("recover", without))
    assert "does not fit the store" in " ".join(out.stderr.split()), out.stderr
    with FrameStore.open(without) as s:
        assert not s.loss.frame_ids
    store = stopped(True)
    done = " ".join(_ok(run_cli("recover", store)).stdout.split())
    assert "recorded the loss" in done, done
    with FrameStore.open(store) as s:
        held = set(map(int, s.frame_ids))
        assert len(held) < 30 and set(s.loss.frame_ids) == recorded - held, sorted(held)
        assert s.loss.revision_ids == tuple(seg["revisions"])
    out = _ok(run_cli("rollback", store, "--to", 0))
    assert f"revision {max(seg['revisions']) + 1}: poses of revision 0 restored" in out.stdout, out.stdout


def test_t22_w1_a_resume_through_the_last_frame_with_a_far_wider_step_is_said(room: dict, tmp_path: Path) -> None:
    """W1: frames 0..24 stored; `--resume --frames 24:60:24` holds frame 24, so the gap refusal lets it through, and
    the odometry tracked frame 48 from frame 24 2.1 m off, exit 0 without a word (as an uninterrupted `0:60:24` build
    tracks its frames). It is still tracked on (trial 21 B1), but a step over 4 times the stored one is said; step 3
    after step 1 stays quiet."""
    base = tmp_path / "base"
    _ok(run_cli("build", room["log"], "--out", base, "--frames", "0:25", "--threads", 1, "--no-loop-closure"))
    said = {}
    for frames in ("24:60:24", "24:34:3"):
        store = tmp_path / frames.replace(":", "_")
        shutil.copytree(base, store)
        out = _ok(run_cli("build", room["log"], "--out", store, "--frames", frames, "--threads", 1,
                          "--no-loop-closure", "--resume"))
        said[frames] = " ".join(out.stderr.split())
    assert "--resume goes on from frame 24 to frame 48, 24 frames on, while the stored frames are 1 apart" \
        in said["24:60:24"], said["24:60:24"]
    assert "--resume goes on" not in said["24:34:3"], said["24:34:3"]


def _flip_uuid(store: Path) -> None:
    p = store / "store.json"
    m = json.loads(p.read_text())
    m["store_uuid"] = m["store_uuid"][:-1] + ("0" if m["store_uuid"][-1] != "0" else "1")
    p.write_text(json.dumps(m, indent=1))


def _flip_comma(store: Path) -> None:
    text = (store / "store.json").read_text()
    at = text.index(",", text.index("segment-000000"))
    (store / "store.json").write_text(text[:at] + "-" + text[at + 1:])


def _number_uuid(store: Path) -> None:
    p = store / "store.json"
    m = json.loads(p.read_text())
    m["store_uuid"] = 5
    p.write_text(json.dumps(m, indent=1))


@pytest.mark.parametrize("case", ["b2-stopped-after-rebuild", "b3-uuid-digit", "b4-segment-deleted",
                                  "b5-not-json", "w1-foreign"])
def test_t23_a_damaged_store_json_still_names_what_a_cut_or_gone_segment_held(room: dict, tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch,
                                                                              case: str) -> None:
    """Hostile trial 23: a damaged `store.json` beside a cut (or deleted) segment lost the cut frames and revision 2
    without a word when the damaged manifest was read as another store's (B3: one flipped hex digit of its id), did
    not parse (B5: a comma flipped), or listed a segment that is gone (B4), or when the recovery that rebuilt it was
    stopped before it declared the loss (B2: the cut segment's record was never written). Each declares the loss now
    and the next id is 3. Another store's manifest (W1: its id with a non-hex character) names nothing."""
    from driftmap.store import recovery

    name, seg = _last_frames_segment(room["C"])
    store = tmp_path / case
    shutil.copytree(room["C"], store)
    if case == "b4-segment-deleted":
        (store / name).unlink()
    else:
        with open(store / name, "r+b") as fh:
            fh.truncate(int(seg["bytes"] * 0.52))
    if case == "w1-foreign":
        other = json.loads((store / "store.json").read_text())
        other["store_uuid"] = "z" + "0123456789abcdef" * 2  # another store's id, one character damaged
        other["store_uuid"] = other["store_uuid"][:32]
        for entry in other["segments"]:
            if entry.get("frames"):
                entry["frames"] = [[a + 10**6, b + 10**6] for a, b in entry["frames"]]
        (store / "store.json").write_text(json.dumps(other, indent=1))
    else:
        {"b2-stopped-after-rebuild": _number_uuid, "b3-uuid-digit": _flip_uuid, "b4-segment-deleted": _number_uuid,
         "b5-not-json": _flip_comma}[case](store)
    if case == "b2-stopped-after-rebuild":
        def stop(*_args: object) -> None:
            raise KeyboardInterrupt  # as a SIGKILL after the rebuilt manifest was written

        with monkeypatch.context() as m:
            m.setattr(recovery._Recovery, "check_segment", stop)
            with pytest.raises(KeyboardInterrupt):
                FrameStore.recover(store)
        assert json.loads((store / "store.json").read_text()).get("rebuilt_because")
    _ok(run_cli("recover", store))
    recorded = set(range(seg["frames"][0][0], seg["frames"][-1][-1] + 1))
    with FrameStore.open(store) as s:
        held = set(map(int, s.frame_ids))
        if case == "w1-foreign":
            assert not any(f >= 10**6 for f in s.loss.frame_ids), s.loss
            return
        assert set(s.loss.frame_ids) == recorded - held and s.loss.revision_ids == tuple(seg["revisions"]), s.loss
    out = _ok(run_cli("rollback", store, "--to", 0))
    assert f"revision {max(seg['revisions']) + 1}: poses of revision 0 restored" in out.stdout, out.stdout


def test_t23_b6_a_turned_mounting_whose_pairs_slide_cannot_judge_rather_than_fit(room: dict, tmp_path: Path) -> None:
    """Hostile trial 23 B6: ground truth with the sensor mounted turned 10 deg about its y axis, at every 3rd frame
    of the room, read "yes (4 frame pairs)": 3 of its pairs slid and no longer decide, and of the 4 that did 1
    disagreed (before slides stopped deciding it read "NO: 4 of 7 frame pairs disagree"). A "yes" the slid pairs could
    overturn cannot judge now; the true file still reads yes."""
    from scipy.spatial.transform import Rotation

    rows = np.loadtxt(room["log"] / "groundtruth.txt", ndmin=2)
    turned = rows.copy()
    turned[:, 4:8] = (Rotation.from_quat(rows[:, 4:8]) * Rotation.from_euler("y", 10, degrees=True)).as_quat()
    np.savetxt(tmp_path / "turned.txt", turned, fmt="%.9f")
    said = {}
    for name, poses in (("turned", tmp_path / "turned.txt"), ("true", room["log"] / "groundtruth.txt")):
        out = _ok(run_cli("build", room["log"], "--out", tmp_path / name, "--frames", "0:60:3", "--poses", poses,
                          "--threads", 1, "--no-loop-closure"))
        said[name] = " ".join(out.stdout.replace("\u2502", " ").split())
    assert "given poses fit the frames cannot judge (" in said["turned"] and "slid along repeated structure" \
        in said["turned"], said["turned"]
    assert "given poses fit the frames yes (" in said["true"], said["true"]
