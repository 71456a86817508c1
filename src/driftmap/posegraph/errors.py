"""The pose graph's error type, :class:`driftmap.errors.PoseGraphError` (defined with every other driftmap error in
:mod:`driftmap.errors`; importable from here as before, the same class)."""

from __future__ import annotations

from driftmap.errors import PoseGraphError

__all__ = ["PoseGraphError"]
