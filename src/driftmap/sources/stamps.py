"""Frame stamps: the one place that checks every stamp a source reads from a file, and the stamps a folder of files
carries (stamps as file names, stamp files such as ``times.txt``).

Every stamp that becomes a frame's ``stamp_ns`` passes through here: :func:`parse_stamp_s` (text in seconds, as
``times.txt``, TUM's ``depth.txt``), :func:`check_stamp_ns` (a stamp read some other way: a ROS header, a pose file's
rows, a file name), :func:`nominal_stamp_ns` (``frame_id * period`` for data without stamps) and
:func:`check_increasing_stamps` (frames need strictly increasing stamps). A file of stamps in seconds must also step
like a sensor (:func:`check_seconds_period`: a median step within 1 ms .. 10 s), else it is refused as a file in
another unit. A stamp must be a finite number, ``>= 0``
and within the int64 nanoseconds the frame store keeps (:data:`MAX_STAMP_NS`, the year 2262); anything else is a
:class:`SourceError` naming the file and the line (or the message), never a traceback at store time.

Used by every source here: the cloud-folder source (its precedence of stamps is documented there and in
docs/sources-datasets.md), KITTI (``times.txt``), TUM (``depth.txt``), the nominal-rate data sets and the ROS logs.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from driftmap.errors import SourceError
from driftmap.trajectory import Trajectory, read_lines, stamp_s_to_ns

logger = logging.getLogger(__name__)

MAX_STAMP_NS = 2**63 - 1
"""The largest stamp a frame can carry (the store keeps int64 nanoseconds: 2262-04-11)."""

_SECONDS_TEXT = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)
"""A number of seconds as data files write it: digits, an optional fraction and exponent (no ``nan`` / ``inf``,
no ``1_000``)."""


def read_pose_file(reader: Callable[..., Trajectory], path: Path, *args: Any) -> Trajectory:
    """``reader(path, *args)`` (a :mod:`driftmap.trajectory` reader), with a value beyond what it can hold (a stamp
    past the int64 ns range, a frame number too large) raised as :class:`SourceError` naming the file instead of a
    bare ``OverflowError``."""
    try:
        return reader(path, *args)
    except OverflowError as exc:
        raise SourceError(f"{path}: a stamp or number is out of range ({exc}); stamps must lie within "
                          f"0 .. {MAX_STAMP_NS} ns") from exc


def check_stamp_ns(stamp_ns: int, where: str, *, shown: str | None = None) -> int:
    """``stamp_ns`` when it can be a frame's stamp (``0 <= stamp_ns <=`` :data:`MAX_STAMP_NS`); otherwise a
    :class:`SourceError` naming ``where`` (``file:line``, the message, ...) and the stamp (``shown``: as written)."""
    value = int(stamp_ns)
    text = shown if shown is not None else f"{value} ns"
    if value < 0:
        raise SourceError(f"{where}: stamp {text} is negative; frame stamps must be >= 0 (seconds since the start of "
                          f"the recording or the Unix epoch)")
    if value > MAX_STAMP_NS:
        raise SourceError(f"{where}: stamp {text} is beyond the largest stamp a frame can carry ({MAX_STAMP_NS} ns, "
                          f"the year 2262): is it in another unit than seconds?")
    return value


def parse_stamp_s(text: str, where: str) -> int:
    """A stamp written in seconds (``times.txt``, TUM lists) as int ns, exactly as written, checked: a plain
    number (not NaN / inf), ``>= 0`` and within :data:`MAX_STAMP_NS`; otherwise :class:`SourceError` naming
    ``where`` (``file:line``) and the text."""
    stripped = text.strip()
    if not _SECONDS_TEXT.fullmatch(stripped):
        raise SourceError(f"{where}: {stripped!r} is not a number of seconds")
    try:
        value = stamp_s_to_ns(stripped)
    except ValueError as exc:
        raise SourceError(f"{where}: {stripped!r} is not a finite number of seconds") from exc
    except OverflowError as exc:
        raise SourceError(f"{where}: stamp {stripped!r} s is beyond the largest stamp a frame can carry "
                          f"({MAX_STAMP_NS} ns)") from exc
    return check_stamp_ns(value, where, shown=f"{stripped!r} s")


def nominal_stamp_ns(frame_id: int, period_ns: int, where: str) -> int:
    """``frame_id * period_ns``, the stamp of a frame of data without stamps (nominal rate, ``--period-s``),
    checked like every stamp: a frame number so large that the stamp leaves the int64 range raises naming
    ``where`` (the file the number comes from) and, when the number reads as a Unix time, says so."""
    value = int(frame_id) * int(period_ns)
    if 0 <= value <= MAX_STAMP_NS:
        return value
    hint = ""
    as_stamp = name_stamp_ns(str(frame_id))
    if as_stamp is not None:
        hint = (f"; the number reads as a Unix time in {as_stamp[1]} (a stamp, not a frame number): give the frames "
                f"stamps that fit their names (see the stamp precedence in docs/sources-datasets.md)")
    raise SourceError(f"{where}: frame number {frame_id} times the period {int(period_ns)} ns is not a stamp a frame "
                      f"can carry (0 .. {MAX_STAMP_NS} ns){hint}")

STAMP_FILE_NAMES = ("times.txt", "timestamps.txt", "stamps.txt")
"""Stamp files a folder of clouds may hold: one stamp per line, in seconds (as KITTI's ``times.txt``)."""

MIN_PERIOD_NS = 1_000_000
MAX_PERIOD_NS = 10_000_000_000
"""Stamps of a sensor's frames are plausible when their median step is within 1 ms .. 10 s."""

EPOCH_MIN_S = 946_684_800
EPOCH_MAX_S = 4_102_444_800
"""A number in a file name is a stamp only when it is a Unix time between 2000-01-01 and 2100-01-01 in one of
the units of :data:`NAME_STAMP_UNITS` (smaller numbers are frame numbers: ``000123.pcd`` is frame 123)."""

#: unit of a file-name stamp -> ns per unit; the epoch ranges of the units do not overlap
NAME_STAMP_UNITS = {"s": 1_000_000_000, "ms": 1_000_000, "us": 1_000, "ns": 1}

_NAME_NUMBER = re.compile(r"[0-9]+(?:\.[0-9]+)?")


def name_stamp_ns(name: str | Path) -> tuple[int, str] | None:
    """The stamp a file name is, as ``(stamp_ns, unit)``, or ``None`` when it is not one.

    The last number of the name without its suffix is read: with a decimal fraction (``1630577758.569490.pcd``)
    it is seconds, exactly to the ns; an integer is seconds, ms, us or ns by its magnitude
    (``1630577758569.pcd`` ms, ``1630577758569490.pcd`` us, ``1630577758569490000.pcd`` ns). Either way it must
    fall between :data:`EPOCH_MIN_S` and :data:`EPOCH_MAX_S`."""
    found = _NAME_NUMBER.findall(Path(name).stem)
    if not found:
        return None
    text = found[-1]
    if "." in text:
        whole = int(text.partition(".")[0])
        return (stamp_s_to_ns(text), "s") if EPOCH_MIN_S <= whole <= EPOCH_MAX_S else None
    value = int(text)
    for unit, ns in NAME_STAMP_UNITS.items():
        per_s = 1_000_000_000 // ns
        if EPOCH_MIN_S * per_s <= value <= EPOCH_MAX_S * per_s:
            return value * ns, unit
    return None


def period_problem(stamps_ns: Sequence[int]) -> str | None:
    """What is implausible about the steps of increasing ``stamps_ns`` (median outside 1 ms .. 10 s), or ``None``."""
    if len(stamps_ns) < 2:
        return None
    median = float(np.median(np.diff(np.asarray(stamps_ns, dtype=np.int64))))
    if MIN_PERIOD_NS <= median <= MAX_PERIOD_NS:
        return None
    return (f"their median step is {median / 1e9:.6g} s, outside the {MIN_PERIOD_NS / 1e9:g} .. "
            f"{MAX_PERIOD_NS / 1e9:g} s of a sensor's frames")


def check_seconds_period(stamps_ns: Sequence[int], file: Path | str, what: str) -> None:
    """Stamps read as seconds from ``file`` (a stamp file such as KITTI's ``times.txt``, a TUM ``depth.txt``) whose
    median step no sensor has (outside :data:`MIN_PERIOD_NS` .. :data:`MAX_PERIOD_NS`): :class:`SourceError`
    naming the file and ``what`` the stamps are of ("the 16 clouds"), asking whether the file is in seconds (a file
    in milliseconds steps ~100 s at 10 Hz, one in microseconds ~1e5 s).

    Only the steps forward are judged (a duplicate or a step back is :func:`check_increasing_stamps`' to report);
    fewer than one step forward is not judged. The one check of the period of stamps read in seconds, shared by the
    cloud-folder source, KITTI and TUM."""
    steps = np.diff(np.asarray(stamps_ns, dtype=np.int64))
    steps = steps[steps > 0]
    if steps.size == 0:
        return
    median = float(np.median(steps))
    if MIN_PERIOD_NS <= median <= MAX_PERIOD_NS:
        return
    raise SourceError(f"{file}: read as seconds, the stamps of {what} do not fit a sensor: their median step is "
                      f"{median / 1e9:.6g} s, outside {MIN_PERIOD_NS / 1e9:g} .. {MAX_PERIOD_NS / 1e9:g} s "
                      f"(is the file in seconds?)")


def stamps_from_file_names(files: Sequence[Path], what: str) -> tuple[list[tuple[int, Path]], str] | None:
    """``([(stamp_ns, file)] in stamp order, unit)`` when every file name is a stamp (:func:`name_stamp_ns`) of
    one unit and the stamps are plausible; otherwise ``None`` (the names are frame numbers).

    Two files with the same stamp raise :class:`SourceError` naming both. Names that are stamps of different
    units, or whose period is implausible (:func:`period_problem`), are logged and taken as frame numbers."""
    parsed = [(name_stamp_ns(f.name), f) for f in files]
    if not parsed or any(p is None for p, _ in parsed):
        n_stamps = sum(p is not None for p, _ in parsed)
        if n_stamps:
            logger.info("%s: %d of %d file names look like stamps; the names are taken as frame numbers", what,
                        n_stamps, len(parsed))
        return None
    units = sorted({p[1] for p, _ in parsed if p is not None}, key=list(NAME_STAMP_UNITS).index)
    if len(units) > 1:
        logger.warning("%s: the file names look like stamps of different units (%s); they are taken as frame "
                       "numbers", what, ", ".join(units))
        return None
    entries = sorted(((p[0], f) for p, f in parsed if p is not None), key=lambda e: (e[0], e[1].name))
    for (a, fa), (b, fb) in zip(entries, entries[1:]):
        if a == b:
            raise SourceError(f"{fa} and {fb}: both file names are the stamp {a} ns ({what})")
    problem = period_problem([s for s, _ in entries])
    if problem is not None:
        logger.warning("%s: the file names look like stamps in %s, but %s; they are taken as frame numbers", what,
                       units[0], problem)
        return None
    return entries, units[0]


def read_times(file: Path) -> list[int]:
    """A stamp file (``times.txt``: seconds, one row per frame; blank lines skipped) as int ns, exactly as
    written. A line that is not one number of seconds, or a stamp that is negative or out of range, raises
    :class:`SourceError` naming ``file:line`` (:func:`parse_stamp_s`)."""
    return [stamp for stamp, _ in read_times_with_lines(file)]


def read_times_with_lines(file: Path) -> list[tuple[int, int]]:
    """:func:`read_times` with the 1-based line of each stamp: ``[(stamp_ns, line)]``."""
    out = []
    for lineno, line in enumerate(read_lines(file, "stamp file"), start=1):
        if line.strip():
            out.append((parse_stamp_s(line, f"{file}:{lineno}"), lineno))
    return out


def check_increasing_stamps(
    stamps_ns: Sequence[int],
    frame_ids: Sequence[int | str],
    what: str,
    *,
    lenient: bool,
    skipped: list[tuple[int, str]] | None = None,
) -> list[int]:
    """Positions to keep so that stamps strictly increase.

    A duplicate or earlier stamp raises :class:`SourceError` naming ``what`` (the file) and the two frames;
    in lenient mode the later frame is dropped with a logged reason (and recorded in ``skipped``).
    ``frame_ids`` name the entries: an int ``n`` reads "frame n", a string is used as it is ("row 7").
    """

    def name(k: int) -> str:
        return f"frame {frame_ids[k]}" if isinstance(frame_ids[k], (int, np.integer)) else str(frame_ids[k])

    keep: list[int] = []
    for k, stamp in enumerate(stamps_ns):
        if keep and stamp <= stamps_ns[keep[-1]]:
            prev = keep[-1]
            kind = "duplicate stamp" if stamp == stamps_ns[prev] else "stamp goes back in time"
            reason = (
                f"{what}: {kind}: {name(k)} has stamp_ns {stamp}, {name(prev)} before it has stamp_ns {stamps_ns[prev]}"
            )
            if not lenient:
                raise SourceError(reason)
            logger.warning("%s (%s skipped)", reason, name(k))
            if skipped is not None:
                skipped.append((k, reason))
            continue
        keep.append(k)
    return keep


def pose_file_stamp_lines(file: Path, format: str) -> list[int]:
    """The 1-based line of each row's stamp in a pose file with stamps (TUM and EuRoC: every data line; ``4x4``:
    the last line of every block), for messages about a row; empty when the file cannot be read."""
    try:
        lines = read_lines(file, "pose file")
    except SourceError:
        return []
    data = [k for k, line in enumerate(lines, start=1) if line.partition("#")[0].strip()]
    return data[3::4] if format == "4x4" else data


def check_pose_file_stamps(file: Path, format: str, stamps_ns: Sequence[int]) -> list[int]:
    """The stamps of a pose file's rows that stamp frames, each checked as a frame's stamp (:func:`check_stamp_ns`),
    errors naming the file and the line of the row."""
    lines = pose_file_stamp_lines(file, format)
    out = []
    for k, stamp in enumerate(stamps_ns):
        where = f"{file}:{lines[k]}" if k < len(lines) else f"{file} (row {k + 1})"
        out.append(check_stamp_ns(int(stamp), where))
    return out


def rows_for_frames(n_rows: int, frame_ids: Sequence[int]) -> tuple[list[int], str] | None:
    """Which row of a per-frame file (a stamp file, a pose file found beside the frames) belongs to each frame,
    and how it was decided; ``None`` when the rows do not fit.

    As many rows as frames: row ``k`` is the ``k``-th frame. More rows, and every frame number below their count:
    row ``n`` is frame ``n`` (the file covers the whole sequence and the folder a part of it, as KITTI's
    ``times.txt``). Otherwise (fewer rows, or numbers beyond them) the file does not fit the frames."""
    if n_rows == len(frame_ids):
        return list(range(n_rows)), "row k = k-th file"
    if n_rows > len(frame_ids) and frame_ids and min(frame_ids) >= 0 and max(frame_ids) < n_rows:
        return list(frame_ids), "row n = frame n"
    return None
