"""KITTI odometry sequences (Velodyne HDL-64E scans).

Layout of a sequence folder (``sequences/NN/`` in the official archive)::

    velodyne/NNNNNN.bin   float32 x, y, z, intensity per point, Velodyne frame (metres)
    calib.txt             line "Tr: 12 numbers" = T_cam0_velo (3x4 row-major), Velodyne -> left camera cam0
    times.txt             seconds since the start of the sequence, row k = frame k
    poses.txt             ground truth T_world_cam0 (KITTI 3x4 rows), row k = frame k; also looked up as
                          ../../poses/NN.txt (the official layout) or given with poses=

``frame_id`` is the number in the ``.bin`` name. The point layout (``x, y, z, intensity`` or, as some conversions
write, ``x, y, z`` only) is decided once for the whole folder (:func:`decide_point_layout`), never per file; a
layout given with ``--point-layout`` (``point_layout=``) is checked against the data the same way, and refused when
the scans read as scans only in the other layout (:func:`check_given_layout`).
Ground truth is converted to the Velodyne frame:
``T_world_velo = inv(Tr) @ T_cam0 @ Tr`` (so the world is the Velodyne frame of frame 0). Frames carry no
estimate (``PoseSource.NONE``) unless ``poses_from_ground_truth=True``. Points are the raw scan (no range
filtering; points with a NaN / inf coordinate, exactly at the sensor origin (no return) or farther than
:data:`~driftmap.sources.point_fields.MAX_POINT_RANGE_M` are dropped and counted, and a scan left without a point
is refused: :func:`~driftmap.sources.point_fields.measured_points`); intensity is a per-point attribute.
``times.txt`` must step like a sensor (seconds: :func:`~driftmap.sources.stamps.check_seconds_period`).
Hidden and temporary files in ``velodyne/`` are not scans (:func:`~driftmap.sources.cloud_folder.is_ignored_file`).
"""

from __future__ import annotations

import enum
import logging
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import ConfigError, SourceError, TransformError, parse_enum
from driftmap.frame import Frame, PointAttributes, PoseSource, Provenance, SensorKind
from driftmap.sources.base import FrameSource, register_source, same_file_or_copy
from driftmap.sources.cloud_folder import numbered_files, opener_for, pose_or_none
from driftmap.sources.point_fields import checked_intensity, measured_points
from driftmap.sources.stamps import (
    check_increasing_stamps,
    check_seconds_period,
    nominal_stamp_ns,
    read_pose_file,
    read_times,
)
from driftmap.trajectory import Trajectory, read_kitti, read_lines

logger = logging.getLogger(__name__)

NOMINAL_PERIOD_NS = 100_000_000
"""Nominal 10 Hz (the Velodyne spin rate; real times.txt steps are ~0.1037 s), used only without times.txt."""
POINT_BYTES = 16  # float32 x, y, z, intensity


class PointLayout(str, enum.Enum):
    """What a point of a ``.bin`` scan holds: float32 ``x, y, z, intensity`` (KITTI) or ``x, y, z``."""

    AUTO = "auto"
    XYZI = "xyzi"
    XYZ = "xyz"

    @property
    def columns(self) -> int:
        return 4 if self is PointLayout.XYZI else 3

    @property
    def point_bytes(self) -> int:
        return 4 * self.columns

    @property
    def spelled(self) -> str:
        return "float32 x, y, z, intensity" if self is PointLayout.XYZI else "float32 x, y, z"


LAYOUT_SAMPLE_BYTES = 1 << 20
"""How much of a scan the layout check reads (a multiple of 48 bytes: whole points in either layout)."""
MIN_LAYOUT_POINTS = 32
"""A scan sample shorter than this many points cannot tell the layouts apart."""
ABSURD_COORDINATE_M = 1e5
"""No LiDAR measures this far: coordinates beyond it mean the bytes are read in the wrong layout."""


def _layout_misfit(sample: bytes, layout: PointLayout) -> float | None:
    """How badly the bytes read as ``layout`` fit a LiDAR scan: the median step between consecutive points over
    their median range (about 0.004 for a KITTI scan in its own layout, about 1.4 in the other one, where every
    "point" mixes the axes of two points); ``inf`` when over 1 % of the coordinates are NaN / inf or absurd;
    ``None`` for a sample too short to tell. Points at the origin (no return: zeros, the same in either layout)
    tell nothing and are not looked at."""
    values = np.frombuffer(sample, dtype="<f4")
    points = values[: len(values) // layout.columns * layout.columns].reshape(-1, layout.columns)[:, :3]
    if len(points) < MIN_LAYOUT_POINTS:
        return None
    xyz = points.astype(np.float64)
    xyz = xyz[xyz.any(axis=1)]  # not the zeros of "no return" points (NaN counts as non-zero: looked at below)
    if len(xyz) < MIN_LAYOUT_POINTS:
        return None
    sane = np.isfinite(xyz).all(axis=1) & (np.abs(xyz) < ABSURD_COORDINATE_M).all(axis=1)
    if np.mean(sane) < 0.99:
        return float("inf")
    xyz = xyz[sane]
    ranges = np.linalg.norm(xyz, axis=1)
    scale = float(np.median(ranges))
    if len(xyz) < MIN_LAYOUT_POINTS or scale <= 0:
        return None
    return float(np.median(np.linalg.norm(np.diff(xyz, axis=0), axis=1))) / scale


def _layout_from_data(files: list[Path]) -> tuple[PointLayout | None, str]:
    """The layout the data of (up to three of) ``files`` fits clearly better, or ``None`` and why not."""
    picks = sorted({files[0], files[len(files) // 2], files[-1]})
    votes: list[tuple[PointLayout | None, str]] = []
    abstained: list[str] = []  # files too short to tell: the others decide
    for file in picks:
        try:
            with file.open("rb") as fh:
                sample = fh.read(LAYOUT_SAMPLE_BYTES)
        except OSError:
            continue
        sample = sample[: len(sample) // 48 * 48]
        misfit = {lay: _layout_misfit(sample, lay) for lay in (PointLayout.XYZI, PointLayout.XYZ)}
        if any(m is None for m in misfit.values()):
            abstained.append(f"{file.name} holds too few points (off the sensor origin) to tell")
            continue
        best, other = sorted(misfit, key=lambda lay: misfit[lay])  # type: ignore[arg-type]
        clear = misfit[best] < 0.5 and misfit[other] >= 4 * misfit[best]  # type: ignore[operator]
        votes.append((best if clear else None, f"{file.name} reads about as well either way" if not clear else
                      f"{file.name} reads as a scan only as {best.value}"))
    chosen = {v for v, _ in votes}
    said = "; ".join([*(w for _, w in votes), *abstained])
    if len(chosen) == 1 and None not in chosen:
        return chosen.pop(), said
    return None, said or "no scan could be read"


def decide_point_layout(files: list[Path], folder: Path) -> tuple[PointLayout, str]:
    """One layout for every scan of a folder, and why: from the files' sizes (a size that is a multiple of 16 but
    not of 12 can only be x, y, z, intensity, and the other way round; the layout more files fit wins, and the
    others raise when read), and, when every size is a multiple of both (48), from the data
    (:func:`_layout_misfit`). :class:`SourceError` asking for ``--point-layout`` (``point_layout=``) when neither
    settles it."""
    sizes = {}
    for file in files:
        try:
            sizes[file] = file.stat().st_size
        except OSError:
            continue
    fits = {lay: [f for f, n in sizes.items() if n > 0 and n % lay.point_bytes == 0]
            for lay in (PointLayout.XYZI, PointLayout.XYZ)}
    n16, n12 = len(fits[PointLayout.XYZI]), len(fits[PointLayout.XYZ])
    if n16 == n12 == 0:
        return PointLayout.XYZI, "no scan size fits either layout (the KITTI layout is assumed; every scan raises)"
    if n16 != n12 or set(fits[PointLayout.XYZI]) != set(fits[PointLayout.XYZ]):
        if n16 == n12:
            raise SourceError(f"{folder}: {n16} scans have a size that only float32 x, y, z, intensity (16 bytes a "
                              f"point) fits and {n12} one that only x, y, z (12 bytes) fits: the folder mixes layouts "
                              f"or holds damaged scans; give the layout with --point-layout xyzi or xyz "
                              f"(in the library: point_layout='xyzi' or 'xyz')")
        layout = PointLayout.XYZI if n16 > n12 else PointLayout.XYZ
        return layout, f"the sizes of {max(n16, n12)} of {len(sizes)} scans are multiples of {layout.point_bytes} bytes"
    layout, why = _layout_from_data(fits[PointLayout.XYZI])
    if layout is None:
        raise SourceError(f"{folder}: cannot tell whether the scans are float32 x, y, z, intensity (16 bytes a point) "
                          f"or x, y, z (12 bytes): every size is a multiple of both, and {why}; give the layout "
                          f"with --point-layout xyzi or xyz (in the library: point_layout='xyzi' or 'xyz')")
    return layout, f"every size fits both layouts; {why}"


def check_given_layout(layout: PointLayout, files: list[Path], folder: Path) -> str:
    """Why the scans are read in ``layout``, given with ``--point-layout`` (``point_layout=``): the data check
    ``auto`` uses (:func:`_layout_from_data`, on whole 48-byte blocks: it reads in either layout whatever the
    sizes); :class:`SourceError` naming the folder when the scans read as LiDAR scans only in the other layout (x, y, z
    read as x, y, z, intensity, or intensities read as coordinates), before any scan is read as a frame. Data that
    cannot tell is read as given."""
    given = f"given with --point-layout {layout.value} (point_layout='{layout.value}' in the library)"
    if not files:
        return given
    seen, why = _layout_from_data(files)
    if seen is None or seen is layout:
        return given
    raise SourceError(f"{folder}: --point-layout {layout.value} (point_layout='{layout.value}' in the library) reads "
                      f"the scans as {layout.spelled}, but the data looks like {seen.value} ({seen.spelled}): {why}; "
                      f"read as {layout.value}, "
                      + ("the intensities would be read as coordinates" if seen is PointLayout.XYZI else
                         "every fourth coordinate would be read as an intensity")
                      + f"; give --point-layout {seen.value}, or auto to let the data decide")


def read_calib_tr(file: Path) -> NDArray[np.float64]:
    """``T_cam0_velo`` from the ``Tr:`` line of a KITTI odometry ``calib.txt``."""
    if not file.is_file():
        raise SourceError(f"{file}: calibration not found (needed for the Velodyne ground truth)")
    lines = read_lines(file, "calibration")  # SourceError naming the file (and line) for unreadable / non-UTF-8 text
    for lineno, line in enumerate(lines, start=1):
        key, _, rest = line.partition(":")
        if key.strip() != "Tr":
            continue
        try:
            values = [float(v) for v in rest.split()]
        except ValueError as exc:
            raise SourceError(f"{file}:{lineno}: field Tr: not a number ({exc})") from exc
        if len(values) != 12:
            raise SourceError(f"{file}:{lineno}: field Tr: expected 12 numbers (3x4 row-major), got {len(values)}")
        T = np.eye(4)
        T[:3, :] = np.reshape(values, (3, 4))
        try:
            return geometry.as_rigid(T, f"{file}:{lineno} field Tr")
        except TransformError as exc:
            raise SourceError(str(exc)) from exc
    raise SourceError(f"{file}: no 'Tr:' line (Velodyne-to-cam0 transform)")


def velo_poses_from_cam0(T_world_cam0: NDArray[np.float64], T_cam0_velo: NDArray[np.float64]) -> NDArray[np.float64]:
    """KITTI ground truth in the Velodyne frame: ``inv(Tr) @ T_cam0 @ Tr`` for a (N, 4, 4) stack."""
    return geometry.invert(T_cam0_velo) @ np.asarray(T_world_cam0) @ T_cam0_velo


def default_poses_file(sequence_dir: str | Path) -> Path | None:
    """A sequence folder's own ground truth: ``poses.txt`` in it, else the official ``../../poses/NN.txt``."""
    folder = Path(sequence_dir)
    resolved = folder.resolve()
    for candidate in (folder / "poses.txt", resolved.parent.parent / "poses" / f"{resolved.name}.txt"):
        if candidate.is_file():
            return candidate
    return None


# ------------------------------------------------------------------------------ the frame of a KITTI pose file


class KittiFrame(str, enum.Enum):
    """The frame the rows of a KITTI pose file are in, for frames that are Velodyne scans.

    ``auto``: the KITTI data set's own ``poses.txt`` (cam0 ground truth) is converted, any other file is taken
    as Velodyne poses (with a warning); ``velodyne``: rows are ``T_world_velo`` as they are; ``cam0``: rows are
    ``T_world_cam0`` and are converted with ``calib.txt`` ``Tr``.
    """

    AUTO = "auto"
    VELODYNE = "velodyne"
    CAM0 = "cam0"


@dataclass(frozen=True)
class KittiOrigin:
    """The KITTI odometry sequence a source's or a store's frames come from.

    ``poses_file`` (the sequence's own cam0 ground truth) and ``calib_file`` are ``None`` when absent (e.g.
    the data set is no longer at the path the store recorded).
    """

    sequence_dir: Path
    poses_file: Path | None
    calib_file: Path | None

    @classmethod
    def of_folder(cls, sequence_dir: str | Path, poses_file: str | Path | None = None) -> KittiOrigin:
        folder = Path(sequence_dir)
        own = Path(poses_file) if poses_file is not None else default_poses_file(folder)
        calib = folder / "calib.txt"
        return cls(folder, own, calib if calib.is_file() else None)

    def is_own_poses_file(self, file: str | Path) -> bool:
        """``file`` is this sequence's ground-truth file: the same file (paths resolved) or a byte-identical copy."""
        return self.poses_file is not None and same_file_or_copy(file, self.poses_file)


_SCAN_NAME = re.compile(r"^[0-9]+\.bin$")


def kitti_origin_of_source(source: object) -> KittiOrigin | None:
    """The sequence a :class:`KittiOdometry` source reads, or that an MCAP ``driftmap convert`` wrote from one
    was read from (its ``origin``, when the folder is still there); ``None`` for any other source."""
    if isinstance(source, KittiOdometry):
        return KittiOrigin(source.path, source.poses_file,
                           source.path / "calib.txt" if (source.path / "calib.txt").is_file() else None)
    export_origin = getattr(source, "export_origin", None)
    return kitti_origin_named(export_origin() if callable(export_origin) else None, getattr(source, "uri", source))


def kitti_origin_named(origin: dict[str, Any] | None, what: object) -> KittiOrigin | None:
    """The KITTI sequence an origin record (``{"format", "path", ...}``) names, if it is still there."""
    if not origin or origin.get("format") != "kitti":
        return None
    folder = Path(origin["path"])
    if not (folder / "velodyne").is_dir():
        logger.warning("%s comes from the KITTI sequence %s, which is no longer there: its calib.txt and poses.txt "
                       "cannot be recognised (--kitti-frame cam0 --calib FILE converts cam0 poses)", what, folder)
        return None
    return KittiOrigin.of_folder(folder)


def kitti_origin_of_frame_infos(infos: list[dict[str, Any]]) -> KittiOrigin | None:
    """The KITTI sequence stored frames come from, from their metadata (:meth:`FrameStore.frame_info`): every
    frame a ``velodyne`` scan whose provenance is ``<sequence>/velodyne/NNNNNN.bin`` of one sequence folder.
    ``None`` for frames from anything else (or from several sequences)."""
    folders = set()
    for info in infos:
        prov = info.get("provenance")
        if info.get("sensor_frame") != "velodyne" or not prov or not prov.get("source_uri"):
            return None
        scan = Path(prov["source_uri"])
        if scan.parent.name != "velodyne" or not _SCAN_NAME.match(scan.name):
            return None
        folders.add(scan.parent.parent)
    if len(folders) != 1:
        return None
    return KittiOrigin.of_folder(folders.pop())


def kitti_rows_as_velodyne(poses_file: str | Path, T_world_x: NDArray[np.float64],
                           origin: KittiOrigin | None | Callable[[], KittiOrigin | None], *,
                           kitti_frame: KittiFrame | str = KittiFrame.AUTO,
                           calib_file: str | Path | None = None, lidar_frames: bool = False) -> NDArray[np.float64]:
    """The rows of a KITTI pose file as ``T_world_velo`` for frames that are Velodyne scans of ``origin``.

    The one place that decides the frame of a KITTI file (``build --poses``, ``correct --format kitti`` and
    ``diagnose --gt-format kitti`` all call it). ``kitti_frame`` (see :class:`KittiFrame`):

    - ``auto``: when ``origin`` is a KITTI sequence and ``poses_file`` is its own ground truth (cam0), the rows
      are converted, ``inv(Tr) @ T_cam0 @ Tr``, and an info line is logged; another file with a KITTI
      ``origin`` is taken as Velodyne poses, with a warning when its rows move like a camera's
      (:func:`camera_like_motion`); without an ``origin`` rows are returned as they are, with the same warning
      when ``lidar_frames`` (the frames are LiDAR scans whose data set is not known, e.g. read from an MCAP that
      ``driftmap convert`` wrote from a KITTI sequence).
    - ``velodyne``: rows are returned as they are.
    - ``cam0``: rows are converted with ``calib_file`` or else the origin's ``calib.txt``; neither ->
      :class:`ConfigError` naming ``poses_file``.
    """
    frame = parse_enum(KittiFrame, kitti_frame, f"{poses_file}: KITTI frame")
    rows = np.asarray(T_world_x, dtype=np.float64)
    if callable(origin):  # looked up only when the rule needs it (not for velodyne, nor for cam0 with a calib)
        origin = None if frame is KittiFrame.VELODYNE or (frame is KittiFrame.CAM0 and calib_file) else origin()
    calib = Path(calib_file) if calib_file is not None else (origin.calib_file if origin is not None else None)
    if frame is KittiFrame.VELODYNE:
        if calib_file is not None:
            logger.warning("%s: calibration %s not used (KITTI frame velodyne: rows are T_world_velo)", poses_file,
                           calib_file)
        logger.info("%s: KITTI rows taken as Velodyne poses T_world_velo (KITTI frame velodyne)", poses_file)
        return rows
    if frame is KittiFrame.CAM0:
        if calib is None:
            where = (f"{origin.sequence_dir / 'calib.txt'} not found" if origin is not None
                     else "the store's frames do not come from a KITTI data set")
            raise ConfigError(f"{poses_file}: KITTI frame cam0 needs the calibration (calib.txt, line Tr) to convert "
                              f"the rows to the Velodyne frame, but {where}; give the calibration file (--calib)")
        logger.info("%s: KITTI rows are cam0 poses: converted to the Velodyne frame with %s Tr", poses_file, calib)
        return velo_poses_from_cam0(rows, read_calib_tr(calib))
    own = origin is not None and origin.is_own_poses_file(poses_file)
    if not own and calib_file is not None:
        logger.warning("%s: calibration %s not used: the rows are taken as Velodyne poses (KITTI frame auto); "
                       "use --kitti-frame cam0 to convert them", poses_file, calib_file)
    if origin is None:
        if lidar_frames:
            _warn_if_camera_like(poses_file, rows, "--kitti-frame cam0 --calib CALIB (the KITTI sequence of the frames, "
                                 "and so its calib.txt, is not known)")
        return rows
    if own:
        if calib is None:
            raise ConfigError(f"{poses_file} is the cam0 ground truth of {origin.sequence_dir}, but its calibration "
                              f"{origin.sequence_dir / 'calib.txt'} is not found; give the calibration file (--calib) "
                              f"or say the rows are Velodyne poses (--kitti-frame velodyne)")
        logger.info("%s is the data set's cam0 ground truth: rows converted to the Velodyne frame with %s Tr",
                    poses_file, calib)
        return velo_poses_from_cam0(rows, read_calib_tr(calib))
    if not _warn_if_camera_like(poses_file, rows, "--kitti-frame cam0 (or --poses-from-source for build)"):
        logger.info("%s: KITTI rows taken as Velodyne poses T_world_velo (KITTI frame auto; their motion is not a "
                    "camera's); --kitti-frame cam0 converts cam0 poses", poses_file)
    return rows


def _warn_if_camera_like(poses_file: str | Path, rows: NDArray[np.float64], advice: str) -> bool:
    """Warn (and return True) when KITTI rows about to be taken as Velodyne poses move like a camera's."""
    share = camera_like_motion(rows)
    if share is None or share < CAMERA_LIKE_SHARE:
        return False
    logger.warning("%s: KITTI rows are taken as Velodyne poses T_world_velo, but they move along their own z axis "
                   "(a camera's forward axis; a Velodyne's is x) in %.0f %% of the steps: they look like cam0 poses, "
                   "which must be converted (inv(Tr) @ T_cam0 @ Tr): use %s", poses_file, 100 * share, advice)
    return True


CAMERA_LIKE_SHARE = 0.6
"""Rows whose steps mostly run along their own z axis look like camera poses (optical axis z forward)."""


def camera_like_motion(T_world_x: NDArray[np.float64], min_step_m: float = 0.05) -> float | None:
    """The share of the steps (of at least ``min_step_m``) between consecutive poses that run mostly along the
    pose's own z axis (|z| > 0.8 of the step, in the earlier pose's frame); ``None`` without such steps.

    A car-mounted camera moves along its optical axis (z); a Velodyne along its x axis: a KITTI file whose rows
    move along z on a store of Velodyne scans is, most likely, cam0 poses that were not converted."""
    T = np.asarray(T_world_x, dtype=np.float64).reshape(-1, 4, 4)
    if len(T) < 2:
        return None
    rel = geometry.invert(T[:-1]) @ T[1:]
    t = rel[:, :3, 3]
    norm = np.linalg.norm(t, axis=1)
    moving = norm >= min_step_m
    if not moving.any():
        return None
    return float(np.mean(np.abs(t[moving, 2]) > 0.8 * norm[moving]))


class KittiOdometry(FrameSource):
    """A KITTI odometry sequence folder (see the module docstring).

    Options:
        poses: ground-truth pose file (KITTI format, cam0); default ``poses.txt`` in the folder or
            ``../../poses/<folder name>.txt``.
        poses_from_ground_truth: frames carry the Velodyne ground truth (``PoseSource.GROUND_TRUTH``).
        point_layout: ``"auto"`` (default: decided for the whole folder by :func:`decide_point_layout`),
            ``"xyzi"`` (float32 x, y, z, intensity: KITTI) or ``"xyz"``.

    Bad input: a ``.bin`` whose size is not a multiple of the folder's point size (16 bytes for KITTI's
    x, y, z, intensity) raises :class:`SourceError` naming the file (lenient: the frame is skipped); a pose file with fewer rows than frames raises naming the file and
    the first frame without a pose (lenient: a warning, those frames have no ground truth); ``times.txt``
    must have a row per frame and increasing stamps (lenient: offending frames are skipped).
    """

    format_name = "kitti"

    def __init__(
        self,
        path: str | Path,
        *,
        poses: str | Path | None = None,
        poses_from_ground_truth: bool = False,
        point_layout: PointLayout | str = PointLayout.AUTO,
        frames: str | slice | None = None,
        lenient: bool = False,
    ):
        super().__init__(str(path), frames=frames, lenient=lenient)
        self.path = Path(path)
        self.poses_from_ground_truth = poses_from_ground_truth
        self._warned_non_finite: set[int] = set()
        self.ignored_files: list[Path] = []
        """Hidden and temporary files among the scans, not read (:func:`~driftmap.sources.cloud_folder.is_ignored_file`)."""
        scans = numbered_files(self.path / "velodyne", "KITTI Velodyne scans", pattern="*.bin", lenient=lenient,
                               ignored=self.ignored_files)
        ids = [n for n, _ in scans]
        gaps = sorted(set(range(ids[0], ids[-1] + 1)) - set(ids)) if ids else []
        if gaps:  # as 7-Scenes says of its depth images: the frames keep their file numbers, the missing are none
            shown = ", ".join(f"{n:06d}.bin" for n in gaps[:5]) + (", ..." if len(gaps) > 5 else "")
            logger.warning("%s: velodyne/ has no scan %s (%d missing between %06d.bin and %06d.bin): they are not "
                           "frames; the others keep their file numbers as frame ids", self.path, shown, len(gaps),
                           ids[0], ids[-1])
        layout = parse_enum(PointLayout, point_layout, f"{self.path}: point_layout", SourceError)
        if layout is PointLayout.AUTO:
            layout, why = decide_point_layout([f for _, f in scans], self.path / "velodyne")
            logger.info("%s: scans read as %s (%s)", self.path, layout.spelled, why)
        else:
            why = check_given_layout(layout, [f for _, f in scans], self.path / "velodyne")
        self.point_layout: PointLayout = layout
        self.point_layout_reason = why

        # stamps: times.txt row k = frame k
        times_file = self.path / "times.txt"
        if times_file.is_file():
            times = read_times(times_file)
            check_seconds_period(times, times_file, f"its {len(times)} rows")
            stamp_of = {}
            for n in ids:
                if n < len(times):
                    stamp_of[n] = times[n]
                    continue
                reason = f"{times_file}: {len(times)} rows, no stamp for frame {n}"
                if not lenient:
                    raise SourceError(reason)
                logger.warning("%s (frame skipped)", reason)
                self.skipped.append((ids.index(n), reason))
            scans = [(n, f) for n, f in scans if n in stamp_of]
            stamps = [stamp_of[n] for n, _ in scans]
            stamps_what = str(times_file)
        else:
            logger.warning("%s: no times.txt; stamps are frame_id * %d ns (nominal 10 Hz)", self.path,
                           NOMINAL_PERIOD_NS)
            stamps = [nominal_stamp_ns(n, NOMINAL_PERIOD_NS, str(f)) for n, f in scans]
            stamps_what = str(self.path)
        keep = check_increasing_stamps(stamps, [n for n, _ in scans], stamps_what, lenient=lenient,
                                       skipped=self.skipped)
        self._entries: list[tuple[int, Path, int]] = [(scans[k][0], scans[k][1], stamps[k]) for k in keep]

        # ground truth: cam0 poses -> Velodyne frame
        self.poses_file = self._find_poses(poses)
        self._gt: dict[int, NDArray[np.float64]] = {}
        self.T_cam0_velo: NDArray[np.float64] | None = None
        if self.poses_file is not None:
            try:
                # the scans' poses come from it: every problem is an error; otherwise it is extra: a warning
                self._load_ground_truth(lenient=lenient or not poses_from_ground_truth)
            except SourceError as exc:
                if poses_from_ground_truth:
                    raise
                logger.warning("%s; the scans are read without ground truth", exc)
                self.poses_file, self._gt, self.T_cam0_velo = None, {}, None
        elif poses_from_ground_truth:
            raise SourceError(f"{self.path}: no ground-truth poses (poses.txt) to place the scans with (build "
                              f"--poses-from-source; poses_from_ground_truth=True in the library): give the file with "
                              f"--poses FILE instead (poses= in the library)")
        elif (self.path / "calib.txt").is_file():
            self.T_cam0_velo = read_calib_tr(self.path / "calib.txt")

    def _load_ground_truth(self, *, lenient: bool) -> None:
        """``poses_file`` (cam0) as ``T_world_velo`` per frame, converted with ``calib.txt`` ``Tr``."""
        assert self.poses_file is not None
        cam0 = read_pose_file(read_kitti, self.poses_file)
        self.T_cam0_velo = read_calib_tr(self.path / "calib.txt")
        velo = velo_poses_from_cam0(cam0.poses, self.T_cam0_velo)
        for n, _, _ in self._entries:
            if n < len(velo):
                try:  # KITTI rows have 7 digits: project onto SO(3) like every stored pose
                    self._gt[n] = geometry.as_rigid(velo[n], f"{self.poses_file} row {n + 1} (frame {n})")
                except TransformError as exc:
                    raise SourceError(str(exc)) from exc
        missing = [n for n, _, _ in self._entries if n >= len(velo)]
        if missing:
            reason = (f"{self.poses_file}: {len(velo)} pose rows for {len(self._entries)} frames; the first frame "
                      f"without a pose is frame {missing[0]}")
            if not lenient:
                raise SourceError(reason)
            logger.warning("%s (%d frames have no ground truth)", reason, len(missing))

    def _find_poses(self, poses: str | Path | None) -> Path | None:
        if poses is not None:
            if not Path(poses).is_file():
                raise SourceError(f"{poses}: ground-truth pose file not found")
            return Path(poses)
        return default_poses_file(self.path)

    def _count(self) -> int:
        return len(self._entries)

    def _frame_id(self, index: int) -> int:
        return self._entries[index][0]

    def _stamp_ns(self, index: int) -> int:
        return self._entries[index][2]

    def read_scan(self, index: int) -> NDArray[np.float32]:
        """The raw (N, 4) float32 scan ``x, y, z, intensity`` at ``index`` ((N, 3) ``x, y, z`` for a folder of
        that layout)."""
        frame_id, file, _ = self._entries[index]
        layout = self.point_layout
        try:
            size = file.stat().st_size
        except FileNotFoundError:
            raise SourceError(f"{file}: scan of frame {frame_id} not found") from None
        if size == 0 or size % layout.point_bytes:
            raise SourceError(
                f"{file}: size {size} bytes of frame {frame_id} is not a positive multiple of {layout.point_bytes} "
                f"({layout.spelled} per point, the layout of every scan of this folder: {self.point_layout_reason}): "
                f"truncated or not a KITTI scan"
            )
        try:
            raw = np.fromfile(file, dtype="<f4")
        except (OSError, ValueError) as exc:
            raise SourceError(f"{file}: cannot read scan of frame {frame_id} ({exc})") from exc
        if size % 48 == 0:  # the size fits the other layout too: the data must not read as a scan only in that one
            self._check_scan_layout(raw[: LAYOUT_SAMPLE_BYTES // 4].tobytes(), file, frame_id)
        return raw.reshape(-1, layout.columns)

    def _check_scan_layout(self, sample: bytes, file: Path, frame_id: int) -> None:
        """:class:`SourceError` when a scan whose size fits both layouts reads as a LiDAR scan only in the other one
        (an x, y, z file among x, y, z, intensity scans, read as the folder's layout, would be stored scrambled)."""
        layout = self.point_layout
        other = PointLayout.XYZ if layout is PointLayout.XYZI else PointLayout.XYZI
        own_misfit, other_misfit = _layout_misfit(sample, layout), _layout_misfit(sample, other)
        if own_misfit is None or other_misfit is None:
            return
        if other_misfit < 0.5 and own_misfit >= 4 * other_misfit:
            raise SourceError(
                f"{file}: frame {frame_id} reads as a LiDAR scan only as {other.value} ({other.spelled}: neighbouring "
                f"points {other_misfit:.3g} of the range apart, {own_misfit:.3g} as {layout.value}), but the folder's "
                f"scans are {layout.value} ({self.point_layout_reason}): the folder mixes layouts; convert the scan, "
                f"remove it, or skip it with --lenient (--point-layout cannot read both)")

    def _load(self, index: int) -> Frame:
        frame_id, file, stamp_ns = self._entries[index]
        if self.poses_from_ground_truth:
            if frame_id not in self._gt:
                raise SourceError(f"{self.poses_file}: no ground-truth pose for frame {frame_id}")
            pose = pose_or_none(self._gt[frame_id], PoseSource.GROUND_TRUTH)
        else:
            pose = pose_or_none(None, PoseSource.NONE)
        scan = self.read_scan(index)
        finite = np.isfinite(scan[:, :3]).all(axis=1)
        if not finite.all() and frame_id not in self._warned_non_finite:  # dropped and counted, as the cloud-folder
            self._warned_non_finite.add(frame_id)  # and PointCloud2 readers; said once (a pre-pass reads it too)
            logger.warning("%s: frame %d: %d of %d points have a NaN or infinite coordinate and are left out",
                           file, frame_id, int(len(scan) - finite.sum()), len(scan))
        keep = measured_points(scan[:, :3], f"{file} (frame {frame_id})")  # also: no return, too far, none left
        if keep is not None:
            scan = scan[keep]
        if len(scan) < MIN_SCAN_POINTS:
            logger.warning("%s: frame %d has only %d points (a full HDL-64 scan has ~120k): a truncated or "
                           "filtered scan registers poorly", file, frame_id, len(scan))
        return Frame(
            frame_id=frame_id,
            stamp_ns=stamp_ns,
            sensor_name="velodyne",
            sensor_kind=SensorKind.LIDAR,
            points_sensor=scan[:, :3],
            pose=pose,
            attributes=PointAttributes(intensity=checked_intensity(scan[:, 3] if scan.shape[1] == 4 else None,
                                                                   f"{file} (frame {frame_id})")),
            provenance=Provenance(str(file.resolve()), frame_id),
            sensor_frame="velodyne",
        )

    def ground_truth(self) -> Trajectory | None:
        """Ground truth ``T_world_velo`` of the selected frames that have a pose (``frame_ids`` set), at the
        frames' stamps; ``None`` without a pose file."""
        if self.poses_file is None:
            return None
        idx = [i for i in self._indices() if self._entries[i][0] in self._gt]
        return Trajectory(
            np.array([self._entries[i][2] for i in idx], dtype=np.int64),
            np.array([self._gt[self._entries[i][0]] for i in idx], dtype=np.float64).reshape(-1, 4, 4),
            np.array([self._entries[i][0] for i in idx], dtype=np.int64),
        )

    def describe(self) -> dict[str, Any]:
        out = {**super().describe(), "ground_truth": None if self.poses_file is None else str(self.poses_file),
               "estimate": None, "point_layout": self.point_layout.value}
        if self.ignored_files:
            out["ignored_files"] = sorted(f.name for f in self.ignored_files)
        return out


MIN_SCAN_POINTS = 1000
"""A scan with fewer points than this is warned about (KITTI's HDL-64 gives ~120k per scan)."""


def _detect(path: Path) -> bool:
    try:
        return path.is_dir() and (path / "velodyne").is_dir()
    except OSError:
        return False


register_source("kitti", _detect, opener_for(KittiOdometry),
                "KITTI odometry sequence (velodyne/*.bin, calib.txt Tr, times.txt, poses.txt)")
