"""The driftmap exception hierarchy.

Library code raises these; only the CLI turns them into one-line messages and exit codes.
Every error names what it is about (file, frame, field) in its message.
"""

from __future__ import annotations

import enum
from pathlib import Path
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


class NoPointsError(SourceError):
    """Every frame a new store received is empty (every depth pixel invalid, an empty scan): ``build`` removes the
    store, as one of no frame is (hostile trial 25 W6)."""


class NotACloudFile(SourceError):
    """The file has no PCD / PLY header at all (``reason`` says what was found instead)."""

    def __init__(self, file: Path, reason: str):
        super().__init__(f"{file}: {reason}")
        self.reason = reason


class TfError(SourceError):
    """A transform cannot be looked up: unknown frame, no path between two frames, or no data at a time."""


class StoreError(DriftmapError):
    """The frame store or pose ledger rejected an operation or is damaged."""


class StoreCorruptError(StoreError):
    """A store file is truncated or damaged; names the file and the byte offset."""

    def __init__(self, message: str, *, path: Path, offset: int | None):
        super().__init__(message)
        self.path = path
        self.offset = offset


class PoseGraphError(DriftmapError):
    """A pose graph is malformed (unknown key, bad information matrix, unreadable g2o file) or GTSAM failed
    on it (indeterminate linear system, an ISAM2 node with no constraint to the graph)."""


def parse_enum(kind: type[E], value: object, what: str, error: type[DriftmapError] = ConfigError) -> E:
    """``kind(value)``, or ``error`` naming ``what`` and the accepted values (instead of a bare ``ValueError``)."""
    if isinstance(value, kind):
        return value
    try:
        return kind(value)
    except ValueError:
        raise error(f"{what}: {value!r} is not one of {[m.value for m in kind]}") from None


class FrameRejectedError(StoreError):
    """The store refused a frame (or revision) before writing anything: a value it cannot store faithfully.

    ``frame_id`` and ``field`` name what was refused (``frame_id`` is None for a record that is not a frame)."""

    def __init__(self, message: str, *, frame_id: int | None, field: str):
        super().__init__(message)
        self.frame_id = frame_id
        self.field = field


class StoreIOError(StoreError, OSError):
    """An operating-system error (disk full, read-only file system, I/O error, permissions) at the store boundary.

    ``path`` (also ``filename``) is the file the store was reading or writing, ``errno`` the OS error number (None
    if unknown); the message names both and says how to continue (``driftmap build ... --resume`` /
    ``driftmap recover STORE``). It is a :class:`StoreError` and, so that code catching ``OSError`` still does,
    an ``OSError``."""

    def __init__(self, message: str, *, path: object, errno: int | None):
        super().__init__(message)
        self.path = path
        self.errno = errno
        self.filename = None if path is None else str(path)

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class OutputInsideStoreError(ConfigError):
    """An output path (an export, a report, a figure) lies inside a frame-store folder, where it could replace or
    corrupt the store's own files. ``path``: the output as given, ``flag``: the option or argument that named it,
    ``store``: the store folder it is in."""

    def __init__(self, message: str, *, path: object, flag: str, store: object):
        super().__init__(message)
        self.path = path
        self.flag = flag
        self.store = store


class MergeError(DriftmapError):
    """``driftmap merge``: no session could be connected to the first one (no consistent loop between them)."""


class EmptyExportError(DriftmapError):
    """An export has nothing to write (no frames, no points); nothing was written."""


class ExportError(DriftmapError):
    """Frames cannot be written as requested (inconsistent frames, names, stamps)."""


class EmptyStoreError(StoreError, EmptyExportError):
    """The store (or the revision asked for) has no frames, so an export or analysis has nothing to work on."""

    def __init__(self, message: str, *, store: object, revision: int | None):
        super().__init__(message)
        self.store = store
        self.revision = revision


class EmptyStoreExportError(ExportError, EmptyStoreError):
    """The store to export has no frames (an :class:`ExportError` as before, and an
    :class:`~driftmap.errors.EmptyStoreError`)."""


class OutputWriteError(DriftmapError, OSError):
    """An output file (export, figure) could not be written; ``path`` (also ``filename``) names it and nothing was
    left under that name. Also an ``OSError``, as the error it stands for."""

    def __init__(self, message: str, *, path: object, errno: int | None):
        super().__init__(message)
        self.path = path
        self.errno = errno
        self.filename = None if path is None else str(path)

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class QueryError(ConfigError):
    """An action query of ``driftmap decide`` (or its query file) is malformed or cannot be answered on this map:
    ``query_id`` names the query (None for the file itself), ``field`` the offending key (None when the whole query
    is at fault)."""

    def __init__(self, message: str, *, query_id: str | None, field: str | None = None):
        super().__init__(message)
        self.query_id = query_id
        self.field = field


class DuplicateKeyError(ValueError):
    """A JSON object naming one key twice (``json.loads`` would keep the last silently): raised while a file is
    parsed, a ``ValueError`` like every other parse error, so the readers name the file."""
