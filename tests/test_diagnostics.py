"""Double-wall and drift diagnostics on real data (7-Scenes redkitchen, its KinectFusion poses as the
reference) and on the synthetic log (exact ground truth): false flags, detection of injected steps and
drifts, separation accuracy, change points, trajectory metrics against evo, the CLI/JSON contract."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import spearmanr
from typer.testing import CliRunner

from driftmap import geometry
from driftmap.cli import app
from driftmap.demo import embedded_log_path
from driftmap.diagnostics import perturb
from driftmap.diagnostics.attribution import AttributionConfig, FrameAlignment, attribute, drift_rate, segment_errors
from driftmap.diagnostics.double_wall import DiagnosticCloud, DoubleWallConfig, SamplingConfig, detect_double_walls, map_entropy
from driftmap.diagnostics.report import DiagnoseConfig, diagnose_store
from driftmap.pipeline.pose_files import read_ground_truth
from driftmap.diagnostics.trajectory_metrics import trajectory_errors
from driftmap.errors import ConfigError, StoreError
from driftmap.frame import Frame, PoseEstimate, SensorKind
from driftmap.sources.synthetic import SyntheticLog
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory import Trajectory, read_euroc, read_kitti, read_tum, write_euroc, write_kitti, write_tum

STEP_FRAME_ID = 500  # after the first loop segment (frames ~216-260 are revisited at ~928-966)
GT_JUMP_FRAME_ID = 125  # the KinectFusion poses jump between frames 121 and 122 (ICP: 45 mm, 1.65 deg)


# ---------------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def synthetic() -> tuple[DiagnosticCloud, Trajectory, Trajectory, SyntheticLog]:
    log = SyntheticLog(embedded_log_path())
    cloud = DiagnosticCloud.from_frames(list(log))
    return cloud, log.ground_truth(), log.odometry(), log


def dominant_normal(cloud: DiagnosticCloud, poses: np.ndarray) -> np.ndarray:
    """The world direction most surface normals share (within 15 deg; the floor and table tops here)."""
    n = cloud.place(poses).normals_world
    candidates = n[np.random.default_rng(0).choice(len(n), 2000, replace=False)]
    support = (np.abs(candidates @ n[::10].T) >= np.cos(np.radians(15))).sum(axis=1)
    best = candidates[np.argmax(support)]
    near = n[np.abs(n @ best) >= np.cos(np.radians(15))]
    mean = (near * np.sign(near @ best)[:, None]).mean(axis=0)
    return mean / np.linalg.norm(mean)


# ---------------------------------------------------------------------------------------------- perturbations


def test_pose_perturbations_do_what_they_say() -> None:
    rng = np.random.default_rng(3)
    T = np.tile(np.eye(4), (30, 1, 1))
    T[:, :3, 3] = np.cumsum(rng.normal(scale=0.1, size=(30, 3)), axis=0)
    s = perturb.path_length_m(T)
    stepped = perturb.translation_step(T, 10, (0.01, -0.02, 0.03))
    np.testing.assert_array_equal(stepped[:10], T[:10])
    np.testing.assert_allclose(stepped[10:, :3, 3] - T[10:, :3, 3], np.tile([0.01, -0.02, 0.03], (20, 1)), atol=1e-15)
    rotated = perturb.rotation_step(T, 12, (0.0, 0.0, 2.0))
    np.testing.assert_array_equal(rotated[:12], T[:12])
    np.testing.assert_allclose(rotated[12, :3, 3], T[12, :3, 3], atol=1e-12)  # about the step frame's origin
    rel = np.linalg.inv(T[12]) @ T[20]
    np.testing.assert_allclose(np.linalg.inv(rotated[12]) @ rotated[20], rel, atol=1e-12)  # rigid after the step
    angle = np.degrees(np.arccos((np.trace(rotated[20, :3, :3] @ T[20, :3, :3].T) - 1) / 2))
    assert angle == pytest.approx(2.0, abs=1e-9)
    drift = perturb.linear_drift(T, percent_per_m=1.0, direction=(0, 1, 0))
    np.testing.assert_allclose(np.linalg.norm(drift[:, :3, 3] - T[:, :3, 3], axis=1), 0.01 * s, atol=1e-12)
    turned = perturb.linear_drift(T, deg_per_m=0.5, axis=(0, 0, 1))
    for k in (0, 15, 29):
        a = np.degrees(np.arccos(np.clip((np.trace(turned[k, :3, :3] @ T[k, :3, :3].T) - 1) / 2, -1, 1)))
        assert a == pytest.approx(0.5 * s[k], abs=1e-6)
    with pytest.raises(ConfigError):
        perturb.translation_step(T, 30, (0, 0, 1))


def test_sensor_perturbations_scale_points() -> None:
    p = np.array([[0.1, -0.2, 2.0], [1.0, 0.5, 3.0]], np.float32)
    np.testing.assert_allclose(perturb.scale_depth(p, 1.02), p * 1.02, rtol=1e-6)
    f = perturb.scale_focal(p, f_true=585.0, f_assumed=600.0)
    np.testing.assert_allclose(f[:, :2], p[:, :2] * 585.0 / 600.0, rtol=1e-6)
    np.testing.assert_array_equal(f[:, 2], p[:, 2])
    frame = Frame(frame_id=1, stamp_ns=0, sensor_name="s", sensor_kind=SensorKind.DEPTH_CAMERA, points_sensor=p,
                  pose=PoseEstimate(np.eye(4)))
    np.testing.assert_allclose(perturb.with_depth_scale_error(frame, 0.98).points_sensor, p * 0.98, rtol=1e-6)
    np.testing.assert_allclose(perturb.with_focal_error(frame, 1.01).points_sensor[:, :2], p[:, :2] / 1.01, rtol=1e-6)
    with pytest.raises(ConfigError):
        perturb.scale_depth(p, 0.0)


@pytest.mark.parametrize("fmt", ["tum", "kitti", "euroc"])  # euroc: hostile trial 16
def test_cli_perturb_matches_the_library(tmp_path: Path, fmt: str) -> None:
    rng = np.random.default_rng(1)
    T = np.tile(np.eye(4), (40, 1, 1))
    T[:, :3, 3] = np.cumsum(rng.normal(scale=0.05, size=(40, 3)), axis=0)
    stamps = (np.arange(40) * 33_333_333 + 1_000_000_000).astype(np.int64)
    src, out = tmp_path / f"in.{fmt}", tmp_path / f"out.{fmt}"
    read, write = {"tum": (read_tum, write_tum), "kitti": (read_kitti, write_kitti), "euroc": (read_euroc, write_euroc)}[fmt]
    write(src, Trajectory(stamps, T))
    T = read(src).poses  # as written (9 decimals)
    runner = CliRunner()
    result = runner.invoke(app, ["perturb", str(src), str(out), "--format", fmt, "--step-frame", "12", "--step-m", "0.02,0,-0.01",
                                 "--step-deg", "0,1,0", "--drift-percent-per-m", "0.5", "--drift-direction", "0,1,0"])
    assert result.exit_code == 0, result.output
    expected = perturb.PosePerturbation(step_index=12, step_m=(0.02, 0, -0.01), step_deg=(0, 1, 0), drift_percent_per_m=0.5,
                                        drift_direction=(0, 1, 0)).apply(T)
    got = read(out)
    np.testing.assert_allclose(got.poses, expected, atol=2e-8)
    if fmt != "kitti":
        np.testing.assert_array_equal(got.stamps_ns, stamps)
    bad = runner.invoke(app, ["perturb", str(src), str(out), "--step-m", "0.02,0,0", "--overwrite"])
    assert bad.exit_code != 0 and "--step-frame" in str(bad.exception)
    beyond = runner.invoke(app, ["perturb", str(src), str(tmp_path / "x"), "--format", fmt, "--step-frame", "40", "--step-m", "0,0,1"])
    assert beyond.exit_code != 0 and "the step frame 40 is not a row of the file (it has rows 0..39)" in str(beyond.exception)
    # an existing output is kept unless --overwrite
    again = ["perturb", str(src), str(out), "--format", fmt, "--drift-percent-per-m", "1"]
    refused = runner.invoke(app, again)
    assert refused.exit_code != 0 and "already exists (POSES_OUT)" in str(refused.exception)
    assert np.allclose(read(out).poses, got.poses)
    assert runner.invoke(app, [*again, "--overwrite"]).exit_code == 0
    assert not np.allclose(read(out).poses, got.poses)


# ---------------------------------------------------------------------------------------------- MME / MPV


def test_map_entropy_of_a_noisy_plane_matches_the_closed_form() -> None:
    """Uniform points on a plane with Gaussian noise sigma: covariance ~ diag(r^2/4, r^2/4, sigma^2) inside a
    disc of radius r, so h = 0.5 ln((2 pi e)^3 r^4 sigma^2 / 16) and MPV ~ sigma^2."""
    rng = np.random.default_rng(0)
    n, sigma = 400_000, 0.003
    pts = np.column_stack([rng.uniform(0, 4, n), rng.uniform(0, 4, n), rng.normal(0, sigma, n)])
    r = 0.1
    e = map_entropy(pts, radius_m=r, min_neighbors=10, max_neighbors=4000, max_query_points=2000)
    interior = e.n_points_used > 0
    assert interior
    expected_h = 0.5 * np.log((2 * np.pi * np.e) ** 3 * r**4 * sigma**2 / 16)
    assert e.mme == pytest.approx(expected_h, abs=0.15)  # edge points of the 4 m square make it a little lower
    assert e.mpv_m2 == pytest.approx(sigma**2, rel=0.1)


# ---------------------------------------------------------------------------------------------- exact ground truth


def test_synthetic_log_ground_truth_is_clean_and_odometry_doubles_the_loop(synthetic) -> None:
    """The synthetic room has a 2 cm board, a 5 cm door recess and glass (real two-layer geometry): with exact
    poses nothing is flagged; the drifting odometry doubles the walls where the loop closes."""
    cloud, gt, odo, _ = synthetic
    clean = detect_double_walls(cloud.place(gt.poses))
    assert clean.voxels_evaluated > 1000
    assert clean.fraction_flagged <= 0.005
    assert clean.smearing_score_m < 0.002  # the noise floor: a few millimetres at most
    drifted = detect_double_walls(cloud.place(odo.poses))
    assert drifted.fraction_flagged >= 0.03
    assert drifted.smearing_score_m > 5 * clean.smearing_score_m
    top = drifted.regions[0]
    n = len(cloud.frame_ids)
    # the loop: the first frames against the last ones
    assert top.frames_a.min() < n // 4 and top.frames_b.max() > 3 * n // 4
    assert top.separation_m > 0.02 and top.separation_sigma_m < 0.25 * top.separation_m
    assert top.stamp_ns_a[0] <= top.stamp_ns_b[0]


def test_synthetic_step_is_found_measured_and_located(synthetic) -> None:
    cloud, gt, _, _ = synthetic
    d = dominant_normal(cloud, gt.poses)
    k = 30
    for mag in (0.02, 0.04):
        step = mag * d
        poses = perturb.translation_step(gt.poses, k, step)
        placed = cloud.place(poses)
        result = detect_double_walls(placed)
        scores = perturb.evaluate_step(cloud, gt.poses, k, step, result)
        affected = sum(s.n_affected for s in scores)
        detected = sum(s.n_detected for s in scores)
        assert affected >= 20
        assert detected / affected >= (0.6 if mag == 0.02 else 0.9)
        # separation error <= max(5 mm, 15 %) for every detected group: exact poses here (measured over sampling
        # seeds 0/1: all of 700-724 groups, max error 3.0 mm)
        ok = np.concatenate([s.within_tolerance(abs_m=0.005, rel=0.15) for s in scores])
        assert ok.all(), f"{(~ok).sum()} of {ok.size} separations off by more than max(5 mm, 15 %)"
        # and unbiased: the synthetic floor lies on a voxel face (z = 0) at every voxel size; before the groups on
        # both sides of a face were joined, the face cut each layer's noise band and the median read 2.0 mm short
        # (measured now: |median| <= 0.02 mm, also with the scene moved 3.7 cm off the grid)
        err = np.concatenate([s.separation_error_m for s in scores])
        assert abs(float(np.median(err))) <= 0.0005, f"median separation error {1000 * np.median(err):+.2f} mm"
        cps = attribute(placed).change_points
        assert cps, "the step must show as a change point"
        best = max(cps, key=lambda c: c.z_score)
        assert abs(int(np.searchsorted(cloud.frame_ids, best.frame_id)) - k) <= 2
        # the split scan's step at the change point: measured 20.01-20.10 / 40.01-40.10 mm for 20 / 40 mm (seeds
        # 0/1, also with the scene moved 3.7 cm along z; 17.5 / 37.5 mm before the voxel-face join)
        assert best.jump_m == pytest.approx(mag, abs=0.0005)


# ---------------------------------------------------------------------------------------------- 7-Scenes


def test_kitchen_ground_truth_map_flags_little_and_finds_the_known_pose_jump(kitchen: FrameStore, kitchen_cloud: DiagnosticCloud) -> None:
    """Acceptance target: <= 1 % of evaluated voxels flagged on the ground-truth-posed map. The KinectFusion
    poses are not perfect: they jump by ~4.5 cm between frames 121 and 122 (pairwise ICP: 45 mm, 1.65 deg),
    which the detector must report. Measured: 0.86 % at the default sampling seed, 1.15 / 1.04 % at seeds 1 / 2."""
    placed = kitchen_cloud.place(kitchen.poses(0))
    result = detect_double_walls(placed)
    assert result.voxels_evaluated > 2000
    assert result.fraction_flagged <= 0.015
    # most flags are the reference's own errors in frames 60-170, where pairwise ICP of consecutive stored frames
    # corrects it by up to 4.3 cm / 1.66 deg (0.1-0.4 cm elsewhere; docs/diagnostics.md); the flags whose smaller
    # layer lies elsewhere: measured 0.43 % of the evaluated voxels (0.32 / 0.25 % at sampling seeds 1 / 2)
    def smaller(r):
        return r.frames_a if len(r.frames_a) < len(r.frames_b) else r.frames_b
    elsewhere = sum(r.n_voxels for r in result.regions if not 60 <= np.median(smaller(r)) <= 170)
    assert elsewhere / result.voxels_evaluated <= 0.005
    # the known jump: a doubled region with frames up to 120 on one side and from 125 on the other
    jump = [r for r in result.regions if r.frames_a.max() <= 120 and r.frames_b.min() >= GT_JUMP_FRAME_ID]
    assert jump and 0.03 <= max(r.separation_m for r in jump) <= 0.07
    attribution = attribute(placed)
    top = max(attribution.change_points, key=lambda c: c.z_score)
    assert top.frame_id == GT_JUMP_FRAME_ID
    assert 0.03 <= top.jump_m <= 0.07


def test_kitchen_detector_kernels_equal_numpy(kitchen: FrameStore, kitchen_cloud: DiagnosticCloud) -> None:
    """The compiled per-group sums and dot products the detector runs on (driftmap.kernels.groups) equal the numpy
    expressions they replaced, bit for bit, on real samples (scattered group ids, real normals and positions):
    the voxel normals' outer-product sums, the per-group position sums and the lateral cells."""
    from driftmap.diagnostics.surfaces import surface_groups, voxel_ids
    from driftmap.kernels.groups import group_outer_sums, group_row_sums, plane_cells

    placed = kitchen_cloud.place(kitchen.poses(0))
    P, Nw = placed.world_columns
    vox, _, _ = voxel_ids(P, 0.1)
    n_vox = int(vox.max()) + 1
    outer = group_outer_sums(vox, n_vox, Nw)
    sums = group_row_sums(vox, n_vox, P)
    for a in range(3):
        assert np.array_equal(sums[a], np.bincount(vox, weights=P[a], minlength=n_vox))
        for b in range(3):
            assert np.array_equal(outer[:, a, b], np.bincount(vox, weights=Nw[a] * Nw[b], minlength=n_vox))
    sg = surface_groups(placed, 0.1)
    p = P.take(sg.point_index, axis=1)
    u = np.cross(sg.normals, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(sg.normals, u)
    along, keys = plane_cells(p, sg.group, sg.normals, u, v, sg.centers_m, 0.025, 22)

    def from_center(axes: np.ndarray) -> np.ndarray:  # the numpy expression of the stop before the kernels
        t, g = np.ascontiguousarray(axes.T), sg.group
        return p[0] * t[0].take(g) + p[1] * t[1].take(g) + p[2] * t[2].take(g) - np.einsum("ij,ij->i", sg.centers_m, axes).take(g)

    assert np.array_equal(along, from_center(sg.normals)) and np.array_equal(along, sg.offset_m)
    cu = np.clip(np.floor(from_center(u) / 0.025).astype(np.int64) + 11, 0, 21)
    cv = np.clip(np.floor(from_center(v) / 0.025).astype(np.int64) + 11, 0, 21)
    assert np.array_equal(keys, (sg.group * 22 + cu) * 22 + cv)


@pytest.mark.parametrize("mag", [0.02, 0.04])
def test_kitchen_step_detection_separation_and_location(kitchen: FrameStore, kitchen_cloud: DiagnosticCloud, mag: float) -> None:
    """A translation step at frame 500 along the dominant surface normal. Affected voxels: normal within 25 deg
    of the step, seen from both sides of it, and consistent across it before the step (the reference poses
    are not everywhere: see the test above). Targets: >= 60 % detected at 2 cm, >= 90 % at 4 cm, separation
    error <= max(5 mm, 15 %), the step located within +-2 frames."""
    base = kitchen.poses(0)
    d = dominant_normal(kitchen_cloud, base)
    k = int(np.searchsorted(kitchen_cloud.frame_ids, STEP_FRAME_ID))
    step = mag * d
    placed = kitchen_cloud.place(perturb.translation_step(base, k, step))
    result = detect_double_walls(placed)
    scores = perturb.evaluate_step(kitchen_cloud, base, k, step, result)
    affected = sum(s.n_affected for s in scores)
    detected = sum(s.n_detected for s in scores)
    assert affected >= 50
    assert detected / affected >= (0.6 if mag == 0.02 else 0.9)
    # the separation target per detected group; measured over sampling seeds 0-4: 98.9-100 % of groups within
    # (one of 90 off by 12.9 mm at 4 cm, seed 1), median error 1.2 mm, max otherwise 3.8 mm. The reference poses
    # are not everywhere consistent (see above), so a few groups may miss: at most 5 %.
    within = np.concatenate([s.within_tolerance(abs_m=0.005, rel=0.15) for s in scores])
    assert within.mean() >= 0.95, f"{(~within).sum()} of {within.size} separations off by more than max(5 mm, 15 %)"
    cps = attribute(placed).change_points
    near = [c for c in cps if abs(int(np.searchsorted(kitchen_cloud.frame_ids, c.frame_id)) - k) <= 2]
    assert near, f"no change point within 2 frames of {STEP_FRAME_ID}: {[(c.frame_id, c.jump_m) for c in cps]}"
    # jump_m is the split scan's step (not a region separation): measured 20.34-20.59 mm at 2 cm, 40.20-40.36 mm
    # at 4 cm (seeds 0-4); 0.8 mm leaves ~35 % margin on the largest error (0.59 mm)
    assert near[0].jump_m == pytest.approx(mag, abs=0.0008)


@pytest.mark.slow
def test_kitchen_step_frame_is_located_along_every_dominant_normal(kitchen: FrameStore, kitchen_cloud: DiagnosticCloud) -> None:
    """2 cm steps at frames 400/500/600/700 along each of the three dominant surface normals (12 runs): the
    change-point scan puts a change point within +-2 frames of the step in at least 10 runs (measured: 12),
    with the step's size; on the unperturbed reference map it reports few change points, the known
    121/122 jump among them."""
    base = kitchen.poses(0)
    ids = kitchen_cloud.frame_ids
    reference = attribute(kitchen_cloud.place(base)).change_points
    assert GT_JUMP_FRAME_ID in [c.frame_id for c in reference]
    assert len(reference) <= 8
    located, along = 0, []
    for frame in (400, 500, 600, 700):
        k = int(np.searchsorted(ids, frame))
        for d in perturb.dominant_normals(kitchen_cloud.place(base).normals_world, 3):
            cps = attribute(kitchen_cloud.place(perturb.translation_step(base, k, 0.02 * d))).change_points
            near = [c for c in cps if abs(int(np.searchsorted(ids, c.frame_id)) - k) <= 2]
            if near:
                located += 1
                along.append(float(np.dot(near[0].step_m, d)))
    assert located >= 10, f"step located in {located} of 12 runs"
    # the step along its direction; the reference's own local inconsistencies add to it (it has a 2.5 cm
    # change point at frame 410, next to the step at 400)
    assert np.median(along) == pytest.approx(0.02, abs=0.004)
    assert all(0.01 <= a <= 0.05 for a in along), along


def test_kitchen_smearing_score_rises_with_linear_drift(kitchen: FrameStore, kitchen_cloud: DiagnosticCloud) -> None:
    """Drift of 0.25 / 0.5 / 1 / 2 %/m along random directions: the score rises strictly with the drift for
    every direction, Spearman >= 0.95 over all of them."""
    base = kitchen.poses(0)
    mags = (0.25, 0.5, 1.0, 2.0)
    x, y = [], []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        d = rng.normal(size=3)
        scores = []
        for p in mags:
            placed = kitchen_cloud.place(perturb.linear_drift(base, percent_per_m=p, direction=d / np.linalg.norm(d)))
            scores.append(detect_double_walls(placed).smearing_score_m)
        assert np.all(np.diff(scores) > 0), f"seed {seed}: {scores}"
        x += list(mags)
        y += scores
    assert spearmanr(x, y).statistic >= 0.95


def test_kitchen_smearing_score_rises_with_rotation_drift(kitchen: FrameStore, kitchen_cloud: DiagnosticCloud) -> None:
    """Rotation drift of 0.05 / 0.1 / 0.2 deg/m about random axes: the between-visit score rises with it for
    every axis (the frame-to-frame score did for 3 of 5: the reference poses' own jitter hid it)."""
    base = kitchen.poses(0)
    for seed in range(3):
        d = np.random.default_rng(seed).normal(size=3)
        scores = [detect_double_walls(kitchen_cloud.place(perturb.linear_drift(base, deg_per_m=r, axis=d / np.linalg.norm(d))))
                  .smearing_score_m for r in (0.05, 0.1, 0.2)]
        assert np.all(np.diff(scores) > 0), f"seed {seed}: {scores}"


def _visit_groups(rng: np.random.Generator, offset_m: float, jitter_m: float, gap_path_m: float) -> tuple:
    """2000 groups, each seen in two runs of 10 frames (20 points of 1 cm noise each); the runs are
    ``gap_path_m`` of travel apart and their true mean offsets differ by ``offset_m``; every frame's mean
    also jitters by ``jitter_m`` (viewpoint-dependent distortion)."""
    G, F, n, sigma = 2000, 10, 20, 0.01
    e_group = np.repeat(np.arange(G), 2 * F)
    run = np.tile(np.repeat([0, 1], F), G)
    e_path = np.tile(np.r_[np.linspace(0.0, 0.5, F), gap_path_m + np.linspace(0.0, 0.5, F)], G)
    e_mean = (run - 0.5) * offset_m + rng.normal(0.0, jitter_m, e_group.size) + rng.normal(0.0, sigma / np.sqrt(n), e_group.size)
    e_n = np.full(e_group.size, float(n))
    return e_group, e_path, e_n, e_mean, np.ones(e_group.size, bool), np.full(G, sigma**2), G


def test_visit_smearing_measures_the_disagreement_between_visits_not_the_jitter() -> None:
    """The between-visit estimator: two visits 2 cm apart give sqrt(dispersion) = 1 cm whatever the frame
    jitter within the visits (2 cm of jitter per frame: 1.01 cm; leaving the jitter in the visit means' noise
    out gives 1.10 cm); visits that agree give little (3.1 mm against 4.4 mm without the jitter term: the rest is
    the bias of a clipped square root); runs closer than the gap are one visit (NaN: nothing to compare)."""
    from driftmap.diagnostics.layers import visit_smear as _visit_smear

    rng = np.random.default_rng(0)
    for jitter in (0.0, 0.02):
        smear, visits = _visit_smear(*_visit_groups(rng, 0.02, jitter, 3.0), gap_m=1.0)
        assert np.all(visits == 2)
        assert np.sqrt(np.mean(smear**2)) == pytest.approx(0.01, rel=0.03)
    smear, _ = _visit_smear(*_visit_groups(rng, 0.0, 0.02, 3.0), gap_m=1.0)
    assert np.sqrt(np.mean(smear**2)) < 0.0037
    smear, visits = _visit_smear(*_visit_groups(rng, 0.02, 0.005, 0.8), gap_m=1.0)
    assert np.all(visits == 1) and np.all(np.isnan(smear))


def test_drift_rate_fit_separates_the_noise_floor_from_the_drift() -> None:
    """Disagreements built from the model: the fit returns the rate and the floor it was built with, and a pure
    noise floor reads as no drift (a line through the origin read it as drift)."""
    rng = np.random.default_rng(3)
    M = 200
    s = rng.uniform(1.0, 5.0, M)
    q = rng.choice([1.0, 2.0 / 3.0], (M, 2))

    def alignment(rate_m_per_m: float, rate_deg_per_m: float, floor_m: float, floor_deg: float) -> FrameAlignment:
        def vectors(norms: np.ndarray) -> np.ndarray:
            v = rng.normal(size=(M, 3))
            return v / np.linalg.norm(v, axis=1, keepdims=True) * norms[:, None]
        t = vectors(np.sqrt(floor_m**2 + q[:, 0] * (rate_m_per_m * s) ** 2))
        r = vectors(np.sqrt(floor_deg**2 + q[:, 1] * (rate_deg_per_m * s) ** 2))
        return FrameAlignment(t, r, np.full(M, 500), np.zeros(M, np.int64), np.zeros(M), np.zeros((M, 3)), q)

    d = drift_rate(alignment(0.01, 0.2, 0.012, 0.9), s, AttributionConfig())
    assert d.percent_per_m == pytest.approx(1.0, rel=1e-6) and d.deg_per_m == pytest.approx(0.2, rel=1e-6)
    assert d.noise_floor_m == pytest.approx(0.012, rel=1e-6) and d.noise_floor_deg == pytest.approx(0.9, rel=1e-6)
    assert d.n_frames == M and d.path_span_m == pytest.approx(s.max())
    still = drift_rate(alignment(0.0, 0.0, 0.012, 0.9), s, AttributionConfig())
    assert still.percent_per_m == pytest.approx(0.0, abs=1e-6) and still.deg_per_m == pytest.approx(0.0, abs=1e-6)
    # frames closer than revisit_min_path_m do not count; none left: no estimate
    none = drift_rate(alignment(0.01, 0.2, 0.0, 0.0), s * 0.1, AttributionConfig())
    assert none.percent_per_m is None and none.n_frames == 0


def test_kitchen_drift_rate_estimate_follows_the_injected_drift(kitchen: FrameStore, kitchen_cloud: DiagnosticCloud) -> None:
    base = kitchen.poses(0)
    floor = attribute(kitchen_cloud.place(base))
    assert floor.revisit_fraction > 0.5 and floor.revisit_note is None
    # the reference poses: no phantom drift from the per-frame noise floor (a line through the origin read 0.31 %/m)
    assert floor.drift.percent_per_m < 0.1
    assert 0.003 < floor.drift.noise_floor_m < 0.03 and 0.1 < floor.drift.noise_floor_deg < 3.0
    rates = []
    for p in (1.0, 2.0):
        a = attribute(kitchen_cloud.place(perturb.linear_drift(base, percent_per_m=p, direction=(0.6, 0.0, 0.8))))
        rates.append(a.drift.percent_per_m)
    assert floor.drift.percent_per_m < rates[0] < rates[1]
    # The model is approximate (docs/diagnostics.md: the floor is not the same at every path length) and reads
    # low. Measured over sampling seeds 0-4: 0.944-0.952 %/m for 1 %/m (<= 5.6 % low), 1.789-1.804 %/m for
    # 2 %/m (<= 10.6 % low). Tolerances: ~40 % margin on the largest error.
    assert rates[0] == pytest.approx(1.0, rel=0.08) and rates[1] == pytest.approx(2.0, rel=0.15)
    deg = [attribute(kitchen_cloud.place(perturb.linear_drift(base, deg_per_m=d, axis=(0.0, 1.0, 0.3)))).drift.deg_per_m
           for d in (0.2, 0.4)]
    assert floor.drift.deg_per_m < deg[0] < deg[1]
    # measured 0.170-0.200 deg/m for 0.2 deg/m (<= 15 % low; 0.200 at the default seed), 0.328-0.340 deg/m for
    # 0.4 deg/m (<= 18 % low); ~40 % margin on the largest error
    assert deg[0] == pytest.approx(0.2, rel=0.22) and deg[1] == pytest.approx(0.4, rel=0.25)
    # the first 20 frames travel less than a metre: nothing is revisited, and the result says drift is invisible
    first = kitchen_cloud.subset(np.arange(20))
    alone = attribute(first.place(base[:20]))
    assert alone.revisit_fraction == 0.0 and alone.drift.percent_per_m is None
    assert "invisible" in alone.revisit_note


# ---------------------------------------------------------------------------------------------- ground truth metrics


def test_trajectory_errors_agree_with_evo(kitchen: FrameStore) -> None:
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    gt = kitchen.poses(0)
    est = perturb.linear_drift(perturb.translation_step(gt, 60, (0.03, -0.01, 0.02)), percent_per_m=1.0, deg_per_m=0.2,
                               direction=(1, 1, 0), axis=(0.3, 1.0, 0.1))
    ours = trajectory_errors(est, gt)
    stamps = kitchen.ledger.stamps_ns / 1e9
    ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=stamps)
    e = PoseTrajectory3D(poses_se3=list(est), timestamps=stamps)
    rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
    rpe_t.process_data((ref, e))
    rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
    rpe_r.process_data((ref, e))
    e.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    assert ours.ate_rmse_m == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)
    assert ours.rpe_trans_rmse_m == pytest.approx(rpe_t.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)
    assert ours.rpe_rot_rmse_deg == pytest.approx(rpe_r.get_statistic(metrics.StatisticsType.rmse), rel=1e-5)


def test_ground_truth_of_another_trajectory_is_warned_about(caplog: pytest.LogCaptureFixture) -> None:
    import logging

    from driftmap.diagnostics.attribution import ground_truth_errors

    rng = np.random.default_rng(3)
    est = np.tile(np.eye(4), (50, 1, 1))
    est[:, :3, 3] = np.cumsum(rng.normal(scale=0.05, size=(50, 3)), axis=0)
    other = np.tile(np.eye(4), (50, 1, 1))
    other[:, :3, 3] = np.cumsum(rng.normal(scale=5.0, size=(50, 3)), axis=0)  # a car's drive, not this camera's
    with caplog.at_level(logging.WARNING, logger="driftmap.diagnostics.attribution"):
        ground_truth_errors(est, est @ geometry.make_transform(None, (0.01, 0, 0)))
        assert not caplog.records
        out = ground_truth_errors(est, other)
    assert out["ate_rmse_m"] > 10 and "is the ground truth for these frames" in caplog.records[0].getMessage()


def test_kitti_segment_errors_of_a_known_drift() -> None:
    """A straight 1 km drive with a 1 % lateral drift: every segment has 1 % translational error."""
    n = 1001
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3] = np.arange(n, dtype=np.float64)
    est = perturb.linear_drift(gt, percent_per_m=1.0, direction=(0, 1, 0))
    seg = segment_errors(est, gt)
    assert seg.n_segments.min() > 0
    np.testing.assert_allclose(seg.translation_percent, 1.0, rtol=1e-6)
    np.testing.assert_allclose(seg.rotation_deg_per_m, 0.0, atol=1e-9)


# ---------------------------------------------------------------------------------------------- CLI / JSON contract


def test_cli_diagnose_writes_the_json_contract_and_figures(kitchen: FrameStore, tmp_path: Path) -> None:
    """``driftmap diagnose STORE --revision N --gt FILE --gt-format kitti --json OUT --report DIR``."""
    store_path = tmp_path / "small"
    ids = kitchen.frame_ids[:80]
    with FrameStore.create(store_path) as small:
        for fid in ids:
            small.append(kitchen.frame(int(fid)))
        gt = small.poses(0)
        small.add_revision(dict(zip(ids.tolist(), perturb.translation_step(gt, 40, (0.0, 0.03, 0.0)))),
                           source="external_file", propagate=False)
    gt_file = tmp_path / "gt.kitti"
    full = np.tile(np.eye(4), (int(ids.max()) + 1, 1, 1))
    full[ids] = gt  # row i = frame_id i
    write_kitti(gt_file, Trajectory(np.arange(len(full)), full))
    out, report = tmp_path / "diag.json", tmp_path / "report"
    result = CliRunner().invoke(app, ["diagnose", str(store_path), "--revision", "1", "--gt", str(gt_file), "--gt-format", "kitti",
                                      "--json", str(out), "--report", str(report), "--compare-revision", "0",
                                      "--points-per-frame", "2000"])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert data["revision"] == 1 and isinstance(data["smearing_score_m"], float)
    dw = data["double_wall"]
    assert {"voxels_evaluated", "voxels_flagged", "fraction_flagged", "median_separation_m", "regions"} <= dw.keys()
    assert isinstance(dw["voxels_evaluated"], int) and isinstance(dw["voxels_flagged"], int)
    assert dw["voxels_flagged"] > 0 and isinstance(dw["median_separation_m"], float)
    region = dw["regions"][0]
    assert {"center_m", "normal", "separation_m", "separation_sigma_m", "frames_a", "frames_b", "stamp_ns_a", "stamp_ns_b"} <= region.keys()
    assert len(region["center_m"]) == 3 and len(region["normal"]) == 3
    assert all(isinstance(v, int) for v in region["frames_a"] + region["frames_b"] + region["stamp_ns_a"] + region["stamp_ns_b"])
    assert len(region["stamp_ns_a"]) == 2 and region["stamp_ns_a"][0] <= region["stamp_ns_a"][1]
    assert len(data["frames"]) == 80
    f0 = data["frames"][0]
    assert isinstance(f0["frame_id"], int) and isinstance(f0["stamp_ns"], int)
    assert isinstance(f0["disagreement_m"], float) and isinstance(f0["disagreement_deg"], float)
    assert any(c["frame_id"] == int(ids[40]) for c in data["change_points"])
    assert all(isinstance(c["frame_id"], int) and isinstance(c["jump_m"], float) for c in data["change_points"])
    assert 0.0 <= data["revisit_fraction"] <= 1.0
    assert isinstance(data["mme"], float) and isinstance(data["mpv"], float)
    tr = data["trajectory"]
    assert {"ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg"} <= tr.keys()
    assert tr["rpe_trans_rmse_m"] == pytest.approx(0.03 / np.sqrt(79), rel=1e-3)  # one 3 cm step among 79 increments
    assert data["comparison"]["revision"] == 0 and isinstance(data["comparison"]["smearing_score_m"], float)
    for name in ("double_walls_rev1.png", "frame_disagreement_rev1.png", "smearing_before_after.png",
                 "volume_top_view_rev1.png"):
        assert (report / name).stat().st_size > 10_000
    # with --report the diagnosed revision's volumetric layers: their voxels by state, all of the grid
    volume = data["volume"]
    assert volume["revision"] == 1 and volume["voxel_size_m"] == 0.02  # the depth camera's default voxel
    assert volume["occupied"] > 0 and volume["free"] > 0
    assert volume["occupied"] + volume["free"] + volume["unknown"] == volume["n_voxels"]
    # without --gt there is no trajectory block; a bad revision is one error line and exit code 1
    small_cfg = DiagnoseConfig(sampling=SamplingConfig(points_per_frame=1000))
    diagnosis = diagnose_store(FrameStore.open(store_path), 0, config=small_cfg)
    assert "trajectory" not in diagnosis.to_json()
    assert CliRunner().invoke(app, ["diagnose", str(store_path), "--revision", "7", "--json", str(out)]).exit_code != 0
    # ground truth for too few frames is refused when it is read, before the diagnosis (which is the costly part)
    few = tmp_path / "few.kitti"
    write_kitti(few, Trajectory(np.arange(2), full[:2]))
    with pytest.raises(StoreError, match=r"few.kitti: ground truth matched only 1 of the 80 stored frames.*at least 3"):
        read_ground_truth(FrameStore.open(store_path), few, "kitti")


def test_double_wall_config_rejects_nonsense() -> None:
    with pytest.raises(ValueError):
        DoubleWallConfig(voxel_sizes_m=(0.1,), min_layer_fraction=0.7)
    with pytest.raises(ValueError):
        DoubleWallConfig(cell_fraction=0.0)


def test_diagnose_report_draws_the_volume_from_above_and_only_adds_to_the_json(tmp_path: Path) -> None:
    """run_diagnose with a report folder: the diagnosed revision's volumetric layers from above (one PNG, every state
    in its colour where the layers put it), and the JSON of a run without a report plus a "volume" block."""
    from PIL import Image

    from driftmap.diagnostics.figures import STATE_TOP_VIEW_RGB, plot_state_top_view, sensor_up, top_view_layout
    from driftmap.pipeline.build import build
    from driftmap.pipeline.diagnose import run_diagnose
    from driftmap.volume import VolumeConfig

    path = tmp_path / "store"
    build(embedded_log_path(), path, poses_from_source=True, loop_closure=False, frames="0:60:2")
    with FrameStore.open(path) as store:
        plain = run_diagnose(store, tmp_path / "plain.json", points_per_frame=1000)
        report = run_diagnose(store, tmp_path / "report.json", report_dir=tmp_path / "report", points_per_frame=1000,
                              volume_config=VolumeConfig(voxel_size_m=0.05))
        poses = store.poses(0)
    without, with_report = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("plain", "report"))
    assert set(with_report) == set(without) | {"volume"}
    timings = ("seconds",)
    assert {k: v for k, v in with_report.items() if k not in (*timings, "volume")} == \
        {k: v for k, v in without.items() if k not in timings}
    assert plain.volume is None and plain.files == {}
    layers, volume = report.volume, with_report["volume"]
    stats = layers.stats()
    assert volume["revision"] == layers.revision == 0 and volume["voxel_size_m"] == 0.05
    assert (volume["occupied"], volume["free"], volume["unknown"], volume["n_voxels"]) == \
        (stats.occupied, stats.free, stats.unknown, stats.n_voxels)
    assert volume["occupied"] > 10_000 and volume["free"] > volume["occupied"]
    # the top view: its counts in the JSON, its PNG in the report folder, each cell in its state's colour
    png = report.files["volume_top_view"]
    assert png == tmp_path / "report" / "volume_top_view_rev0.png"
    redrawn = plot_state_top_view(tmp_path / "again.png", layers.state_grid(), layers.grid,
                                  up=sensor_up(poses, layers.sensor_kind), sensor_origins_m=poses[:, :3, 3])
    view = redrawn.view
    assert view.axes == (0, 1)  # the synthetic room: z up
    top = volume["top_view"]
    assert top["band_m"] == [round(v, 6) for v in view.band_m]
    assert {k: top[k] for k in ("occupied", "free", "unknown")} == view.counts()
    assert sum(view.counts().values()) == view.cells.size
    image = np.asarray(Image.open(png).convert("RGB")).astype(int)
    layout = top_view_layout(view.extent_m)
    assert image.shape == (layout.height_px, layout.width_px, 3)
    for state, rgb in STATE_TOP_VIEW_RGB.items():
        ij = np.argwhere(view.cells == state)
        assert len(ij) > 200, state
        px = layout.pixels(np.asarray(view.min_m) + (ij + 0.5) * view.voxel_size_m).astype(int)
        assert np.mean(np.all(image[px[:, 1], px[:, 0]] == rgb, axis=1)) > 0.9, state
