"""How the synthetic robot moves: its path, the scan schedule, and the continuous-time ground truth.

The path is the room's circle or the street's rounded rectangle (:func:`street_path`), driven ``loop_turns`` times.
The log's ``n_frames`` stamps ``start_stamp_ns + k * frame_period_ns`` split time into scans: scan ``k`` runs
from stamp ``k`` to stamp ``k + 1``, and during it the robot does one of three things (:class:`ScanMotion`):

- ``move``: it advances one step along the path (every moving scan the same arc, so the speed is constant);
- ``still``: it stands (the stationary start, the stops);
- ``turn``: it turns in place about its z axis by ``turn_in_place_deg_per_frame``.

Within a scan the motion is uniform in time (the arc and the yaw grow linearly from the scan's stamp to the next),
so :func:`base_poses_at` gives ``T_world_base`` at any instant, not only at the stamps. The last scan has no next
stamp: it continues the motion of the scan before it.

Where the events happen (:func:`motion_schedule`): the stationary start before the first step; the ``stops`` at
the fractions ``j / (stops + 1)`` of the moving path; the in-place turns at the fractions ``turn_in_place_at``, or
``j / (turns_in_place + 1)``. A turn lasts ``turn_in_place_frames`` scans; when that is not a whole number of
turns (``turn_in_place_frames * turn_in_place_deg_per_frame`` not a multiple of 360 deg) the robot turns back the
same way (as many scans at the opposite rate), so after every turn it heads along the path again and the loop
stays a loop.
"""

from __future__ import annotations

import enum
import math
from collections import defaultdict
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap.errors import ConfigError

SyntheticLogConfig = Any
"""A :class:`driftmap.sources.synthetic.SyntheticLogConfig` (not imported here: that module imports this one)."""

STREET_HALF_SIZE_M = (35.0, 25.0)
"""Half the size of the street loop's rounded rectangle (x, y), centreline of the road."""
STREET_CORNER_RADIUS_M = 10.0
STREET_PERIMETER_M = float(4 * (STREET_HALF_SIZE_M[0] - STREET_CORNER_RADIUS_M)
                           + 4 * (STREET_HALF_SIZE_M[1] - STREET_CORNER_RADIUS_M) + 2 * math.pi * STREET_CORNER_RADIUS_M)


class ScanMotion(str, enum.Enum):
    """What the robot does during one scan (from its stamp to the next)."""

    MOVE = "move"
    STILL = "still"
    TURN = "turn"


def street_path(s_m: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(xy, heading)`` at arc lengths ``s_m`` along the street loop: the rounded rectangle of
    :data:`STREET_HALF_SIZE_M` and :data:`STREET_CORNER_RADIUS_M`, counter-clockwise from the middle of its
    -y side (heading +x)."""
    a, b = STREET_HALF_SIZE_M
    r = STREET_CORNER_RADIUS_M
    # (length, start xy, start heading, curvature) of the nine pieces
    pieces = [(a - r, (0.0, -b), 0.0, 0.0), (math.pi * r / 2, (a - r, -b), 0.0, 1 / r),
              (2 * (b - r), (a, -b + r), math.pi / 2, 0.0), (math.pi * r / 2, (a, b - r), math.pi / 2, 1 / r),
              (2 * (a - r), (a - r, b), math.pi, 0.0), (math.pi * r / 2, (-a + r, b), math.pi, 1 / r),
              (2 * (b - r), (-a, b - r), 1.5 * math.pi, 0.0), (math.pi * r / 2, (-a, -b + r), 1.5 * math.pi, 1 / r),
              (a - r, (-a + r, -b), 0.0, 0.0)]
    perimeter = sum(p[0] for p in pieces)
    s = np.mod(np.asarray(s_m, dtype=np.float64), perimeter)
    xy = np.zeros((len(s), 2))
    heading = np.zeros(len(s))
    start = 0.0
    for length, (x0, y0), h0, kappa in pieces:
        on = (s >= start) & (s <= start + length)
        u = s[on] - start
        if kappa == 0.0:
            xy[on] = np.stack([x0 + u * math.cos(h0), y0 + u * math.sin(h0)], axis=1)
            heading[on] = h0
        else:  # a left turn of radius 1 / kappa
            h = h0 + u * kappa
            xy[on] = np.stack([x0 + (np.sin(h) - math.sin(h0)) / kappa, y0 - (np.cos(h) - math.cos(h0)) / kappa], axis=1)
            heading[on] = h
        start += length
    return xy, heading


def path_length_m(config: SyntheticLogConfig) -> float:
    """Length of the whole path (``loop_turns`` times round the circle or the block), metres."""
    if config.scene == "street":
        return STREET_PERIMETER_M * config.loop_turns
    return 2.0 * math.pi * config.circle_radius_m * config.loop_turns


def _path_total(config: SyntheticLogConfig) -> float:
    """The end of the path in its own parameter: an angle (rad) on the room's circle, an arc length (m) on the street."""
    if config.scene == "street":
        return STREET_PERIMETER_M * config.loop_turns
    return 2.0 * math.pi * config.loop_turns


def turns_full_circle(config: SyntheticLogConfig) -> bool:
    """Whether one in-place turn is a whole number of full turns (else the robot turns back after it)."""
    total = config.turn_in_place_frames * config.turn_in_place_deg_per_frame
    return abs(total / 360.0 - round(total / 360.0)) < 1e-9 and round(total / 360.0) != 0


def turn_fractions(config: SyntheticLogConfig) -> tuple[float, ...]:
    """Where on the moving path (fractions 0-1) the in-place turns happen."""
    if config.turn_in_place_at:
        return tuple(float(f) for f in config.turn_in_place_at)
    k = config.turns_in_place
    return tuple(j / (k + 1) for j in range(1, k + 1))


def stop_fractions(config: SyntheticLogConfig) -> tuple[float, ...]:
    """Where on the moving path (fractions 0-1) the stops happen: evenly spaced, ``j / (stops + 1)``."""
    return tuple(j / (config.stops + 1) for j in range(1, config.stops + 1))


def scans_per_turn(config: SyntheticLogConfig) -> int:
    """Scans one in-place turn lasts (with the turn back, if any)."""
    return config.turn_in_place_frames * (1 if turns_full_circle(config) else 2)


def non_moving_scans(config: SyntheticLogConfig) -> int:
    """Scans in which the robot does not advance along the path: the stationary start, the stops, the turns."""
    return (config.stationary_start_frames + config.stops * config.stop_frames
            + len(turn_fractions(config)) * scans_per_turn(config))


def moving_scans(config: SyntheticLogConfig) -> int:
    """Scans among the first ``n_frames - 1`` in which the robot advances (one equal step each)."""
    return config.n_frames - 1 - non_moving_scans(config)


def frames_for_speed(config: SyntheticLogConfig, speed_m_per_s: float) -> int:
    """The frame count at which the robot drives the whole path at ``speed_m_per_s`` (at least one step), with the
    stationary, stop and turn scans on top."""
    step_m = speed_m_per_s * config.frame_period_ns * 1e-9
    return 1 + max(1, int(math.floor(path_length_m(config) / step_m + 0.5))) + non_moving_scans(config)


@dataclass(frozen=True)
class MotionSchedule:
    """The motion of every scan of a log, and the robot's state at every stamp.

    ``path_index[k]`` counts the moving scans before stamp ``k`` (the robot is at step ``path_index[k]`` of
    ``n_moving`` along the path) and ``yaw_rad[k]`` is the in-place yaw it has turned by then (about its z axis, on
    top of the path's heading). Both have ``n_frames + 1`` entries: the last is one period after the last stamp."""

    kinds: tuple[ScanMotion, ...]
    path_index: NDArray[np.float64]
    yaw_rad: NDArray[np.float64]
    n_moving: int


def motion_schedule(config: SyntheticLogConfig) -> MotionSchedule:
    """The scan-by-scan motion of a log (the module docstring says where the events happen)."""
    n_moving = moving_scans(config)
    if n_moving < 1:
        raise ConfigError(f"n_frames: {config.n_frames} frames leave {n_moving} moving scans after the "
                          f"{non_moving_scans(config)} stationary, stop and turn scans; give more frames or a speed")
    events: defaultdict[int, list[tuple[float, float, ScanMotion]]] = defaultdict(list)

    def at(fraction: float) -> int:
        return int(math.floor(fraction * n_moving + 0.5))

    events[0] += [(0.0, 0.0, ScanMotion.STILL)] * config.stationary_start_frames
    for f in stop_fractions(config):
        events[at(f)] += [(0.0, 0.0, ScanMotion.STILL)] * config.stop_frames
    delta = math.radians(config.turn_in_place_deg_per_frame)
    for f in turn_fractions(config):
        events[at(f)] += [(0.0, delta, ScanMotion.TURN)] * config.turn_in_place_frames
        if not turns_full_circle(config):
            events[at(f)] += [(0.0, -delta, ScanMotion.TURN)] * config.turn_in_place_frames
    scans: list[tuple[float, float, ScanMotion]] = []
    for i in range(n_moving + 1):
        scans += events.get(i, [])
        if i < n_moving:
            scans.append((1.0, 0.0, ScanMotion.MOVE))
    scans.append(scans[-1] if scans else (1.0, 0.0, ScanMotion.MOVE))  # the last scan continues the one before
    steps = np.array([s[0] for s in scans])
    yaws = np.array([s[1] for s in scans])
    return MotionSchedule(
        kinds=tuple(s[2] for s in scans),
        path_index=np.concatenate([[0.0], np.cumsum(steps)]),
        yaw_rad=np.concatenate([[0.0], np.cumsum(yaws)]),
        n_moving=n_moving,
    )


def _path_values(config: SyntheticLogConfig, schedule: MotionSchedule, index: NDArray[np.float64]) -> NDArray[np.float64]:
    """The path parameter (angle on the circle, arc length on the street) at fractional step ``index``: at whole
    steps exactly the values of ``linspace(0, end, n_moving + 1)`` (the default logs' own), in between and past
    the end linear in the step."""
    total = _path_total(config)
    grid = np.linspace(0.0, total, schedule.n_moving + 1)
    whole = (index == np.floor(index)) & (index <= schedule.n_moving)
    values = total * index / schedule.n_moving
    values[whole] = grid[index[whole].astype(np.int64)]
    return values


def _base_poses(config: SyntheticLogConfig, path: NDArray[np.float64], yaw: NDArray[np.float64], *,
                per_pose: bool) -> NDArray[np.float64]:
    """``T_world_base`` at path parameters ``path`` with in-place yaws ``yaw``; ``per_pose`` builds the room's
    poses one by one (as the default log always did, so its bits stay the same)."""
    poses = np.tile(np.eye(4), (len(path), 1, 1))
    if config.scene == "street":
        xy, heading = street_path(path)
        poses[:, :3, :3] = Rotation.from_euler("z", (heading + yaw)[:, None]).as_matrix()
        poses[:, :2, 3] = xy
        return poses
    r = config.circle_radius_m
    if per_pose:
        for k, (a, psi) in enumerate(zip(path, yaw)):
            poses[k, :3, :3] = Rotation.from_euler("z", a + math.pi / 2 + psi).as_matrix()
            poses[k, :3, 3] = (r * math.cos(a), r * math.sin(a), 0.0)
        return poses
    poses[:, :3, :3] = Rotation.from_euler("z", (path + math.pi / 2 + yaw)[:, None]).as_matrix()
    poses[:, 0, 3] = r * np.cos(path)
    poses[:, 1, 3] = r * np.sin(path)
    return poses


def frame_base_poses(config: SyntheticLogConfig, schedule: MotionSchedule | None = None) -> NDArray[np.float64]:
    """``T_world_base`` at the ``n_frames`` stamps."""
    schedule = schedule or motion_schedule(config)
    n = config.n_frames
    return _base_poses(config, _path_values(config, schedule, schedule.path_index[:n].copy()), schedule.yaw_rad[:n],
                       per_pose=True)


def base_poses_at(config: SyntheticLogConfig, stamps_ns: NDArray[np.int64],
                  schedule: MotionSchedule | None = None) -> NDArray[np.float64]:
    """Ground-truth ``T_world_base`` at any ``stamps_ns`` from the first stamp to one period after the last: the
    continuous trajectory (uniform motion within each scan, along the path itself). At the frame stamps it is the
    ``groundtruth.txt`` pose of the frame (composed with ``T_base_camera``); the LiDAR point at offset ``t`` of scan
    ``k`` was measured from ``base_poses_at(stamp_k + t) @ T_base_lidar``."""
    schedule = schedule or motion_schedule(config)
    rel = np.asarray(stamps_ns, dtype=np.int64) - np.int64(config.start_stamp_ns)
    period = np.int64(config.frame_period_ns)
    k = rel // period
    if np.any(k < 0) or np.any(k >= config.n_frames):
        end_ns = config.start_stamp_ns + config.n_frames * config.frame_period_ns
        raise ConfigError(f"stamps_ns: outside the log's {config.n_frames} scans ({config.start_stamp_ns} to {end_ns} ns)")
    tau = (rel - k * period).astype(np.float64) / float(period)
    index = schedule.path_index[k] + tau * (schedule.path_index[k + 1] - schedule.path_index[k])
    yaw = schedule.yaw_rad[k] + tau * (schedule.yaw_rad[k + 1] - schedule.yaw_rad[k])
    return _base_poses(config, _path_values(config, schedule, index), yaw, per_pose=False)
