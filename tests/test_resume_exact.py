"""``driftmap build --resume`` after a SIGKILL continues our odometry exactly: the resumed store equals an
uninterrupted build (the trial's case: a 60-frame synthetic log, seed 3, ``--threads 1 --no-loop-closure``, killed
half way). The resume re-tracks the stored frames (``pipeline/build.py``: ``_Poser._retrack``) instead of re-seeding
the odometry from the last ten, which had left the resumed poses up to 13 cm from the uninterrupted ones."""

from __future__ import annotations

import json
import logging
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from cli_run import run_cli

from driftmap import geometry
from driftmap.errors import StoreError
from driftmap.pipeline.build import BuildConfig, build
from driftmap.registration.odometry import OdometryConfig
from driftmap.store.frame_store import FrameStore

N_FRAMES = 60
BUILD_FLAGS = ("--threads", "1", "--no-loop-closure")


@pytest.fixture(scope="module")
def trial_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The hostile trial's log: ``driftmap synth LOG --lidar --seed 3 --frames 60`` (a depth camera and a LiDAR)."""
    log = tmp_path_factory.mktemp("resume-exact") / "log"
    made = run_cli("synth", log, "--lidar", "--seed", 3, "--frames", N_FRAMES)
    assert made.returncode == 0, made.stderr
    return log


def _start_build(log: Path, out: Path, *flags: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "driftmap.cli", "build", str(log), "--out", str(out), *BUILD_FLAGS,
                             *flags], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _kill_after(proc: subprocess.Popen, out: Path, n_frames: int, timeout_s: float = 120) -> int:
    """SIGKILL ``proc`` once its store holds ``n_frames`` frames (as tests/test_build.py's killed build); the number
    of frames the killed build left."""
    deadline = time.time() + timeout_s
    seen = None
    while time.time() < deadline and proc.poll() is None:
        if (out / "store.json").exists():
            try:
                with FrameStore.open(out) as store:
                    seen = len(store)
            except StoreError:  # caught between writes: the next look sees it
                pass
            if seen is not None and seen >= n_frames:
                break
        time.sleep(0.01)
    status = proc.poll()
    proc.kill()
    proc.wait()
    if status is not None or seen is None or seen < n_frames:
        pytest.fail(f"the build was to be killed after {n_frames} stored frames (seen: {seen}; child "
                    f"{'exited with ' + str(status) if status is not None else 'still running'})", pytrace=False)
    with FrameStore.open(out) as store:
        return len(store)


def _stored(out: Path) -> tuple[list[int], np.ndarray, list[dict]]:
    with FrameStore.open(out) as store:
        ids, poses = [int(i) for i in store.frame_ids], np.array(store.poses(0))
    tracking = json.loads((out / "build_summary.json").read_text())["tracking"]["per_frame"]
    return ids, poses, tracking


@pytest.mark.parametrize("sensor", ["lidar", "depth"])
def test_a_killed_build_resumes_to_the_uninterrupted_poses(trial_log: Path, tmp_path: Path, sensor: str) -> None:
    """Killed after 30 stored frames, then ``--resume``: every pose equals the uninterrupted build's to the bit
    (KISS-ICP on the LiDAR, frame-to-map GICP on the depth camera), and so do the tracking records; the run says it
    re-tracked the stored frames."""
    flags = ("--sensor", sensor)
    fresh, resumed = tmp_path / "fresh", tmp_path / "resumed"
    uninterrupted = _start_build(trial_log, fresh, *flags)  # alongside the build that is killed
    n_killed = _kill_after(_start_build(trial_log, resumed, *flags), resumed, 30)
    assert uninterrupted.wait(timeout=300) == 0, uninterrupted.stderr.read()
    assert 30 <= n_killed < N_FRAMES
    assert not (resumed / "build_summary.json").exists(), "killed before the build recorded its settings"

    done = run_cli("build", trial_log, "--out", resumed, *BUILD_FLAGS, *flags, "--resume")
    assert done.returncode == 0, done.stderr
    assert "time: re-tracking" in done.stdout and f"{N_FRAMES - n_killed} / {N_FRAMES}" in done.stdout
    assert "re-tracking the" not in done.stderr, "no disagreement with one thread"

    fresh_ids, fresh_poses, fresh_tracking = _stored(fresh)
    ids, poses, tracking = _stored(resumed)
    assert ids == fresh_ids == list(range(N_FRAMES))
    assert float(np.abs(poses - fresh_poses).max()) <= 1e-9
    np.testing.assert_array_equal(poses, fresh_poses)  # exactly: one thread repeats every registration to the bit
    assert tracking == fresh_tracking



def test_a_build_in_two_parts_equals_one_build(trial_log: Path, tmp_path: Path) -> None:
    """Depth camera (its odometry settings do not depend on the frames): ``--frames 0:25`` and then all frames with
    ``--resume`` give the poses of one build of all frames, to the bit; a resume with nothing new re-tracks nothing."""
    once, parts = tmp_path / "once", tmp_path / "parts"
    config = BuildConfig(num_threads=1)
    build(trial_log, once, config=config, loop_closure=False, frames="0:40")
    build(trial_log, parts, config=config, loop_closure=False, frames="0:25")
    result = build(trial_log, parts, config=config, loop_closure=False, frames="0:40", resume=True)
    assert (result.n_frames_new, result.n_frames) == (15, 40) and "re-tracking" in result.seconds_per_stage
    np.testing.assert_array_equal(_stored(parts)[1], _stored(once)[1])
    again = build(trial_log, parts, config=config, loop_closure=False, frames="0:40", resume=True)
    assert again.n_frames_new == 0 and "re-tracking" not in again.seconds_per_stage
    np.testing.assert_array_equal(_stored(parts)[1], _stored(once)[1])


def test_a_resume_that_re_tracks_otherwise_keeps_the_stored_poses(trial_log: Path, tmp_path: Path,
                                                                  caplog: pytest.LogCaptureFixture) -> None:
    """When the re-tracked poses disagree with the stored ones (here: the recorded odometry settings edited, as a store
    from another version or a multi-threaded build would be), the resume says so with the largest difference, keeps
    the stored poses, and places the new frames by the odometry's motion from the last stored frame's stored pose (no
    jump of the difference where the build resumed)."""
    store, other = tmp_path / "s", tmp_path / "other"
    config = BuildConfig(num_threads=1)
    build(trial_log, store, config=config, loop_closure=False, frames="0:20")
    summary_file = store / "build_summary.json"
    summary = json.loads(summary_file.read_text())
    summary["odometry_config"]["gicp_map_voxel_m"] *= 1.2
    summary_file.write_text(json.dumps(summary))
    edited = OdometryConfig.model_validate(summary["odometry_config"])
    build(trial_log, other, config=BuildConfig(num_threads=1, odometry=edited), loop_closure=False, frames="0:30")
    before = _stored(store)[1]
    with caplog.at_level(logging.WARNING, logger="driftmap.pipeline.build"):
        build(trial_log, store, config=config, loop_closure=False, frames="0:30", resume=True)
    messages = [r.getMessage() for r in caplog.records]
    warned = [m for m in messages if "re-tracking the 20 stored frames gave poses up to" in m]
    assert warned and "stored poses are kept" in warned[0], messages
    poses, edited_poses = _stored(store)[1], _stored(other)[1]
    np.testing.assert_array_equal(poses[:20], before)
    assert np.abs(edited_poses[19] - before[19]).max() > 0.01, "the edited settings re-track elsewhere"
    # from frame 19 on, the motion is the edited odometry's (which the re-tracking rebuilt), from the stored pose
    for k in range(20, 30):
        np.testing.assert_allclose(geometry.invert(poses[19]) @ poses[k],
                                   geometry.invert(edited_poses[19]) @ edited_poses[k], atol=1e-9)
