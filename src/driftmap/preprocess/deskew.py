"""Deskew: the points of a moving LiDAR's scan placed with the pose of the instant each was seen.

A spinning or non-repetitive LiDAR takes its scan over tens to hundreds of milliseconds; a point seen ``t`` after
the frame's stamp was seen from ``T_world_sensor(stamp + t)``, not from the frame's pose. Stored frames keep their
raw sensor-frame points and per-point times (``PointAttributes.time_offset_ns``, relative to the stamp); the map
view places them with the revision's *continuous* trajectory: between a frame's pose and the next frame's, the motion
is taken as constant (``T(stamp + t) = T_k exp((t / dt) log(T_k^-1 T_k+1))``, the last frame extrapolates the motion
before it). A correction that moves a frame or its neighbour therefore also re-deskews it, as a rebuild from the
corrected trajectory would.

Convention: a frame's pose is the pose at its stamp. KISS-ICP's pose of a scan is that of the scan's middle; the
odometry (:class:`driftmap.registration.odometry.KissOdometry`) moves it to the stamp with its motion model before
storing it.

A frame that cannot be deskewed (no neighbour, a gap longer than :data:`MAX_GAP_NS`, times spanning more than the
gap to the neighbour) is placed rigidly, and :func:`scan_motion` says why; the map view keeps the reason per frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry

logger = logging.getLogger(__name__)

MAX_GAP_NS = 2_000_000_000
"""Frames further apart than this (2 s) do not deskew each other: the motion between them is not one scan's."""
MAX_SPAN_OVER_GAP = 1.5
"""A scan whose per-point times span more than this times the gap to its neighbour is not this trajectory's scan."""


@dataclass(frozen=True, slots=True)
class ScanMotion:
    """The constant motion ``xi`` (twist ``[rho, phi]`` in the sensor frame at the stamp) over ``dt_ns``."""

    xi: NDArray[np.float64]
    dt_ns: int
    neighbour_row: int
    extrapolated: bool


def scan_motion(stamps_ns: NDArray[np.int64], poses: NDArray[np.float64], row: int, order: NDArray[np.int64],
                rank: NDArray[np.int64], offsets_span_ns: int) -> tuple[ScanMotion | None, str]:
    """The motion that deskews frame ``row``: towards the next frame in time (``order``: rows by stamp, ``rank``:
    each row's place in it), or the previous frame's motion extrapolated for the last one. ``(None, reason)`` when
    there is none to trust."""
    k = int(rank[row])
    if len(order) < 2:
        return None, "no other frame: the motion during its scan is unknown"
    extrapolated = k + 1 >= len(order)
    a, b = (int(order[k - 1]), row) if extrapolated else (row, int(order[k + 1]))
    dt = int(stamps_ns[b]) - int(stamps_ns[a])
    if dt <= 0:
        return None, f"its neighbour in time has the same stamp ({stamps_ns[a]} ns)"
    if dt > MAX_GAP_NS:
        return None, f"the nearest frame in time is {dt / 1e9:.2f} s away (more than {MAX_GAP_NS / 1e9:g} s)"
    if offsets_span_ns > MAX_SPAN_OVER_GAP * dt:
        return None, (f"its per-point times span {offsets_span_ns / 1e6:.1f} ms, more than {MAX_SPAN_OVER_GAP:g} x the "
                      f"{dt / 1e6:.1f} ms to its neighbour")
    delta = geometry.invert(poses[a]) @ poses[b]
    xi = geometry.se3_log(delta)
    if not np.all(np.isfinite(xi)):
        return None, "the motion to its neighbour is not finite"
    return ScanMotion(xi, dt, a if extrapolated else b, extrapolated), ""


def point_motions(offsets_ns: NDArray[np.integer], xi: NDArray[np.float64], dt_ns: int) -> NDArray[np.float64]:
    """(n, 4, 4) ``exp((t_i / dt) xi)``: where each point of a scan was seen from, relative to the frame's pose."""
    alpha = np.asarray(offsets_ns, dtype=np.float64) / float(dt_ns)
    return geometry.se3_exp(alpha[:, None] * np.asarray(xi, dtype=np.float64)[None, :])


def deskew_to_world(points_sensor: NDArray[np.floating], offsets_ns: NDArray[np.integer],
                    T_world_sensor: NDArray[np.float64], motion: ScanMotion) -> NDArray[np.float32]:
    """World points of one scan: point ``i`` placed with ``T_world_sensor @ exp((t_i / dt) xi)`` (float64 products,
    float32 result)."""
    p = np.asarray(points_sensor, dtype=np.float64)
    D = point_motions(offsets_ns, motion.xi, motion.dt_ns)
    local = np.einsum("nij,nj->ni", D[:, :3, :3], p) + D[:, :3, 3]
    T = np.asarray(T_world_sensor, dtype=np.float64)
    return (local @ T[:3, :3].T + T[:3, 3]).astype(np.float32)

