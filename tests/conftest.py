"""Shared fixtures: where the real data lives, and a hard failure in CI when it is missing."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from driftmap.datasets import ENV_VAR, shared_datasets_dir

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
