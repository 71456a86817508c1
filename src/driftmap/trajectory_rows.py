"""Rows of a pose file that no motion explains, named when the file is read (they are used as written): a row
that jumps away from its neighbours and back (a *spike*), two rows of a stamped file too fast for the file's own
motion, a row of an index-matched file repeated exactly. (:func:`driftmap.trajectory.read_trajectory` calls them.)"""

from __future__ import annotations

import logging
from pathlib import Path
import numpy as np
from numpy.typing import NDArray

logger = logging.getLogger(__name__)


SPIKE_MIN_M = 0.5
SPIKE_FACTOR = 3.0
SPIKE_MIN_DEG = 30.0
"""A row is a **spike** when it lies more than ``max(SPIKE_MIN_M, SPIKE_FACTOR * (b + s))`` from both its neighbours,
``b`` the distance between the two neighbours and ``s`` the file's typical step (its lower quartile: a file whose every
third row is off still has its true steps there), or turns more than ``max(SPIKE_MIN_DEG, SPIKE_FACTOR * (b + s))``
degrees from both (the same in angles): a jump away and straight back that no vehicle makes (hostile trial 14 W5: one
row at 1e8 m among 24 cm steps; trial 15: 2.7 m, a 170 deg flip). A U-turn or a real fast motion keeps the distance
from a neighbour within about ``b + s``. The first and last rows are judged against the step beyond their one
neighbour the same way."""


def _spikes(values_away: NDArray[np.float64], base: NDArray[np.float64], typical: float,
            floor: float) -> NDArray[np.bool_]:
    with np.errstate(over="ignore", invalid="ignore"):
        return values_away > np.maximum(floor, SPIKE_FACTOR * (base + typical))


def spike_rows(positions_m: NDArray[np.floating],
               rotations: NDArray[np.floating] | None = None) -> NDArray[np.int64]:
    """Rows (indices) of ``positions_m`` (and of the ``(N, 3, 3)`` ``rotations``, when given) that jump away from
    their neighbours and back (:data:`SPIKE_FACTOR`)."""
    p = np.asarray(positions_m, dtype=np.float64)
    n = len(p)
    if n < 3:
        return np.zeros(0, dtype=np.int64)
    flagged = np.zeros(n, dtype=bool)
    with np.errstate(over="ignore", invalid="ignore"):
        def dist(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
            return np.linalg.norm(a - b, axis=-1)

        measures = [(dist, p, SPIKE_MIN_M)]
        if rotations is not None:
            R = np.asarray(rotations, dtype=np.float64)

            def turn(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
                cos = (np.einsum("nij,nij->n", a, b) - 1.0) / 2.0
                return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))

            measures.append((turn, R, SPIKE_MIN_DEG))
        for measure, x, floor in measures:
            steps = measure(x[1:], x[:-1])
            typical = float(np.percentile(steps, 25))
            away = np.minimum(measure(x[1:-1], x[:-2]), measure(x[1:-1], x[2:]))
            flagged[1:-1] |= _spikes(away, measure(x[2:], x[:-2]), typical, floor)
            # the ends: away from their one neighbour, against that neighbour's next step
            flagged[0] |= bool(_spikes(steps[:1], steps[1:2], typical, floor)[0])
            flagged[-1] |= bool(_spikes(steps[-1:], steps[-2:-1], typical, floor)[0])
    return np.flatnonzero(flagged).astype(np.int64)


def warn_spikes(path: Path, poses: NDArray[np.float64], source_lines: NDArray[np.int64] | None) -> None:
    """Log the rows of a pose file (``poses``: its ``(N, 4, 4)`` rows; ``source_lines``: their 1-based lines) that
    jump away from their neighbours and back (:func:`spike_rows`)."""
    p, R = poses[:, :3, 3], poses[:, :3, :3]
    rows = spike_rows(p, R)
    if not rows.size:
        return
    k = int(rows[0])
    line = _line_of(path, source_lines, k)
    near = k - 1 if k > 0 else k + 1
    turned = float(np.degrees(np.arccos(np.clip((np.trace(R[k].T @ R[near]) - 1.0) / 2.0, -1.0, 1.0))))
    logger.warning("%s: the pose jumps %.3g m / %.3g deg away from its neighbour and back (the file's typical step is "
                   "%.3g m): a corrupt row? (%d such row(s)%s; they are used as written)", line,
                   float(np.linalg.norm(p[k] - p[near])), turned,
                   float(np.percentile(np.linalg.norm(np.diff(p, axis=0), axis=1), 25)), rows.size,
                   "" if rows.size == 1 else f": rows {', '.join(str(int(r) + 1) for r in rows[:5])}"
                   + (" ..." if rows.size > 5 else ""))


ROW_SPEED_FACTOR = 20.0
ROW_SPEED_MIN_M_PER_S = 10.0
ROW_SPEED_MIN_STEP_M = 0.05
"""Two consecutive rows of a stamped pose file are **too fast** when the step between them (at least
``ROW_SPEED_MIN_STEP_M``) over their stamps' difference exceeds ``max(ROW_SPEED_MIN_M_PER_S, ROW_SPEED_FACTOR *`` the
file's 90th-percentile speed``)`` (hostile trial 17 W1: a row 1.5 ms and 0.5 m from the next, 333 m/s in a room)."""


def _line_of(path: Path, source_lines: NDArray[np.int64] | None, k: int) -> str:
    return f"{path}:{int(source_lines[k])}" if source_lines is not None else f"{path} (row {k + 1})"


def warn_rows(path: Path, poses: NDArray[np.float64], stamps_ns: NDArray[np.int64],
              source_lines: NDArray[np.int64] | None, stamped: bool) -> None:
    """Rows that no motion explains, logged naming their lines (they are used as written): in a stamped file two rows
    too fast for the file's own motion (:data:`ROW_SPEED_FACTOR`: two poses for one time?); in a file matched by row
    index or frame id (KITTI, Redwood, an unstamped 4x4) a row repeated exactly while the rest moves, which puts every later row a frame late (hostile
    trial 17 W1: both read "given poses fit the frames: yes")."""
    p, n = poses[:, :3, 3], len(poses)
    if n < 3:
        return
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    if stamped:
        dt_s = np.diff(stamps_ns).astype(np.float64) * 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            speed = np.where(dt_s > 0, steps / dt_s, np.nan)
        if not np.isfinite(speed).any():
            return
        limit = max(ROW_SPEED_MIN_M_PER_S, ROW_SPEED_FACTOR * float(np.nanpercentile(speed, 90)))
        fast = np.flatnonzero((speed > limit) & (steps >= ROW_SPEED_MIN_STEP_M))
        if fast.size:
            k = int(fast[0])
            logger.warning("%s and the next row are %.3g ms but %.3g m apart (%.3g m/s; the file's 90th-percentile "
                           "speed is %.3g m/s): two poses for one time, or a corrupt stamp? (%d such pair(s); the row "
                           "nearest a frame's stamp is used)", _line_of(path, source_lines, k), 1e3 * dt_s[k],
                           steps[k], speed[k], float(np.nanpercentile(speed, 90)), fast.size)
        return
    flat = poses.reshape(n, 16)
    same = np.flatnonzero(np.all(flat[1:] == flat[:-1], axis=1))
    if same.size and same.size < n - 1 and float(np.median(steps)) > 0.0:
        k = int(same[0])
        logger.warning("%s and the next row hold the same pose while the trajectory moves: a repeated row? Matched by "
                       "row index, every later row would be a frame late (%d such pair(s))", _line_of(path, source_lines, k),
                       same.size)
