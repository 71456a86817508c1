"""The perturbation sweep of the decisions (issue 25): each assumption perturbs what it names and nothing else, and
the flipped fraction grows with the magnitude (the full sweep, all assumptions and two seeds, is
``scripts/decision_sweep.py``; its table is in docs/decisions.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from driftmap.decisions import load_queries
from driftmap.decisions.sweep import ASSUMPTIONS, perturbed_frames, sweep
from driftmap.diagnostics import perturb
from driftmap.errors import ConfigError
from driftmap.pipeline.build import build
from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log
from driftmap.store.frame_store import FrameStore

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "datasets" / "synthetic-loop"
QUERIES = ROOT / "datasets" / "synthetic-loop-queries.json"


@pytest.fixture(scope="module")
def gt_store(tmp_path_factory: pytest.TempPathFactory) -> FrameStore:
    out = tmp_path_factory.mktemp("sweep") / "gt"
    build(LOG, out, poses_file=LOG / "groundtruth.txt", loop_closure=False)
    return FrameStore.open(out)


def _frames(store: FrameStore, name: str, magnitude: float, seed: int = 0) -> list:
    return list(perturbed_frames(store, 0, name, magnitude, seed))


def test_point_perturbations_change_the_points_as_named(gt_store: FrameStore) -> None:
    fid = int(gt_store.frame_ids[3])
    original = gt_store.frame(fid).points_sensor.astype(np.float64)
    row = 3
    kept = _frames(gt_store, "dropout_random", 0.7)[row].points_sensor
    assert abs(len(kept) / len(original) - 0.3) < 0.02
    assert len(np.unique(np.vstack([kept, original.astype(np.float32)]), axis=0)) == len(original)  # a subset
    for name, m in (("dropout_structured", 0.5), ("occlusion", 0.25)):
        left = len(_frames(gt_store, name, m)[row].points_sensor) / len(original)
        assert 0.35 < left < 0.9, (name, left)
    scaled = _frames(gt_store, "depth_scale", 2.0)[row].points_sensor.astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(scaled, axis=1), 1.02 * np.linalg.norm(original, axis=1), rtol=1e-5)
    turned = _frames(gt_store, "extrinsic_rotation", 1.0)[row].points_sensor.astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(turned, axis=1), np.linalg.norm(original, axis=1), rtol=1e-5)
    cos = np.sum(turned * original, axis=1) / np.linalg.norm(turned, axis=1) ** 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() <= 1.0 + 1e-3  # no ray turned by more than 1 deg
    focal = _frames(gt_store, "focal_length", 4.0)[row].points_sensor.astype(np.float64)
    np.testing.assert_allclose(focal[:, 2], original[:, 2], rtol=1e-6)  # depth kept, x and y / 1.04
    np.testing.assert_allclose(focal[:, :2], original[:, :2] / 1.04, rtol=1e-5, atol=1e-7)
    for frame in _frames(gt_store, "depth_scale", 2.0):  # the poses are untouched
        np.testing.assert_array_equal(frame.T_world_sensor, gt_store.poses(0)[list(gt_store.frame_ids).index(frame.frame_id)])


def test_pose_perturbations_move_only_the_poses(gt_store: FrameStore) -> None:
    poses = gt_store.poses(0)
    drifted = np.stack([f.T_world_sensor for f in _frames(gt_store, "pose_drift", 2.0, seed=3)])
    offset = np.linalg.norm(drifted[:, :3, 3] - poses[:, :3, 3], axis=1)
    np.testing.assert_allclose(offset, 0.02 * perturb.path_length_m(poses), atol=1e-9)
    stepped = np.stack([f.T_world_sensor for f in _frames(gt_store, "motion", 4.0)])
    moved = np.linalg.norm(stepped[:, :3, 3] - poses[:, :3, 3], axis=1)
    half = len(poses) // 2
    assert np.all(moved[:half] < 1e-12) and np.allclose(moved[half:], 0.04)
    frame = _frames(gt_store, "motion", 4.0)[half]
    np.testing.assert_array_equal(frame.points_sensor, gt_store.frame(frame.frame_id).points_sensor)


def test_the_same_seed_draws_the_same_perturbation(gt_store: FrameStore) -> None:
    a, b, c = (_frames(gt_store, "dropout_random", 0.5, seed=s)[0].points_sensor for s in (4, 4, 5))
    np.testing.assert_array_equal(a, b)
    assert len(a) != len(c) or not np.array_equal(a, c)


def test_bad_sweeps_are_clear_errors(gt_store: FrameStore, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="unknown assumption 'gravity'"):
        _frames(gt_store, "gravity", 1.0)
    with pytest.raises(ConfigError, match="dropout_random: a fraction below 1"):
        _frames(gt_store, "dropout_random", 1.0)
    with pytest.raises(ConfigError, match="magnitude must be a finite number"):
        _frames(gt_store, "depth_scale", float("nan"))
    with pytest.raises(ConfigError, match="unknown assumption"):
        sweep(gt_store, QUERIES, tmp_path / "w", assumptions=["pose_drift", "gravity"])
    lidar = generate_synthetic_log(tmp_path / "lidar", SyntheticLogConfig(n_frames=3, lidar=True))
    store_path = tmp_path / "lidar.store"
    build(lidar, store_path, source_options={"sensor": "lidar"}, poses_file=lidar / "groundtruth.txt",
          loop_closure=False)
    with pytest.raises(ConfigError, match="occlusion masks image pixels; frame 0 has no camera intrinsics"):
        _frames(FrameStore.open(store_path), "occlusion", 0.2)
    assert not (tmp_path / "w").exists() or not any((tmp_path / "w").iterdir())


@pytest.mark.slow
def test_the_flipped_fraction_grows_with_the_magnitude(gt_store: FrameStore, tmp_path: Path) -> None:
    """A pose slip of 1, 4 and 16 cm at the middle frame (decisions on the 333 generated queries)."""
    result = sweep(gt_store, load_queries(QUERIES), tmp_path / "work", assumptions=["motion"],
                   magnitudes={"motion": [1.0, 4.0, 16.0]}, seeds=[0])
    fractions = [r.flipped_fraction for r in result.runs]
    assert fractions == sorted(fractions) and fractions[-1] > fractions[0] + 0.02, fractions
    assert result.spearman()["motion"] == pytest.approx(1.0)
    assert not any((tmp_path / "work").iterdir())  # each perturbed copy removed after its decisions
    assert set(ASSUMPTIONS) >= {"dropout_random", "dropout_structured", "occlusion", "depth_scale", "pose_drift",
                                "motion", "focal_length", "extrinsic_rotation"}
