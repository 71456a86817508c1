"""Trajectory files: TUM (``stamp tx ty tz qx qy qz qw``) and KITTI (3x4 row-major per line).

Readers return a :class:`Trajectory` (stamps in int nanoseconds, poses as 4x4 float64); writers take one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap.errors import SourceError


@dataclass(frozen=True, slots=True)
class Trajectory:
    """A sequence of poses ``T_world_x`` with stamps (ns) and, optionally, the frame ids they belong to."""

    stamps_ns: NDArray[np.int64]
    poses: NDArray[np.float64]  # (N, 4, 4)
    frame_ids: NDArray[np.int64] | None = None

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


def _stamp_s_to_ns(text: str) -> int:
    """Seconds as written in a file -> int ns, exactly (no float rounding of the decimal digits)."""
    text = text.strip()
    negative = text.startswith("-")
    if negative:
        text = text[1:]
    if "e" in text.lower():
        value = round(float(text) * 1e9)
    else:
        whole, _, frac = text.partition(".")
        value = int(whole or "0") * 1_000_000_000 + int((frac + "000000000")[:9] or "0")
    return -value if negative else value


def _format_stamp_ns(stamp_ns: int) -> str:
    sign = "-" if stamp_ns < 0 else ""
    s, ns = divmod(abs(int(stamp_ns)), 1_000_000_000)
    return f"{sign}{s}.{ns:09d}"


def _poses_from_rows(path: Path, translation_m: NDArray[np.float64], quat_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 4, 4) poses from translations and unit quaternions; a non-unit quaternion names its data row."""
    norms = np.linalg.norm(quat_xyzw, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if bad.size:
        raise SourceError(f"{path}: quaternion on data row {bad[0] + 1} has norm {norms[bad[0]]:.4f}, expected 1")
    poses = np.tile(np.eye(4), (len(translation_m), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(quat_xyzw).as_matrix()
    poses[:, :3, 3] = translation_m
    return poses


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file; comment lines start with ``#``."""
    path = Path(path)
    stamps: list[int] = []
    rows: list[list[float]] = []
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise SourceError(f"{path}: cannot read TUM trajectory ({exc})") from exc
    for lineno, line in enumerate(lines, start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise SourceError(f"{path}:{lineno}: expected 8 columns 'stamp tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            stamps.append(_stamp_s_to_ns(parts[0]))
            rows.append([float(p) for p in parts[1:]])
        except ValueError as exc:
            raise SourceError(f"{path}:{lineno}: not a number ({exc})") from exc
    if not rows:
        raise SourceError(f"{path}: no poses in TUM file")
    data = np.asarray(rows)
    return Trajectory(np.asarray(stamps, dtype=np.int64), _poses_from_rows(path, data[:, :3], data[:, 3:7]))


def write_tum(path: str | Path, trajectory: Trajectory) -> None:
    """Write a TUM file (stamps in seconds with nanosecond digits, quaternions ``qx qy qz qw``)."""
    quat = Rotation.from_matrix(trajectory.poses[:, :3, :3]).as_quat()
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, T, q in zip(trajectory.stamps_ns, trajectory.poses, quat, strict=True):
        t = T[:3, 3]
        lines.append(f"{_format_stamp_ns(int(stamp))} " + " ".join(f"{v:.9f}" for v in (*t, *q)))
    Path(path).write_text("\n".join(lines) + "\n")


def read_kitti(path: str | Path) -> Trajectory:
    """Read a KITTI pose file (12 numbers per line, the top 3x4 of ``T_world_x``); stamps are row indices."""
    path = Path(path)
    try:
        data = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise SourceError(f"{path}: cannot read KITTI poses ({exc})") from exc
    if data.shape[1] != 12:
        raise SourceError(f"{path}: expected 12 columns per KITTI pose row, got {data.shape[1]}")
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :] = data.reshape(-1, 3, 4)
    ids = np.arange(len(data), dtype=np.int64)
    return Trajectory(ids.copy(), poses, ids)


def write_kitti(path: str | Path, trajectory: Trajectory) -> None:
    """Write one 3x4 row-major line per pose."""
    rows = trajectory.poses[:, :3, :].reshape(-1, 12)
    np.savetxt(path, rows, fmt="%.9e")


# ---- EuRoC, Redwood .log, and format detection -----------------------------------------------------------------

#: Formats :func:`read_trajectory` knows, with what their lines look like (used in error messages).
TRAJECTORY_FORMATS = {
    "tum": "'stamp_s tx ty tz qx qy qz qw' (8 columns, stamp in seconds)",
    "kitti": "12 numbers per line (3x4 row-major T_world_x, one line per frame)",
    "euroc": "CSV 'stamp_ns, px, py, pz, qw, qx, qy, qz, ...' (integer ns stamp, quaternion w first)",
    "redwood": "blocks of an 'i j n' line + 4 lines of a 4x4 matrix (.log)",
}


def read_euroc(path: str | Path) -> Trajectory:
    """Read an EuRoC ground-truth CSV (``#timestamp [ns], p_RS_R_x, p_RS_R_y, p_RS_R_z, q_RS_w, q_RS_x, q_RS_y,
    q_RS_z, ...``): poses ``T_R_S`` (body ``S`` in the world ``R``); columns after the quaternion are ignored.

    The quaternion is stored **w first**; it is reordered to scipy's ``(x, y, z, w)`` here.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise SourceError(f"{path}: cannot read EuRoC trajectory ({exc})") from exc
    stamps: list[int] = []
    rows: list[list[float]] = []
    for lineno, line in enumerate(lines, start=1):
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
    if not rows:
        raise SourceError(f"{path}: no poses in EuRoC file")
    data = np.asarray(rows)
    quat_wxyz = data[:, 3:7]
    return Trajectory(np.asarray(stamps, dtype=np.int64), _poses_from_rows(path, data[:, :3], quat_wxyz[:, [1, 2, 3, 0]]))


def read_redwood_log(path: str | Path) -> Trajectory:
    """Read a Redwood / Open3D ``.log`` trajectory: per pose an ``i j n`` line and 4 lines of a 4x4 matrix.

    ``frame_ids`` are the first number of each header line; the format has no time, so ``stamps_ns`` are the
    frame ids (as :func:`read_kitti` uses row indices). Each matrix must be rigid (within the tolerance of
    :func:`driftmap.geometry.as_rigid`, which also projects it onto SO(3)).
    """
    from driftmap import geometry
    from driftmap.errors import TransformError

    path = Path(path)
    try:
        raw = path.read_text().splitlines()
    except OSError as exc:
        raise SourceError(f"{path}: cannot read Redwood .log trajectory ({exc})") from exc
    lines = [(n, line.split()) for n, line in enumerate(raw, start=1) if line.strip()]
    if not lines:
        raise SourceError(f"{path}: no poses in Redwood .log file")
    if len(lines) % 5:
        raise SourceError(
            f"{path}: {len(lines)} non-empty lines is not a multiple of 5 (an 'i j n' line + 4 matrix rows per pose)"
        )
    ids: list[int] = []
    poses: list[np.ndarray] = []
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


def _first_data_lines(path: Path, n: int = 5) -> list[str]:
    """The first ``n`` non-empty lines that are not ``#`` comments (reads only the head of the file)."""
    out: list[str] = []
    with path.open("r", errors="replace") as fh:
        for line in fh:
            line = line.strip()
            if line and not line.startswith("#"):
                out.append(line)
                if len(out) >= n:
                    break
    return out


def detect_trajectory_format(path: str | Path) -> str:
    """Tell TUM / KITTI / EuRoC / Redwood ``.log`` apart from the first lines of ``path``.

    Raises :class:`SourceError` naming every format tried and what the file looks like when none fits.
    """
    path = Path(path)
    try:
        head = _first_data_lines(path)
        with path.open("r", errors="replace") as fh:
            first_line = fh.readline()
    except OSError as exc:
        raise SourceError(f"{path}: cannot read trajectory file ({exc})") from exc
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
    is_int = all(f.lstrip("-").isdigit() for f in fields)
    if len(fields) == 3 and is_int and len(head) >= 2 and len(head[1].split()) == 4:
        return "redwood"
    if len(fields) == 12 and numeric(fields):
        return "kitti"
    if len(fields) == 8 and numeric(fields):
        return "tum"
    raise SourceError(
        f"{path}: cannot tell the trajectory format: the first data line has {len(fields)} fields "
        f"({line[:80]!r}); tried {tried} (pass format=)"
    )


def read_trajectory(path: str | Path, format: str | None = None) -> Trajectory:
    """Read a TUM, KITTI, EuRoC or Redwood ``.log`` trajectory; ``format=None`` detects it from the contents."""
    readers = {"tum": read_tum, "kitti": read_kitti, "euroc": read_euroc, "redwood": read_redwood_log}
    if format is None:
        format = detect_trajectory_format(path)
    if format not in readers:
        raise SourceError(f"{path}: unknown trajectory format {format!r}; known: {', '.join(readers)}")
    return readers[format](path)
