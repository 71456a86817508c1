"""Shared fixtures: where the real data lives, and a hard failure in CI when it is missing."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# pytest-xdist workers (scripts/test.sh) are started with COLUMNS=80, which the CLI's console reads when it is
# imported (driftmap.cli.common: piped output is 160 columns wide unless COLUMNS says otherwise); a worker prints
# the tables a single test process prints.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.pop("COLUMNS", None)
    os.environ.pop("LINES", None)

from driftmap.datasets import ENV_VAR, shared_datasets_dir
from driftmap.diagnostics.double_wall import DiagnosticCloud
from driftmap.pipeline.build import build
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
def kitchen_session(tmp_path_factory: pytest.TempPathFactory, sevenscenes_dir: Path) -> Path:
    """A store of 50 real 7-Scenes frames (0:300:6, full resolution) built as a user builds one, with the data
    set's poses and no loop closure: a session of another place for the merge tests (hostile trial 14 F4)."""
    path = tmp_path_factory.mktemp("kitchen_session") / "kitchen"
    build(sevenscenes_dir, path, poses_from_source=True, frames="0:300:6", loop_closure=False)
    return path


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


# The suite runs on several pytest-xdist workers (scripts/test.sh). Tests that start or contact a Ray cluster
# (and one that counts Ray processes machine-wide) must not overlap: they share one group, so one worker runs
# them one after the other. Every other test is grouped by its module, so a module's session fixtures are
# built once per worker that runs it, not once per worker.
RAY_TESTS = (
    "test_batch.py::",
    "test_hostile_trial5.py::test_t5_w12_w13_batch_list_lines_are_checked_when_read",
    "test_hostile_trial6.py::test_t6_w11_w12_w14_list_lines_perturb_vectors_and_correct_sources",
    "test_hostile_trial7.py::test_t7_w1_w2_w3_w6_bounds_of_perturb_synth_diagnose_and_batch",
    "test_hostile_trial8.py::test_t8_b5_",
    "test_hostile_trial8.py::test_t8_b4_",
    "test_hostile_trial8.py::test_t9_a_ray_address_",
    "test_hostile_trial8.py::test_t17_w11_a_batch_killed_outright",
)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        module = item.nodeid.split("::", 1)[0]
        if any(pattern in item.nodeid for pattern in RAY_TESTS) or item.get_closest_marker("ray"):
            item.add_marker(pytest.mark.ray)
            item.add_marker(pytest.mark.xdist_group("ray"))
        else:
            item.add_marker(pytest.mark.xdist_group(module))
