"""Shared fixtures: where the real data lives, and a hard failure in CI when it is missing."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from driftmap.datasets import ENV_VAR, shared_datasets_dir
from driftmap.diagnostics.double_wall import DiagnosticCloud
from driftmap.sources.sevenscenes import SevenScenes
from driftmap.store.frame_store import FrameStore

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def _require(path: Path) -> Path:
    if path.exists():
        return path
    message = f"shared data not found at {path} (set {ENV_VAR} to the shared datasets folder)"
    if IN_CI:
        pytest.fail(message + "; in CI the data must be present", pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    return _require(shared_datasets_dir())


@pytest.fixture(scope="session")
def sevenscenes_dir(datasets_dir: Path) -> Path:
    return _require(datasets_dir / "7scenes-redkitchen")


@pytest.fixture(scope="session")
def kitti_dir(datasets_dir: Path) -> Path:
    return _require(datasets_dir / "kitti-00-frames0-15")


@pytest.fixture(scope="session")
def icl_dir(datasets_dir: Path) -> Path:
    return _require(datasets_dir / "icl-nuim-livingroom1-5frames")


@pytest.fixture(scope="session")
def balm_dir(datasets_dir: Path) -> Path:
    """80 real solid-state (Livox-like) LiDAR scans with their LIO poses (balm-lidar-0-79)."""
    return _require(datasets_dir / "balm-lidar-0-79")


@pytest.fixture(scope="session")
def kitchen(tmp_path_factory: pytest.TempPathFactory, sevenscenes_dir: Path) -> FrameStore:
    """7-Scenes redkitchen, 200 frames (every 5th of 1000, 160x120 pixels) with the data set's poses as
    revision 0; built once for the diagnostics and verification tests (read only)."""
    path = tmp_path_factory.mktemp("kitchen") / "kitchen"
    source = SevenScenes(sevenscenes_dir, pixel_stride=4, poses_from_ground_truth=True, frames="0:1000:5")
    with FrameStore.create(path) as store:
        for frame in source:
            store.append(frame)
    return FrameStore.open(path)


@pytest.fixture(scope="session")
def kitchen_cloud(kitchen: FrameStore) -> DiagnosticCloud:
    """The default diagnostic samples of ``kitchen``."""
    return DiagnosticCloud.from_store(kitchen)


@pytest.fixture(scope="session")
def room10(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 10-frame synthetic room log (seed 3) and a store of it placed with its ground truth (no loop closure):
    built once for the hostile-trial tests, which read them only (a test that writes copies them first)."""
    from driftmap.pipeline.build import build
    from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log

    root = tmp_path_factory.mktemp("room10")
    log = generate_synthetic_log(root / "log", SyntheticLogConfig(n_frames=10, seed=3))
    build(log, root / "gt", poses_file=log / "groundtruth.txt", loop_closure=False)
    return {"root": root, "log": log, "gt": root / "gt"}
