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
    quat = data[:, 3:7]
    norms = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if bad.size:
        raise SourceError(f"{path}: quaternion on data row {bad[0] + 1} has norm {norms[bad[0]]:.4f}, expected 1")
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(quat).as_matrix()
    poses[:, :3, 3] = data[:, :3]
    return Trajectory(np.asarray(stamps, dtype=np.int64), poses)


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
