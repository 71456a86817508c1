"""Trajectory files: TUM (``stamp tx ty tz qx qy qz qw``), KITTI (3x4 row-major per line), EuRoC CSV, Redwood
``.log`` and blocks of one 4x4 matrix per frame (``4x4``, with or without a stamp in the last row).

Readers return a :class:`Trajectory` (stamps in int nanoseconds, poses as 4x4 float64); writers take one.

Every reader validates what it reads and raises :class:`SourceError` naming the file, the 1-based line and the
field: text that is not UTF-8, a wrong column count, a value that is not a number or not finite (NaN, inf),
a quaternion that is not unit length, a KITTI rotation block that is not a rotation (within
:data:`driftmap.geometry.RIGID_TOLERANCE`, checked by :func:`driftmap.geometry.as_rigid`), and a stamp that
goes back in time. A stamp written twice (two rows, same instant) is kept and logged as a warning: the
official TUM ``fr2_desk`` ground truth has one (line 10863), and nearest-stamp lookups stay well defined.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.errors import SourceError, TransformError
from driftmap.trajectory_rows import spike_rows as spike_rows  # re-exported: read here before the split
from driftmap.trajectory_rows import warn_rows, warn_spikes

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Trajectory:
    """A sequence of poses ``T_world_x`` with stamps (ns) and, optionally, the frame ids they belong to."""

    stamps_ns: NDArray[np.int64]
    poses: NDArray[np.float64]  # (N, 4, 4)
    frame_ids: NDArray[np.int64] | None = None
    #: 1-based line in the file each row was read from (readers of stamped formats fill it), for error messages.
    source_lines: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        if self.poses.ndim != 3 or self.poses.shape[1:] != (4, 4):
            raise SourceError(f"Trajectory: poses must be (N, 4, 4), got {self.poses.shape}")
        if len(self.stamps_ns) != len(self.poses):
            raise SourceError(f"Trajectory: {len(self.stamps_ns)} stamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def positions_m(self) -> NDArray[np.float64]:
        return self.poses[:, :3, 3]


def stamp_s_to_ns(text: str) -> int:
    """Seconds as written in a file -> int ns, exactly (no float rounding of the decimal digits)."""
    text = text.strip()
    if "_" in text or not text:  # int() would read "1_000"
        raise ValueError(f"{text!r} is not a number of seconds")
    negative = text.startswith("-")
    if negative:
        text = text[1:]
    if "e" in text.lower():
        value = round(float(text) * 1e9)
    else:
        whole, _, frac = text.partition(".")
        value = int(whole or "0") * 1_000_000_000 + int((frac + "000000000")[:9] or "0")
    if value > _INT64_MAX:  # a stamp must fit the int64 ns every stamp is kept in
        raise OverflowError(f"{text!r} s is beyond the int64 nanosecond range (year 2262): are the stamps in "
                            f"nanoseconds or milliseconds? TUM and driftmap pose files give seconds")
    return -value if negative else value


_INT64_MAX = 2**63 - 1


def _format_stamp_ns(stamp_ns: int) -> str:
    sign = "-" if stamp_ns < 0 else ""
    s, ns = divmod(abs(int(stamp_ns)), 1_000_000_000)
    return f"{sign}{s}.{ns:09d}"


def read_lines(path: Path, what: str) -> list[str]:
    """The lines of a text file (split at ``\\n`` only, so line numbers are the ones an editor shows).

    A file that cannot be read, or is not UTF-8, raises :class:`SourceError` naming it (and the line of the
    first byte that is not UTF-8). A leading UTF-8 byte-order mark is ignored.
    """
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SourceError(f"{path}: cannot read {what} ({exc})") from exc
    bom = b"\xef\xbb\xbf"
    start = len(bom) if raw.startswith(bom) else 0
    try:
        text = raw[start:].decode("utf-8")
    except UnicodeDecodeError as exc:
        offset = start + exc.start
        lineno = raw.count(b"\n", 0, offset) + 1
        utf16 = raw[:2] in (b"\xff\xfe", b"\xfe\xff")
        hint = "; it starts with a UTF-16 byte-order mark, save it as UTF-8" if utf16 else ""
        raise SourceError(
            f"{path}:{lineno}: not UTF-8 text (byte 0x{raw[offset]:02x} at byte offset {offset}); "
            f"cannot read {what}{hint}"
        ) from exc
    return text.split("\n")


def _check_finite(path: Path, data: NDArray[np.float64], linenos: Sequence[int],
                  columns: Sequence[tuple[str, str, int]]) -> None:
    """``columns[j] = (field, name, column)`` describes ``data[:, j]`` (column 1-based in the file); the first
    NaN or inf raises naming its line, field and column."""
    bad = ~np.isfinite(data)
    if bad.any():
        r, c = (int(v) for v in np.argwhere(bad)[0])
        field, name, column = columns[c]
        raise SourceError(f"{path}:{linenos[r]}: {field} is not finite (column {column}: {name}={data[r, c]})")


def _check_stamp_order(path: Path, stamps_ns: Sequence[int], linenos: Sequence[int], texts: Sequence[str]) -> None:
    """A stamp earlier than the one before it raises naming both lines; a repeated stamp is logged (the rows
    are read; :func:`~driftmap.store.pose_match.refuse_conflicting_rows` refuses disagreeing ones where a pose per
    instant is needed). ``texts`` are the stamps as written in the file, for the messages."""
    if len(stamps_ns) < 2:
        return
    steps = np.diff(np.asarray(stamps_ns, dtype=np.int64))
    back = np.flatnonzero(steps < 0)
    if back.size:
        k = int(back[0]) + 1
        raise SourceError(
            f"{path}:{linenos[k]}: stamp goes back in time: {texts[k]} is earlier than {texts[k - 1]} "
            f"on line {linenos[k - 1]} (stamps must increase)"
        )
    repeated = np.flatnonzero(steps == 0)
    if repeated.size:
        k = int(repeated[0]) + 1
        logger.warning(
            "%s:%d: duplicate stamp: %s is also on line %d; %d repeated stamp(s) in the file; where one pose per "
            "instant is needed (build --poses, correct, diagnose --gt) rows of one stamp that disagree are refused",
            path, linenos[k], texts[k], linenos[k - 1], repeated.size,
        )


def _poses_from_rows(path: Path, translation_m: NDArray[np.float64], quat_xyzw: NDArray[np.float64],
                     linenos: Sequence[int]) -> NDArray[np.float64]:
    """(N, 4, 4) poses from translations and unit quaternions; a non-unit quaternion names its line."""
    norms = np.linalg.norm(quat_xyzw, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if bad.size:
        raise SourceError(f"{path}:{linenos[bad[0]]}: quaternion has norm {norms[bad[0]]:.4f}, expected 1")
    far = np.flatnonzero(np.max(np.abs(translation_m), axis=1) > geometry.MAX_TRANSLATION_M)
    if far.size:
        raise SourceError(f"{path}:{linenos[far[0]]}: translation {translation_m[far[0]].tolist()} m is beyond "
                          f"{geometry.MAX_TRANSLATION_M:g} m from the origin (a unit error?)")
    poses = np.tile(np.eye(4), (len(translation_m), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(quat_xyzw).as_matrix()
    poses[:, :3, 3] = translation_m
    return poses


#: (field, name, 1-based file column) of the values after the stamp in a TUM row.
_TUM_COLUMNS = [("translation", n, c) for c, n in enumerate(("tx", "ty", "tz"), start=2)] + [
    ("quaternion", n, c) for c, n in enumerate(("qx", "qy", "qz", "qw"), start=5)
]


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file; comment lines start with ``#``.

    Stamps must not go back in time; a repeated stamp is kept with a logged warning (see the module docs).
    """
    path = Path(path)
    stamps: list[int] = []
    rows: list[list[float]] = []
    linenos: list[int] = []
    stamp_texts: list[str] = []
    for lineno, line in enumerate(read_lines(path, "TUM trajectory"), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            hint = " (12 numbers per row: a KITTI pose file? read it as KITTI, e.g. --format kitti / --gt-format kitti)" \
                if len(parts) == 12 else (" (4 numbers per row: a file of 4x4 matrices? read it as 4x4, e.g. --format 4x4 / "
                                          "--gt-format 4x4)") if len(parts) == 4 else ""
            raise SourceError(f"{path}:{lineno}: expected 8 columns 'stamp tx ty tz qx qy qz qw', got {len(parts)}{hint}")
        try:
            stamps.append(stamp_s_to_ns(parts[0]))
            rows.append([float(p) for p in parts[1:]])
        except ValueError as exc:
            raise SourceError(f"{path}:{lineno}: not a number ({exc})") from exc
        except OverflowError as exc:  # e.g. "1e400" or "1e10" s as a stamp
            raise SourceError(f"{path}:{lineno}: stamp {parts[0]!r} is not a usable time ({exc})") from exc
        linenos.append(lineno)
        stamp_texts.append(parts[0])
    if not rows:
        raise SourceError(f"{path}: no poses in TUM file")
    data = np.asarray(rows)
    _check_finite(path, data, linenos, _TUM_COLUMNS)
    _check_stamp_order(path, stamps, linenos, stamp_texts)
    return Trajectory(np.asarray(stamps, dtype=np.int64), _poses_from_rows(path, data[:, :3], data[:, 3:7], linenos),
                      source_lines=np.asarray(linenos, dtype=np.int64))


def _format_number(value: float) -> str:
    """The shortest text that reads back as exactly ``value`` (Python's ``repr`` of a float)."""
    return repr(float(value))


def _write_text_atomically(path: str | Path, text: str, what: str, trajectory: Trajectory) -> None:
    """Write a pose file: refused when empty (its readers refuse a file without poses); written under a temporary
    name in the same folder and renamed into place when complete (:func:`driftmap.files.atomic_write`), so a failed
    write leaves no partial file and an existing file survives a failed overwrite. Callers that take the path from a
    user refuse one inside a store folder first (:func:`driftmap.store.refuse_inside_store`)."""
    from driftmap.errors import EmptyExportError
    from driftmap.files import atomic_write

    if len(trajectory) == 0:
        raise EmptyExportError(f"{path}: no poses to write ({what}); nothing written")
    with atomic_write(path, f"{what} file") as tmp:
        tmp.write_text(text)


def write_tum(path: str | Path, trajectory: Trajectory) -> None:
    """Write a TUM file (stamps in seconds with nanosecond digits, quaternions ``qx qy qz qw``); numbers are
    written with the shortest digits that read back exactly, so :func:`read_tum` returns the same poses.

    The file appears complete or not at all (temporary file renamed into place); an empty trajectory is an
    :class:`~driftmap.errors.EmptyExportError`."""
    quat = Rotation.from_matrix(trajectory.poses[:, :3, :3]).as_quat() if len(trajectory) else np.zeros((0, 4))
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, T, q in zip(trajectory.stamps_ns, trajectory.poses, quat, strict=True):
        t = T[:3, 3]
        lines.append(f"{_format_stamp_ns(int(stamp))} " + " ".join(_format_number(v) for v in (*t, *q)))
    _write_text_atomically(path, "\n".join(lines) + "\n", "TUM trajectory", trajectory)


#: (field, name, 1-based file column) of the 12 numbers of a KITTI row (3x4 row-major ``[R | t]``).
_KITTI_COLUMNS = [
    ("translation", ("tx", "ty", "tz")[i], 4 * i + 4) if j == 3 else ("rotation", f"R[{i},{j}]", 4 * i + j + 1)
    for i in range(3)
    for j in range(4)
]


def read_kitti(path: str | Path) -> Trajectory:
    """Read a KITTI pose file (12 numbers per line, the top 3x4 of ``T_world_x``); stamps are row indices.

    ``#`` starts a comment. Each rotation block must be a rotation within the tolerance of
    :func:`driftmap.geometry.as_rigid` (orthonormal, determinant +1); rows are kept as written (not projected).
    """
    path = Path(path)
    rows: list[list[float]] = []
    linenos: list[int] = []
    for lineno, line in enumerate(read_lines(path, "KITTI poses"), start=1):
        parts = line.partition("#")[0].split()
        if not parts:
            continue
        if len(parts) != 12:
            raise SourceError(
                f"{path}:{lineno}: expected 12 numbers per KITTI pose row (3x4 row-major T_world_x), got {len(parts)}"
            )
        try:
            rows.append([float(p) for p in parts])
        except ValueError as exc:
            raise SourceError(f"{path}:{lineno}: not a number ({exc})") from exc
        linenos.append(lineno)
    if not rows:
        raise SourceError(f"{path}: no poses in KITTI file")
    data = np.asarray(rows)
    _check_finite(path, data, linenos, _KITTI_COLUMNS)
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :] = data.reshape(-1, 3, 4)
    bad, _ = geometry.rigid_stack_problems(poses)
    if bad.size:  # as_rigid names what is wrong with the first such row
        k = int(bad[0])
        try:
            geometry.as_rigid(poses[k], f"{path}:{linenos[k]} (frame {k})")
        except TransformError as exc:
            raise SourceError(str(exc)) from exc
    ids = np.arange(len(data), dtype=np.int64)
    return Trajectory(ids.copy(), poses, ids)


def write_kitti(path: str | Path, trajectory: Trajectory) -> None:
    """Write one 3x4 row-major line per pose, with the shortest digits that read back exactly (atomically, never
    empty: as :func:`write_tum`)."""
    rows = trajectory.poses[:, :3, :].reshape(-1, 12)
    _write_text_atomically(path, "".join(" ".join(_format_number(v) for v in row) + "\n" for row in rows),
                           "KITTI trajectory", trajectory)


# ---- EuRoC, Redwood .log, and format detection -----------------------------------------------------------------

#: Formats :func:`read_trajectory` knows, with what their lines look like (used in error messages).
TRAJECTORY_FORMATS = {
    "tum": "'stamp_s tx ty tz qx qy qz qw' (8 columns, stamp in seconds)",
    "kitti": "12 numbers per line (3x4 row-major T_world_x, one line per frame)",
    "euroc": "CSV 'stamp_ns, px, py, pz, qw, qx, qy, qz, ...' (integer ns stamp, quaternion w first)",
    "redwood": "blocks of an 'i j n' line + 4 lines of a 4x4 matrix (.log)",
    "4x4": "blocks of 4 lines of a 4x4 matrix [R t; 0 0 0 s] (space- or comma-separated; s = stamp in seconds, "
           "or 1: no stamps, block k = frame k)",
}

#: Formats whose rows carry time (matched to frames by stamp); ``4x4`` files do when their last rows hold stamps.
STAMPED_FORMATS = ("tum", "euroc")


#: (field, name, 1-based file column) of the 7 pose values after the stamp in an EuRoC row.
_EUROC_COLUMNS = [("position", n, c) for c, n in enumerate(("p_x", "p_y", "p_z"), start=2)] + [
    ("quaternion", n, c) for c, n in enumerate(("q_w", "q_x", "q_y", "q_z"), start=5)
]


def read_euroc(path: str | Path) -> Trajectory:
    """Read an EuRoC ground-truth CSV (``#timestamp [ns], p_RS_R_x, p_RS_R_y, p_RS_R_z, q_RS_w, q_RS_x, q_RS_y,
    q_RS_z, ...``): poses ``T_R_S`` (body ``S`` in the world ``R``); columns after the quaternion are ignored.

    The quaternion is stored **w first**; it is reordered to scipy's ``(x, y, z, w)`` here. Stamps must not
    go back in time; a repeated stamp is kept with a logged warning.
    """
    path = Path(path)
    stamps: list[int] = []
    rows: list[list[float]] = []
    linenos: list[int] = []
    stamp_texts: list[str] = []
    for lineno, line in enumerate(read_lines(path, "EuRoC trajectory"), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) < 8:
            raise SourceError(
                f"{path}:{lineno}: expected at least 8 comma-separated columns "
                f"'stamp_ns, px, py, pz, qw, qx, qy, qz', got {len(parts)}"
            )
        try:
            stamps.append(int(parts[0]))
        except ValueError as exc:
            raise SourceError(f"{path}:{lineno}: stamp {parts[0]!r} is not an integer number of nanoseconds") from exc
        try:
            rows.append([float(p) for p in parts[1:8]])
        except ValueError as exc:
            raise SourceError(f"{path}:{lineno}: not a number ({exc})") from exc
        linenos.append(lineno)
        stamp_texts.append(parts[0])
    if not rows:
        raise SourceError(f"{path}: no poses in EuRoC file")
    data = np.asarray(rows)
    _check_finite(path, data, linenos, _EUROC_COLUMNS)
    _check_stamp_order(path, stamps, linenos, stamp_texts)
    quat_wxyz = data[:, 3:7]
    return Trajectory(np.asarray(stamps, dtype=np.int64),
                      _poses_from_rows(path, data[:, :3], quat_wxyz[:, [1, 2, 3, 0]], linenos),
                      source_lines=np.asarray(linenos, dtype=np.int64))


def write_euroc(path: str | Path, trajectory: Trajectory) -> None:
    """Write an EuRoC CSV (integer ns stamps, quaternion w first) that :func:`read_euroc` reads back exactly
    (atomically, never empty: as :func:`write_tum`)."""
    quat = Rotation.from_matrix(trajectory.poses[:, :3, :3]).as_quat() if len(trajectory) else np.zeros((0, 4))
    lines = ["#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    for stamp, T, q in zip(trajectory.stamps_ns, trajectory.poses, quat, strict=True):
        lines.append(f"{int(stamp)}," + ",".join(_format_number(v) for v in (*T[:3, 3], q[3], q[0], q[1], q[2])))
    _write_text_atomically(path, "\n".join(lines) + "\n", "EuRoC trajectory", trajectory)


def read_redwood_log(path: str | Path) -> Trajectory:
    """Read a Redwood / Open3D ``.log`` trajectory: per pose an ``i j n`` line and 4 lines of a 4x4 matrix.

    ``frame_ids`` are the first number of each header line; the format has no time, so ``stamps_ns`` are the
    frame ids (as :func:`read_kitti` uses row indices). Each matrix must be rigid (within the tolerance of
    :func:`driftmap.geometry.as_rigid`, which also projects it onto SO(3)).
    """
    path = Path(path)
    raw = read_lines(path, "Redwood .log trajectory")
    lines = [(n, line.split()) for n, line in enumerate(raw, start=1) if line.strip()]
    if not lines:
        raise SourceError(f"{path}: no poses in Redwood .log file")
    if len(lines) % 5:
        raise SourceError(
            f"{path}: {len(lines)} non-empty lines is not a multiple of 5 (an 'i j n' line + 4 matrix rows per pose)"
        )
    ids: list[int] = []
    poses: list[np.ndarray] = []
    header_line: dict[int, int] = {}
    for b in range(0, len(lines), 5):
        lineno, header = lines[b]
        if len(header) != 3:
            raise SourceError(
                f"{path}:{lineno}: expected an 'i j n' header line with 3 integers, got {len(header)} fields"
            )
        try:
            ids.append(int(header[0]))
        except ValueError as exc:
            raise SourceError(f"{path}:{lineno}: frame id {header[0]!r} is not an integer") from exc
        if ids[-1] in header_line:
            raise SourceError(f"{path}:{lineno}: frame id {ids[-1]} is named by two pose blocks, at lines "
                              f"{header_line[ids[-1]]} and {lineno} (which one is the frame's pose?)")
        header_line[ids[-1]] = lineno
        matrix = []
        for lineno_r, row in lines[b + 1 : b + 5]:
            if len(row) != 4:
                raise SourceError(f"{path}:{lineno_r}: expected 4 numbers in a matrix row, got {len(row)}")
            try:
                matrix.append([float(v) for v in row])
            except ValueError as exc:
                raise SourceError(f"{path}:{lineno_r}: not a number ({exc})") from exc
        try:
            poses.append(geometry.as_rigid(matrix, f"{path}:{lineno} (frame {ids[-1]})"))
        except TransformError as exc:
            raise SourceError(str(exc)) from exc
    frame_ids = np.asarray(ids, dtype=np.int64)
    return Trajectory(frame_ids.copy(), np.asarray(poses, dtype=np.float64), frame_ids)


def _matrix_fields(line: str) -> list[str] | None:
    """The fields of one row of a ``4x4`` file: comma-separated (one trailing comma allowed, as BALM writes
    them) or whitespace-separated; ``None`` for an empty field between two commas."""
    if "," in line:
        fields = [f.strip() for f in line.split(",")]
        if fields and fields[-1] == "":
            fields.pop()
        return None if any(f == "" for f in fields) else fields
    return line.split()


#: (field, name, 1-based column) of the 4 numbers of a row of a 4x4 block
_MATRIX_COLUMNS = [("matrix entry", f"column {j + 1}", j + 1) for j in range(4)]


def read_matrix4x4(path: str | Path) -> Trajectory:
    """Read a file of one 4x4 matrix ``T_world_x`` per frame: 4 lines of 4 numbers per block (space- or
    comma-separated, a trailing comma allowed), blank lines allowed between blocks, ``#`` comments.

    The last row of each block is ``0 0 0 s``. When every ``s`` is 1 the file has no time: block ``k`` is frame
    ``k`` (``stamps_ns`` and ``frame_ids`` are the block indices, as :func:`read_kitti`). Otherwise ``s`` is the
    stamp in seconds (BALM's ``alidarPose.csv``), parsed exactly to int ns, and ``frame_ids`` is ``None``; the
    stamps must not go back in time (a repeated one is kept with a warning, as in TUM files).

    Raises :class:`SourceError` naming the file and the 1-based line: a line count that is not a multiple of 4
    (naming the first line of the incomplete block), a blank line inside a block, a row without 4 numbers, a
    value that is not a number or not finite, a last row whose first three entries are not 0, and a rotation
    block that is not a rotation (within :data:`driftmap.geometry.RIGID_TOLERANCE`; rows are kept as written).
    """
    path = Path(path)
    rows: list[list[float]] = []
    linenos: list[int] = []
    stamp_texts: list[str] = []
    blank_in_block: int | None = None  # a blank line after 1-3 rows of a block: an error if the block goes on
    for lineno, line in enumerate(read_lines(path, "4x4 pose file"), start=1):
        line = line.partition("#")[0].strip()
        if not line:
            if len(rows) % 4 and blank_in_block is None:
                blank_in_block = lineno
            continue
        if blank_in_block is not None:
            raise SourceError(f"{path}:{blank_in_block}: blank line inside a 4x4 block (after {len(rows) % 4} of its 4 "
                              f"rows, the block starts on line {linenos[-(len(rows) % 4)]})")
        fields = _matrix_fields(line)
        if fields is None or len(fields) != 4:
            got = "an empty field" if fields is None else f"{len(fields)} fields"
            raise SourceError(f"{path}:{lineno}: expected 4 numbers per row of a 4x4 pose block, got {got}")
        try:
            rows.append([float(f) for f in fields])
        except ValueError as exc:
            raise SourceError(f"{path}:{lineno}: not a number ({exc})") from exc
        linenos.append(lineno)
        if len(rows) % 4 == 0:
            stamp_texts.append(fields[3])
    if not rows:
        raise SourceError(f"{path}: no poses in 4x4 pose file")
    if len(rows) % 4:
        # the first block whose bottom row (0 0 0 s) is not its 4th row is the damaged one; else the last block
        bottoms = [k for k, r in enumerate(rows) if r[0] == r[1] == r[2] == 0.0]
        j = next((j for j, b in enumerate(bottoms) if b != 4 * j + 3), None)
        if j is not None and bottoms[j] < 4 * j + 3:
            first = linenos[4 * j]
            what = f"has only {bottoms[j] - 4 * j + 1} row(s), its 0 0 0 row on line {linenos[bottoms[j]]}"
        elif j is not None:
            first = linenos[4 * j]
            what = (f"has no 0 0 0 last row where its 4th row should be (line {linenos[4 * j + 3]}); the next one "
                    f"is on line {linenos[bottoms[j]]}")
        else:
            first = linenos[len(rows) - len(rows) % 4]
            what = f"has only {len(rows) % 4} row(s)"
        raise SourceError(f"{path}:{first}: {len(rows)} matrix rows is not a multiple of 4; the block starting on "
                          f"line {first} {what} (4 rows per pose)")
    data = np.asarray(rows)
    block_lines = linenos[::4]
    _check_finite(path, data, linenos, _MATRIX_COLUMNS)
    poses = data.reshape(-1, 4, 4).copy()
    last = poses[:, 3, :3]
    bad_last = np.flatnonzero(np.any(last != 0.0, axis=1))
    if bad_last.size:
        k = int(bad_last[0])
        raise SourceError(f"{path}:{linenos[4 * k + 3]}: the last row of a 4x4 pose block must start with 0 0 0, "
                          f"got {' '.join(repr(float(v)) for v in last[k])} (block {k}, starting on line {block_lines[k]})")
    stamped = bool(np.any(poses[:, 3, 3] != 1.0))
    ones = np.flatnonzero(poses[:, 3, 3] == 1.0)
    if stamped and len(poses) > 2 and len(ones) > len(poses) // 2:  # mostly 0 0 0 1: a damaged block, not stamps
        k = int(np.flatnonzero(poses[:, 3, 3] != 1.0)[0])
        raise SourceError(f"{path}:{linenos[4 * k + 3]}: the last row of block {k} (starting on line {block_lines[k]}) "
                          f"is 0 0 0 {stamp_texts[k]}, but {len(ones)} of the {len(poses)} blocks end in 0 0 0 1: "
                          f"expected 0 0 0 1 there (or a stamp in every block's last row)")
    poses[:, 3, 3] = 1.0
    bad, _ = geometry.rigid_stack_problems(poses)
    if bad.size:  # as_rigid names what is wrong with the first such block
        k = int(bad[0])
        try:
            geometry.as_rigid(poses[k], f"{path}:{block_lines[k]} (block {k})")
        except TransformError as exc:
            raise SourceError(str(exc)) from exc
    if not stamped:
        ids = np.arange(len(poses), dtype=np.int64)
        return Trajectory(ids.copy(), poses, ids)
    stamps: list[int] = []
    for k, text in enumerate(stamp_texts):
        try:
            stamps.append(stamp_s_to_ns(text))
        except ValueError as exc:
            raise SourceError(f"{path}:{linenos[4 * k + 3]}: stamp {text!r} is not a number of seconds") from exc
        except OverflowError as exc:
            raise SourceError(f"{path}:{linenos[4 * k + 3]}: stamp {text!r} is not a usable time ({exc})") from exc
    stamp_lines = linenos[3::4]
    _check_stamp_order(path, stamps, stamp_lines, stamp_texts)
    return Trajectory(np.asarray(stamps, dtype=np.int64), poses, source_lines=np.asarray(block_lines, dtype=np.int64))


def has_stamps(trajectory: Trajectory, format: str) -> bool:
    """Whether the rows of ``trajectory`` (read as ``format``) carry time, so that they match frames by stamp:
    TUM and EuRoC always; ``4x4`` when its last rows hold stamps (:func:`read_matrix4x4` then leaves
    ``frame_ids`` unset); KITTI and Redwood ``.log`` never (their ``stamps_ns`` are row indices / frame ids)."""
    return format in STAMPED_FORMATS or (format == "4x4" and trajectory.frame_ids is None)


def _first_data_lines(path: Path, n: int = 5) -> list[str]:
    """The first ``n`` non-empty lines that are not ``#`` comments (reads only the head of the file)."""
    out: list[str] = []
    with path.open("r", encoding="utf-8-sig") as fh:
        for line in fh:
            line = line.strip()
            if line and not line.startswith("#"):
                out.append(line)
                if len(out) >= n:
                    break
    return out


def detect_trajectory_format(path: str | Path) -> str:
    """Tell TUM / KITTI / EuRoC / Redwood ``.log`` / ``4x4`` apart from the first lines of ``path``.

    Raises :class:`SourceError` naming every format tried and what the file looks like when none fits.
    """
    path = Path(path)
    try:
        head = _first_data_lines(path)
        with path.open("r", encoding="utf-8-sig") as fh:
            first_line = fh.readline()
    except OSError as exc:
        raise SourceError(f"{path}: cannot read trajectory file ({exc})") from exc
    except UnicodeDecodeError as exc:
        read_lines(path, "trajectory file")  # raises naming the line of the first byte that is not UTF-8
        raise SourceError(f"{path}: not UTF-8 text ({exc}); cannot read trajectory file") from exc
    tried = "; ".join(f"{name}: {what}" for name, what in TRAJECTORY_FORMATS.items())
    if not head:
        raise SourceError(f"{path}: no data lines; cannot tell the trajectory format (tried {tried})")
    line = head[0]

    def numeric(fields: list[str]) -> bool:
        try:
            [float(f) for f in fields]
        except ValueError:
            return False
        return True

    if "q_rs_w" in first_line.lower() or "[ns]" in first_line.lower():
        return "euroc"
    if "," in line:
        fields = [f.strip() for f in line.split(",")]
        if len(fields) >= 8 and fields[0].lstrip("-").isdigit() and numeric(fields):
            return "euroc"
    fields = line.replace(",", " ").split()
    if fields and fields[0].upper().startswith(("VERTEX_", "EDGE_")):
        raise SourceError(f"{path}: {G2O_HINT}")
    is_int = all(f.lstrip("-").isdigit() for f in fields)
    if len(fields) == 3 and is_int and len(head) >= 2 and len(head[1].split()) == 4:
        return "redwood"
    if len(fields) == 12 and numeric(fields):
        return "kitti"
    rows = [_matrix_fields(h) for h in head[:4]]
    if len(rows) == 4 and all(r is not None and len(r) == 4 and numeric(r) for r in rows) \
            and all(float(v) == 0.0 for v in rows[3][:3]):  # type: ignore[index]
        return "4x4"
    if len(fields) == 8 and numeric(fields):
        return "tum"
    raise SourceError(
        f"{path}: cannot tell the trajectory format: the first data line has {len(fields)} fields "
        f"({line[:80]!r}); tried {tried} (give the format: `correct --format`, `diagnose --gt-format`, or format= "
        f"in the API)"
    )


G2O_HINT = ("a g2o pose graph (VERTEX_/EDGE_ lines), not a trajectory: driftmap reads g2o files as pose graphs "
            "(driftmap.posegraph.PoseGraph.from_g2o); optimise it there and give its poses as a TUM, KITTI or 4x4 "
            "trajectory file")
"""What a trajectory reader says of a g2o file (hostile trial 25 W2: "expected 8 columns")."""


def read_trajectory(path: str | Path, format: str | None = None) -> Trajectory:
    """Read a TUM, KITTI, EuRoC, Redwood ``.log`` or ``4x4`` trajectory; ``format=None`` detects it from the
    contents. A row that jumps away from both neighbours and back (:func:`spike_rows`) is logged naming its line."""
    readers = {"tum": read_tum, "kitti": read_kitti, "euroc": read_euroc, "redwood": read_redwood_log,
               "4x4": read_matrix4x4}
    if format is None:
        format = detect_trajectory_format(path)
    if format not in readers:
        raise SourceError(f"{path}: unknown trajectory format {format!r}; known: {', '.join(readers)}")
    try:
        trajectory = readers[format](path)
    except SourceError as exc:
        hint = _other_format_hint(Path(path), format)
        if hint is None:
            raise
        raise SourceError(f"{exc}; {hint}") from exc
    warn_spikes(Path(path), trajectory.poses, trajectory.source_lines)
    warn_rows(Path(path), trajectory.poses, trajectory.stamps_ns, trajectory.source_lines,
              stamped=has_stamps(trajectory, format))
    return trajectory


def _other_format_hint(path: Path, format: str) -> str | None:
    """When a file refused as ``format`` looks like another trajectory format: which (trial 17 W5: a EuRoC file read
    as TUM got a seconds-versus-nanoseconds question, not the format)."""
    try:
        detected = detect_trajectory_format(path)
    except SourceError as exc:
        return G2O_HINT if G2O_HINT in str(exc) else None
    if detected == format:
        return None
    return (f"the file looks like a {detected} trajectory ({TRAJECTORY_FORMATS[detected]}), not {format}: give its "
            f"format ({detected!r})")
