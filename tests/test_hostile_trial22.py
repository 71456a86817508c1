"""Hostile trial 22's findings on recovery evidence and the given-poses check, each through the command line
(docs/bad-input.md, trial 22)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

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
