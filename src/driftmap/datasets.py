"""Where the shared real sensor data lives (never copied into the repository)."""

from __future__ import annotations

import os
from pathlib import Path

#: Environment variable that points at the shared data-set folder.
ENV_VAR = "DRIFTMAP_DATASETS"


def shared_datasets_dir() -> Path:
    """``$DRIFTMAP_DATASETS`` if set, else ``../shared/datasets`` next to the repository root."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser().resolve()
    repo_root = Path(__file__).resolve().parents[2]
    return (repo_root.parent / "shared" / "datasets").resolve()


def embedded_dir() -> Path:
    """The repository's own ``datasets/`` folder (synthetic data driftmap generates itself)."""
    return Path(__file__).resolve().parents[2] / "datasets"
