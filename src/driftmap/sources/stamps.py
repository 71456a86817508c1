"""Frame stamps that a folder of files carries: stamps as file names, stamp files (``times.txt``), and the checks
that they fit the data (the unit decided by magnitude, stamps that increase, a plausible period).

Used by the cloud-folder source (its precedence of stamps is documented there and in docs/sources-datasets.md)
and by KITTI (``times.txt``).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from driftmap.errors import SourceError
from driftmap.trajectory import _read_lines, _stamp_s_to_ns

logger = logging.getLogger(__name__)

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

_NAME_NUMBER = re.compile(r"\d+(?:\.\d+)?")


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
        return (_stamp_s_to_ns(text), "s") if EPOCH_MIN_S <= whole <= EPOCH_MAX_S else None
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
    written. A line that is not one number of seconds raises :class:`SourceError` naming ``file:line``."""
    out = []
    for lineno, line in enumerate(_read_lines(file, "stamp file"), start=1):
        if not line.strip():
            continue
        try:
            out.append(_stamp_s_to_ns(line))
        except (ValueError, OverflowError) as exc:
            raise SourceError(f"{file}:{lineno}: {line.strip()!r} is not a number of seconds") from exc
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
