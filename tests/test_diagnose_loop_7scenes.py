"""``diagnose`` on a real loop (issue 6): 7-Scenes redkitchen, every 4th of 1000 frames, built with a drifting
but realistic odometry -- frame-to-local-map GICP whose map forgets voxels unseen for 30 frames (a sliding
window, like KISS-ICP's local map) -- then loop-closed, against the ground-truth-posed store of the same frames.

The default frame-to-map odometry keeps the whole map and closes this loop by itself (no double wall to find);
KISS-ICP drifts smoothly and leaves none at the revisit either. With the windowed map, revision 0 holds the
surface near the first pass (frames ~260-520) a second time when the camera returns (frames ~800-1000, which
include the 928-966 revisit of 216-260): ``diagnose`` must find that double wall, and the loop-closed revision
must bring the map back to the ground-truth map's level.

The loop-closed revision no longer holds that wall (measured 5.5 cm, 14-15 voxels -> at most one voxel) once the
odometry edges of the pose graph are keyframe registrations calibrated like the loops (``odometry_edges = auto``
for a windowed odometry); with the windowed odometry's own relative poses as stiff, uncalibrated edges it was
only halved.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from driftmap.diagnostics.double_wall import DiagnosticCloud
from driftmap.diagnostics.report import DiagnoseConfig, diagnose_store
from driftmap.diagnostics.trajectory_metrics import trajectory_errors
from driftmap.pipeline.build import BuildConfig, build
from driftmap.registration.loops import LoopClosureConfig
from driftmap.registration.odometry import OdometryConfig, OdometryMethod
from driftmap.store.frame_store import FrameStore

FRAMES = "0:1000:4"
# loop candidates at least 240 source frames (8 s) apart, as measured below (min_gap_frames counts the source's
# frame numbers; the default 2 s = 60 frames adds near-sequential candidates: ATE 3.14 cm but 1.14-1.25 % flagged,
# and at 120 the corrected revision keeps 2.6-2.7 cm where the loop wall was: docs/build.md). One registration
# thread: the same build in every run (two-thread builds differ by millimetres and move single flagged voxels;
# the assertions below held with margin over eight of them, docs/diagnostics.md)
WINDOWED_GICP = BuildConfig(odometry=OdometryConfig(method=OdometryMethod.GICP_MAP, gicp_map_horizon_frames=30),
                            loop_closure=LoopClosureConfig(min_gap_frames=240), num_threads=1)
FIRST_PASS_MAX_FRAME = 600  # layer A of the loop wall: seen on the first pass through the kitchen
RETURN_MIN_FRAME = 780  # layer B: seen on the way back
REVISIT = (928, 966)  # the frames that revisit 216-260 (the loop the build closes)
SAME_PLACE_M = 0.3
SAME_NORMAL_DEG = 25.0

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def diagnosed(sevenscenes_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    tmp = tmp_path_factory.mktemp("loop7")
    result = build(sevenscenes_dir, tmp / "odo", frames=FRAMES, config=WINDOWED_GICP)
    assert result.loop_revision is not None, "the loop closure must write a revision"
    build(sevenscenes_dir, tmp / "gt", frames=FRAMES, poses_from_source=True, loop_closure=False)
    out: dict = {}
    with FrameStore.open(tmp / "gt") as gt_store:
        gt_poses = gt_store.poses(0)
        out["gt"] = diagnose_store(gt_store, 0).to_json()
    with FrameStore.open(tmp / "odo") as store:
        assert np.array_equal(store.frame_ids, np.sort(store.frame_ids))
        cloud = DiagnosticCloud.from_store(store, DiagnoseConfig().sampling)  # the same samples for both revisions
        out["rev0"] = diagnose_store(store, 0, cloud=cloud).to_json()
        out["head"] = diagnose_store(store, store.head, cloud=cloud).to_json()
        out["ate_rev0_m"] = trajectory_errors(store.poses(0), gt_poses).ate_rmse_m
        out["ate_head_m"] = trajectory_errors(store.poses(store.head), gt_poses).ate_rmse_m
    return out


def _loop_wall(diagnosis: dict) -> dict | None:
    """The largest region whose earlier layer was seen on the first pass and whose later layer on the return,
    with the 928-966 revisit on the later layer."""
    best = None
    for region in diagnosis["double_wall"]["regions"]:
        a, b = np.asarray(region["frames_a"]), np.asarray(region["frames_b"])
        revisit_a = np.sum((a >= REVISIT[0]) & (a <= REVISIT[1]))
        revisit_b = np.sum((b >= REVISIT[0]) & (b <= REVISIT[1]))
        if (region["n_voxels"] >= 5 and np.median(a) < FIRST_PASS_MAX_FRAME and np.median(b) > RETURN_MIN_FRAME
                and revisit_b >= 3 and revisit_b >= 3 * revisit_a):
            if best is None or region["n_voxels"] > best["n_voxels"]:
                best = region
    return best


def _regions_at(diagnosis: dict, wall: dict) -> list[dict]:
    """The regions of ``diagnosis`` at the place and orientation of ``wall``."""
    c, n = np.asarray(wall["center_m"]), np.asarray(wall["normal"])
    return [r for r in diagnosis["double_wall"]["regions"]
            if np.linalg.norm(np.asarray(r["center_m"]) - c) <= SAME_PLACE_M
            and abs(float(np.dot(r["normal"], n))) >= np.cos(np.radians(SAME_NORMAL_DEG))]


def _separation_at(diagnosis: dict, wall: dict) -> float:
    """The largest separation of any region of ``diagnosis`` at the place and orientation of ``wall`` (0 if none)."""
    return max((r["separation_m"] for r in _regions_at(diagnosis, wall)), default=0.0)


def _voxels_at(diagnosis: dict, wall: dict) -> int:
    """Flagged voxels of ``diagnosis`` in regions at the place and orientation of ``wall``."""
    return sum(r["n_voxels"] for r in _regions_at(diagnosis, wall))


def _frac(diagnosis: dict) -> float:
    return diagnosis["double_wall"]["fraction_flagged"]


def test_odometry_only_map_shows_the_loop_double_wall(diagnosed: dict) -> None:
    wall = _loop_wall(diagnosed["rev0"])
    assert wall is not None, [(r["separation_m"], r["n_voxels"], r["stamp_ns_a"], r["stamp_ns_b"])
                              for r in diagnosed["rev0"]["double_wall"]["regions"]]
    assert wall["separation_m"] >= 0.03, wall["separation_m"]
    # the odometry-only map is doubled far more often than the ground-truth map
    assert _frac(diagnosed["rev0"]) >= 3.0 * _frac(diagnosed["gt"]), (_frac(diagnosed["rev0"]), _frac(diagnosed["gt"]))
    # the ground-truth map has no such loop wall
    assert _loop_wall(diagnosed["gt"]) is None


def test_loop_closure_brings_the_map_to_the_ground_truth_level(diagnosed: dict) -> None:
    rev0, head, gt = diagnosed["rev0"], diagnosed["head"], diagnosed["gt"]
    # issue 6: the corrected map's smearing score within 1.5x of the ground-truth-posed map's
    assert head["smearing_score_m"] <= 1.5 * gt["smearing_score_m"], (head["smearing_score_m"], gt["smearing_score_m"])
    # ... and far below the odometry-only map's: the between-visit score, measured 1.65-1.71x (6.3-6.5 mm against
    # 3.8-3.9 mm; the reference 4.0 mm)
    assert head["smearing_score_m"] <= rev0["smearing_score_m"] / 1.4, (head["smearing_score_m"],
                                                                        rev0["smearing_score_m"])
    # the frame-to-frame score, which also holds every pose estimate's jitter, still drops (measured 1.22-1.26x)
    assert head["smearing_score_frames_m"] <= rev0["smearing_score_frames_m"] / 1.1, (
        head["smearing_score_frames_m"], rev0["smearing_score_frames_m"])
    assert head["smearing_score_revisit_m"] < rev0["smearing_score_revisit_m"]
    assert _frac(head) <= 1.5 * _frac(gt), (_frac(head), _frac(gt))
    # a well-posed real map stays under the 1 % false-flag bar (measured 0.63-0.74 %; the data set's own
    # poses give 1.30 % on these frames, their inconsistencies confirmed by `diagnose --verify`)
    assert _frac(head) <= 0.01, _frac(head)
    assert _frac(head) <= 0.5 * _frac(rev0), (_frac(head), _frac(rev0))
    assert diagnosed["ate_head_m"] < 0.9 * diagnosed["ate_rev0_m"], (diagnosed["ate_head_m"], diagnosed["ate_rev0_m"])
    wall = _loop_wall(rev0)
    assert wall is not None
    after = _separation_at(head, wall)
    assert after <= 0.75 * wall["separation_m"], (after, wall["separation_m"])


def test_loop_double_wall_disappears_after_loop_closure(diagnosed: dict) -> None:
    """The 14-15 flagged voxels of the loop wall are gone; at most an isolated voxel is left at its place.

    The odometry registers with two threads, whose sums arrive in a varying order, so two builds of the same frames
    differ by up to 3 mm in pose; over eight builds the loop-closed revision left no flagged voxel at the wall's
    place three times, one 1.9 cm voxel split within the first pass (frames ~364 vs ~478) four times and one
    2.65 cm voxel of the loop split once (docs/diagnostics.md)."""
    wall = _loop_wall(diagnosed["rev0"])
    assert wall is not None
    assert _loop_wall(diagnosed["head"]) is None
    before, after = _voxels_at(diagnosed["rev0"], wall), _voxels_at(diagnosed["head"], wall)
    assert before >= 5 and after <= 1 and after <= before / 5, (before, after)


def test_drift_rate_reads_the_odometry_drift_and_its_correction(diagnosed: dict) -> None:
    """The drift-rate estimate (no ground truth) sees the windowed odometry drift and its removal by loop
    closure; the reference poses read (almost) none. Measured: 0.49 %/m, 0.00 after, 0.00 reference."""
    rev0, head, gt = (diagnosed[k]["drift_rate"] for k in ("rev0", "head", "gt"))
    assert rev0["percent_per_m"] >= 0.25, rev0
    assert head["percent_per_m"] <= 0.5 * rev0["percent_per_m"], (head, rev0)
    assert gt["percent_per_m"] <= 0.5 * rev0["percent_per_m"], (gt, rev0)
    assert head["noise_floor_m"] <= rev0["noise_floor_m"], (head, rev0)


def test_the_revisit_check_measures_the_loop_error_and_its_correction(diagnosed: dict) -> None:
    """The revisit check (docs/diagnostics.md) registers the frames that close the loop onto the first pass (its
    whole-map probes): the odometry-only map disagrees by several cm (measured 8.2 cm, 1.5 deg), the loop-closed
    revision and the ground truth by about 1 cm (1.3 and 1.5 cm). Its frame pairs (a return frame onto a short stretch
    of the first pass) read 3.1 cm on the ground truth and 3.3 cm loop-closed: single frames of 2400 samples register
    less precisely. All within the detector's range, so every figure stays a verdict."""
    checks = {k: diagnosed[k]["revisit_check"] for k in ("gt", "rev0", "head")}
    assert all(c["judged"] and not c["beyond_detector"] for c in checks.values()), checks
    assert all(diagnosed[k]["valid"] for k in checks), {k: diagnosed[k]["reasons"] for k in checks}
    probes = [p["frame_id"] for p in checks["rev0"]["probes"] if p["counted"] and p["target"] == "map"]
    assert sum(f >= RETURN_MIN_FRAME for f in probes) >= 3, probes  # frames of the return, not of the first pass
    assert checks["rev0"]["map_disagreement_m"] >= 0.04, checks["rev0"]
    assert max(checks["gt"]["map_disagreement_m"], checks["head"]["map_disagreement_m"]) <= 0.025, checks
    assert checks["rev0"]["map_disagreement_m"] > 3 * checks["head"]["map_disagreement_m"]
    assert max(checks[k]["disagreement_m"] for k in checks) <= 0.1, checks  # the pairs' noise: half the range
