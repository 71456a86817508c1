"""The frame-source contract and the format registry.

A :class:`FrameSource` yields :class:`~driftmap.Frame` objects in time order, says how many it has when
it knows, and gives random access by index (and by time range) where the format allows. ``frame_id`` is
the data set's own frame number where it has one (7-Scenes ``frame-000640`` -> 640, KITTI ``000007.bin``
-> 7), also after slicing; otherwise the message index in the log. Ground truth, when a data set has it,
is only available through :meth:`FrameSource.ground_truth` and is never used as a frame's estimate.

Formats register themselves with :func:`register_source`; :func:`open_source` picks one from the path
and contents (or ``format=``) and names every format it tried when none fits.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from driftmap.errors import SourceError
from driftmap.frame import Frame
from driftmap.trajectory import Trajectory

logger = logging.getLogger(__name__)


def parse_frame_slice(spec: str | slice | None) -> slice | None:
    """``"START:STOP[:STEP]"`` (any part may be empty) -> ``slice``; ``None`` stays ``None``."""
    if spec is None or isinstance(spec, slice):
        return spec
    if not spec.strip():
        raise SourceError(f"--frames {spec!r}: empty; expected START:STOP[:STEP] (leave --frames out for every frame)")
    parts = spec.split(":")
    if not 1 <= len(parts) <= 3:
        raise SourceError(f"--frames {spec!r}: expected START:STOP[:STEP]")
    if any(not re.fullmatch(r"\s*[+-]?[0-9]*\s*", p) for p in parts):  # int() would take "1_0" as 10, "٣" as 3
        raise SourceError(f"--frames {spec!r}: START, STOP and STEP must be integers (digits only: ASCII 0-9)")
    try:
        values = [int(p) if p.strip() else None for p in parts]
    except ValueError as exc:
        raise SourceError(f"--frames {spec!r}: START, STOP and STEP must be integers") from exc
    if len(values) == 1:  # "N" means just frame index N
        return slice(values[0], values[0] + 1 if values[0] is not None else None)
    if len(values) == 3 and values[2] is not None and values[2] <= 0:
        raise SourceError(f"--frames {spec!r}: STEP must be positive")
    return slice(*values)


class FrameSource:
    """Base class of every source. Subclasses implement ``_count``, ``_load(i)`` and ``_frame_id(i)`` over
    their *underlying* indices; slicing, iteration, time ranges and ids are handled here.

    ``lenient``: a frame that cannot be read is skipped with a logged reason instead of raising.
    """

    format_name: str = "?"

    def __init__(self, uri: str, *, frames: str | slice | None = None, lenient: bool = False):
        self.uri = uri
        self.lenient = lenient
        self._selection: slice | None = parse_frame_slice(frames)
        self.skipped: list[tuple[int, str]] = []
        """(underlying index, reason) of frames skipped in lenient mode."""
        self._warned: set[str] = set()
        """What this source has warned about once already (later frames alike log at DEBUG)."""

    # ---- to implement
    def _count(self) -> int | None:
        raise NotImplementedError

    def _load(self, index: int) -> Frame:
        raise NotImplementedError

    def _frame_id(self, index: int) -> int:
        return index

    def _stamp_ns(self, index: int) -> int | None:
        """Stamp without loading the frame, if the format knows it cheaply (enables time ranges)."""
        return None

    # ---- provided
    def _indices(self) -> range:
        n = self._count()
        if n is None:
            raise SourceError(f"{self.uri}: the number of frames is unknown for this {self.format_name} source")
        return range(n)[self._selection] if self._selection is not None else range(n)

    def __len__(self) -> int:
        return len(self._indices())

    def frame_ids(self) -> list[int]:
        return [self._frame_id(i) for i in self._indices()]

    def stamps_ns(self) -> list[int | None]:
        """The selected frames' stamps without reading the frames (``None`` where the format knows them only
        from the frame itself)."""
        return [self._stamp_ns(i) for i in self._indices()]

    def frame(self, index: int) -> Frame:
        """The ``index``-th frame of this (possibly sliced) source."""
        indices = self._indices()
        try:
            underlying = indices[index]
        except IndexError:
            raise SourceError(f"{self.uri}: frame index {index} out of range (0..{len(indices) - 1})") from None
        return self._load(underlying)

    def __iter__(self) -> Iterator[Frame]:
        for i in self._indices():
            try:
                yield self._load(i)
            except SourceError as exc:
                if not self.lenient:
                    raise
                logger.warning("%s: skipping frame at index %d: %s", self.uri, i, exc)
                self.skipped.append((i, str(exc)))

    def between(self, start_ns: int | None = None, end_ns: int | None = None) -> Iterator[Frame]:
        """Frames with ``start_ns <= stamp_ns < end_ns`` (uses cheap stamps when the format has them)."""
        for i in self._indices():
            stamp = self._stamp_ns(i)
            if stamp is not None and ((start_ns is not None and stamp < start_ns) or (end_ns is not None and stamp >= end_ns)):
                continue
            frame = self._load(i)
            if (start_ns is None or frame.stamp_ns >= start_ns) and (end_ns is None or frame.stamp_ns < end_ns):
                yield frame

    def ground_truth(self) -> Trajectory | None:
        """Ground-truth ``T_world_sensor`` per frame (``frame_ids`` set), if the data set has it."""
        return None

    def pose_file_in_sensor_frame(self, poses_file: Path, trajectory: Trajectory) -> Trajectory:
        """The rows of a pose file given for this source's frames (``build --poses``) as ``T_world_sensor``.

        As they are by default. A data set whose own pose files belong to another sensor converts them (the
        synthetic log's depth-camera files for its LiDAR; KITTI's cam0 files have their own rule,
        :func:`driftmap.sources.kitti.kitti_rows_as_velodyne`)."""
        return trajectory

    def describe(self) -> dict[str, Any]:
        n = self._count()
        return {"format": self.format_name, "uri": self.uri, "frames": None if n is None else len(self)}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.uri!r})"


@dataclass(frozen=True)
class SourceFormat:
    name: str
    detect: Callable[[Path], bool]
    open: Callable[..., FrameSource]
    description: str
    converts_pose_files: bool = False
    """Its sources override :meth:`FrameSource.pose_file_in_sensor_frame` (worth opening for a store's pose file)."""
    origin_of: Callable[[Path], dict[str, Any] | None] | None = None
    """For a log that may have been converted from another data set (MCAP): the origin it names, read cheaply."""


AUTO_STRIDE_MIN_WIDTH_PX = 640
"""depth images this wide or wider are read at every second pixel unless a pixel stride is given (``build.pixel_stride``
None, ``convert --pixel-stride`` unset): a 640 x 480 image back-projects to 300k points, far denser than odometry,
the volume or the diagnosis use"""


def auto_pixel_stride(first: Frame | None) -> int:
    """The pixel stride a depth source is read at when none is given: 2 from :data:`AUTO_STRIDE_MIN_WIDTH_PX` on
    (the width of ``first``, the source's first frame), else 1."""
    return 2 if first is not None and first.intrinsics is not None and first.intrinsics.width >= AUTO_STRIDE_MIN_WIDTH_PX else 1


def first_depth_frame(source: FrameSource) -> Frame | None:
    """The first frame of a source that :func:`reads_depth_pixels` (what :func:`auto_pixel_stride` looks at), or None
    when it selects none (an empty ``--frames``: left to the caller to name). A data set folder reads it by index; a
    ROS log by iterating (its length may be unknown)."""
    try:
        if len(source) == 0:
            return None
    except SourceError:
        pass
    return source.frame(0) if getattr(source, "reads_depth_images", None) is None else next(iter(source), None)


def reads_depth_pixels(source: FrameSource) -> bool:
    """Whether ``source`` back-projects depth images (its opener takes ``pixel_stride`` for them): a data set folder,
    or a ROS log whose topic is a depth image (not its PointCloud2 topics)."""
    flag = getattr(source, "reads_depth_images", None)
    return bool(flag) if flag is not None else hasattr(source, "pixel_stride")


def same_file_or_copy(a: str | Path, b: str | Path) -> bool:
    """``a`` is the file ``b`` (paths resolved) or a byte-identical copy of it (a data set's own pose file
    passed from another place); ``False`` when either cannot be read."""
    a, b = Path(a), Path(b)
    try:
        return a.resolve() == b.resolve() or (a.stat().st_size == b.stat().st_size and a.read_bytes() == b.read_bytes())
    except OSError:
        return False


_REGISTRY: dict[str, SourceFormat] = {}


def accepted_options(opener: Callable[..., FrameSource]) -> frozenset[str]:
    """The keyword options an opener takes (its ``accepted_options`` or its signature's keyword-only ones)."""
    declared = getattr(opener, "accepted_options", None)
    if declared is not None:
        return frozenset(declared)
    import inspect

    target = opener.__init__ if isinstance(opener, type) else opener
    return frozenset(n for n, p in inspect.signature(target).parameters.items()
                     if p.kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD))


def register_source(name: str, detect: Callable[[Path], bool], opener: Callable[..., FrameSource], description: str,
                    *, converts_pose_files: bool = False,
                    origin_of: Callable[[Path], dict[str, Any] | None] | None = None) -> None:
    """Register a format: ``detect(path)`` must be cheap and never raise; ``opener(path, **options)``;
    ``converts_pose_files``: its sources override :meth:`FrameSource.pose_file_in_sensor_frame`; ``origin_of``:
    see :attr:`SourceFormat.origin_of`."""
    _REGISTRY[name] = SourceFormat(name, detect, opener, description, converts_pose_files, origin_of)


def registered_formats() -> dict[str, SourceFormat]:
    _load_builtin_formats()
    return dict(_REGISTRY)


def _load_builtin_formats() -> None:
    import importlib

    for module in _BUILTIN_MODULES:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as exc:  # a format module not written yet must not break the others
            if exc.name != module:
                raise


#: Modules that register formats on import (their registration runs once).
_BUILTIN_MODULES = [
    "driftmap.sources.synthetic",
    "driftmap.sources.sevenscenes",
    "driftmap.sources.tum",
    "driftmap.sources.kitti",
    "driftmap.sources.redwood",
    "driftmap.sources.cloud_folder",
    "driftmap.sources.ros",
]


def open_source(path: str | Path, format: str | None = None, **options: Any) -> FrameSource:
    """Open a data set or log; ``format`` skips detection. Options go to the format's opener
    (``frames="START:STOP[:STEP]"``, ``lenient=True``, and format-specific ones)."""
    formats = registered_formats()
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    if looks_like_store_folder(path):
        raise SourceError(f"{path}: is a driftmap frame store (what `driftmap build` writes), not a source to read "
                          f"frames from: use it directly (driftmap diagnose / correct / export {path}); to read its "
                          f"frames as a log, build from the source it was built from (its build_source.json names "
                          f"it), or write them as a ROS 2 MCAP log in Python with driftmap.export.mcap.export_mcap("
                          f"(store.frame(i) for i in store.frame_ids), 'OUT.mcap') (`export --mcap` writes a "
                          f"Foxglove view, which is not read)")
    if format is not None:
        if format not in formats:
            raise SourceError(f"unknown format {format!r}; known formats: {', '.join(sorted(formats))}")
        return formats[format].open(path, **options)
    tried = []
    for spec in formats.values():
        tried.append(spec.name)
        try:
            detected = spec.detect(path)
        except SourceError:
            raise
        except Exception as exc:  # a detector must not hide the others
            logger.debug("%s: detector %s failed: %s", path, spec.name, exc)
            continue
        if detected:  # what the opener of the detected format raises (a refused option, ...) is its answer
            logger.info("%s: detected format %s", path, spec.name)
            return spec.open(path, **options)
    raise SourceError(f"{path}: cannot tell the format{_foreign_hint(path)}; the formats driftmap reads: "
                      + "; ".join(f"{name} ({spec.description})" for name, spec in formats.items())
                      + " (none of their detectors matched; pass --format FORMAT to force one, format= in the "
                        "library)")


#: file suffixes of formats driftmap does not read, and how to get their data into one it reads
FOREIGN_FORMATS: dict[tuple[str, ...], str] = {
    (".vtk", ".vtp", ".vtu"): "VTK: save the points as PLY (ParaView's Save Data, or meshio) into a folder of "
                              "clouds, one file per scan",
    (".pcap", ".osf"): "an Ouster / Velodyne packet capture or Ouster OSF: export the scans to PCD / PLY files "
                       "(Ouster SDK, ouster-cli) into a folder, or record them as a ROS 2 bag / MCAP with the driver "
                       "(ouster-ros, velodyne)",
    (".las", ".laz"): "LAS / LAZ: convert each scan to PLY or PCD, e.g. `pdal translate scan.las scan.ply`, into a "
                      "folder of clouds",
    (".e57",): "E57: convert each scan to PLY or PCD (PDAL, CloudCompare) into a folder of clouds",
    (".xyz", ".pts", ".xyzn", ".xyzrgb"): "a text point file: convert it to PCD / PLY (Open3D reads .xyz / .pts) "
                                          "into a folder of clouds",
    (".h5", ".hdf5", ".npy", ".npz"): "an array file: write each scan as PCD / PLY into a folder of clouds",
    (".pcd", ".ply"): "one point-cloud file: the cloud_folder format reads a folder of them; pass the folder that "
                      "holds it (or put it in one)",
    (".bin",): "one binary scan: the kitti format reads a sequence folder with velodyne/NNNNNN.bin; pass that folder",
    (".db3",): "a rosbag2 storage file: pass the rosbag2 folder with its metadata.yaml",
    (".png", ".jpg", ".jpeg"): "one image: the depth-image formats read data-set folders (7scenes, tum, redwood)",
    (".mcap", ".bag"): "a log that does not start with its format's magic bytes: a damaged or foreign file",
}


_STORE_MANIFEST = "store.json"
_STORE_FORMAT = "driftmap-store"
_STORE_SEGMENT = re.compile(r"segment-[0-9]{6,}\.mcap")
_MAX_MANIFEST_BYTES = 64 << 20


def looks_like_store_folder(path: Path) -> bool:
    """Whether ``path`` is a driftmap frame store folder: its ``store.json`` says ``"format": "driftmap-store"``, or
    it holds segment files (``segment-NNNNNN.mcap``: a store whose manifest is damaged or gone), as
    :func:`driftmap.store.guards.is_store_folder` decides. A small local check: the sources sit below the store in
    the layers (.importlinter) and do not import it."""
    try:
        if not path.is_dir():
            return False
        manifest = path / _STORE_MANIFEST
        if manifest.is_file() and manifest.stat().st_size <= _MAX_MANIFEST_BYTES:
            try:
                data = json.loads(manifest.read_bytes())
            except (ValueError, RecursionError):
                data = None
            if isinstance(data, dict) and data.get("format") == _STORE_FORMAT:
                return True
        with os.scandir(path) as entries:
            return any(_STORE_SEGMENT.fullmatch(entry.name) for entry in entries)
    except OSError:
        return False


def _foreign_hint(path: Path) -> str:
    """``" (it looks like X: how to convert it)"`` for a file (or a folder of files) of a recognisable format
    driftmap does not read; ``""`` otherwise."""
    suffixes: list[str] = []
    try:
        if path.is_dir():
            with os.scandir(path) as it:
                suffixes = [Path(e.name).suffix.lower() for e, _ in zip(it, range(10_000)) if e.is_file()]
        else:
            if path.is_file() and path.stat().st_size == 0:
                return " (the file is empty: 0 bytes)"
            suffixes = [path.suffix.lower()]
    except OSError:
        return ""
    for known, hint in FOREIGN_FORMATS.items():
        n = sum(s in known for s in suffixes)
        if n:
            return f" (it holds {n} {'/'.join(known)} file(s): {hint})" if path.is_dir() else f" (it looks like {hint})"
    return ""

