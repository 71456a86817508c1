"""The driftmap exception hierarchy.

Library code raises these; only the CLI turns them into one-line messages and exit codes.
Every error names what it is about (file, frame, field) in its message.
"""

from __future__ import annotations

import enum
from typing import TypeVar

E = TypeVar("E", bound=enum.Enum)


class DriftmapError(Exception):
    """Root of every error driftmap raises on purpose."""


class ConfigError(DriftmapError):
    """A configuration value is missing, out of range or inconsistent."""


class GeometryError(DriftmapError):
    """A geometric quantity is malformed (shape, dtype, non-finite values)."""


class TransformError(GeometryError):
    """A 4x4 matrix that should be a rigid transform is not one."""


class IntrinsicsError(GeometryError):
    """Camera intrinsics are invalid or do not match the image they are used with."""


class DepthError(DriftmapError):
    """A depth image cannot be used (wrong dtype, shape, or content)."""


class DepthScaleError(DepthError):
    """The depth scale puts the scene at an implausible distance (the classic unit mistake)."""

    def __init__(self, message: str, *, depth_scale_used: float, depth_scale_suggested: float | None):
        super().__init__(message)
        self.depth_scale_used = depth_scale_used
        self.depth_scale_suggested = depth_scale_suggested


class SourceError(DriftmapError):
    """A data source (log, data-set folder, file) cannot be read."""


class StoreError(DriftmapError):
    """The frame store or pose ledger rejected an operation or is damaged."""


def parse_enum(kind: type[E], value: object, what: str, error: type[DriftmapError] = ConfigError) -> E:
    """``kind(value)``, or ``error`` naming ``what`` and the accepted values (instead of a bare ``ValueError``)."""
    if isinstance(value, kind):
        return value
    try:
        return kind(value)
    except ValueError:
        raise error(f"{what}: {value!r} is not one of {[m.value for m in kind]}") from None
