"""The pose graph's error type (the lowest module of the package: every other one raises it)."""

from __future__ import annotations

from driftmap.errors import DriftmapError

__all__ = ["PoseGraphError"]


class PoseGraphError(DriftmapError):
    """A pose graph is malformed (unknown key, bad information matrix, unreadable g2o file) or GTSAM failed
    on it (indeterminate linear system, an ISAM2 node with no constraint to the graph)."""
