"""The trajectory's jumps for the revisit check (:mod:`driftmap.diagnostics.revisits`): consecutive frames whose
relative motion differs from their neighbours' (:func:`find_jumps`), ranked frame on frame when there are more than
the check registers (:func:`screen_jump`), and the hypothesis that a jump is a pose error (:func:`undo_jump`)."""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.diagnostics.revisit_config import HYPOTHESIS_WITHIN, MIN_PROBE_POINTS, RevisitCheckConfig
from driftmap.diagnostics.samples import PlacedCloud
from driftmap.registration.pairwise import PreparedCloud, downsample, nearest_distances, register_prepared

logger = logging.getLogger(__name__)

MAX_SCREENED_JUMPS = 24
"""When more jumps exceed ``jump_min_share`` than ``max_step_checks`` allows, the largest this many are screened frame
on frame (:func:`_screen_jump`, ~2 registrations of two frames' samples each) and the most disagreeing checked."""


@dataclass(frozen=True)
class StepJump:
    """Consecutive frames whose relative motion differs from their neighbours' (:func:`find_jumps`)."""

    before_frame_id: int
    frame_id: int
    excess_m: float
    """How far the step between the two sensor origins differs from the neighbouring steps' median (m)."""
    excess_deg: float
    """How far the turn between the two frames exceeds the neighbouring turns' median (deg)."""
    implausible: bool
    """Larger than ``implausible_factor`` times the log's 90th-percentile motion between consecutive frames."""

    def to_json(self) -> dict:
        return {"before_frame_id": self.before_frame_id, "frame_id": self.frame_id,
                "excess_m": round(self.excess_m, 5), "excess_deg": round(self.excess_deg, 4), "implausible": self.implausible}


def find_jumps(placed: PlacedCloud, rows: NDArray[np.int64], cfg: RevisitCheckConfig,
                sessions: NDArray[np.int64] | None = None) -> list[tuple[int, StepJump]]:
    """``[(k, jump)]``: up to ``max_step_checks`` consecutive frames ``rows[k - 1]``, ``rows[k]`` whose relative motion
    differs from their neighbours' (the median over three steps either side) by at least ``jump_min_share`` of
    ``max_detectable_m`` or ``max_detectable_deg``, the largest (relative to those) first. A step or a turn that a bad
    correction put between two frames shows here as a jump of the trajectory; a fast but real motion does too, and
    registering the frames after it onto those before it tells the two apart (its frames fit as placed). A merged
    store's step from one session's last frame to the next session's first (``sessions``: each row's session) is no
    motion: neither a jump nor a neighbour of one."""
    n = len(rows)
    if cfg.max_step_checks == 0 or n < 3:
        return []
    poses = placed.poses[rows]
    # step[k - 1]: from rows[k - 1] to rows[k], in the frame of rows[k - 1]: a robot turning at a steady rate makes
    # the same relative step every frame, while its world-frame steps turn with it (hostile trial 28 W4: a synthetic
    # room turning 20 deg per frame read as a 64 cm "jump" at every other frame, and a registration that slid on it
    # as "a pose error there")
    step = np.einsum("kji,kj->ki", poses[:-1, :3, :3], np.diff(poses[:, :3, 3], axis=0))
    turn = np.degrees(geometry.relative_rotation_angle_rad(poses[:-1], poses[1:]))
    half = 3
    index = np.clip(np.arange(len(step))[:, None] + np.r_[-half:0, 1:half + 1][None, :], 0, len(step) - 1)
    own = index == np.arange(len(step))[:, None]  # a clipped neighbour that is the step itself does not count
    across = np.zeros(len(step), dtype=bool) if sessions is None else sessions[rows[1:]] != sessions[rows[:-1]]
    own |= across[index]
    nb_step = np.where(own[..., None], np.nan, step[index])
    nb_turn = np.where(own, np.nan, turn[index])
    with np.errstate(all="ignore"), warnings.catch_warnings():  # a step with no neighbour (a session's only one)
        warnings.simplefilter("ignore", RuntimeWarning)              # has no median: NaN, then 0 (trial 14)
        excess_m = np.linalg.norm(step - np.nanmedian(nb_step, axis=1), axis=1)
        excess_deg = np.clip(turn - np.nanmedian(nb_turn, axis=1), 0.0, None)
    excess_m, excess_deg = np.nan_to_num(excess_m), np.nan_to_num(excess_deg)
    score = np.where(across, -np.inf, np.maximum(excess_m / cfg.max_detectable_m, excess_deg / cfg.max_detectable_deg))
    if across.all():
        return []
    usual_m = float(np.percentile(np.linalg.norm(step[~across], axis=1), 90))
    usual_deg = float(np.percentile(turn[~across], 90))
    order = [int(i) for i in np.argsort(-score, kind="stable")[:MAX_SCREENED_JUMPS] if score[i] >= cfg.jump_min_share]
    if len(order) > cfg.max_step_checks:  # more jumps than checks: in turn the most disagreeing frame on frame
        screened = {i: screen_jump(placed, rows, i + 1, cfg) for i in order}  # (trial 13) and the largest jump (a
        by_screen = sorted(order, key=lambda i: -screened[i])                  # step two frames cannot constrain:
        order = list(dict.fromkeys(i for pair in zip(by_screen, order) for i in pair))  # trial 12's short log)
        logger.info("revisit check: %d jumps screened frame on frame (%s)", len(screened),
                    ", ".join(f"{int(placed.frame_ids[rows[i + 1]])}: {screened[i]:.2f}" for i in by_screen))
    out = []
    for i in order[: cfg.max_step_checks]:
        implausible = bool(excess_m[i] > cfg.implausible_factor * usual_m or excess_deg[i] > cfg.implausible_factor * usual_deg)
        jump = StepJump(int(placed.frame_ids[rows[i]]), int(placed.frame_ids[rows[i + 1]]), float(excess_m[i]),
                        float(excess_deg[i]), implausible)
        out.append((int(i + 1), jump))
    if out:
        logger.info("revisit check: %d jumps of the trajectory checked (%s)", len(out),
                    ", ".join(f"{j.before_frame_id}->{j.frame_id}" for _, j in out))
    return sorted(out, key=lambda kj: kj[0])


def screen_jump(placed: PlacedCloud, rows: NDArray[np.int64], k: int, cfg: RevisitCheckConfig) -> float:
    """How much frame ``rows[k]`` alone disagrees with frame ``rows[k - 1]`` where they are placed, as a share of the
    detectable error (the larger of metres and degrees): the frame registered onto the one before it from the poses as
    placed and from the jump undone (:func:`undo_jump`), refined locally, the hypothesis fitting more kept. A real
    turn fits as placed (0); a pose error fits undone (its size). Cheap (two frames' samples) where the full check
    registers a stretch: it ranks the jumps when there are more than ``max_step_checks`` (trial 13: a street's ten
    real turns of 3-7 deg crowded out a 3 deg pose step). A pair that does not count ranks by its jump alone (-1)."""
    offsets = placed.samples.offsets
    a, b = int(rows[k - 1]), int(rows[k])
    v = cfg.registration_voxel_m
    target = downsample(placed.points_world[offsets[a]:offsets[a + 1]], v)
    source = downsample(placed.points_world[offsets[b]:offsets[b + 1]], v)
    if len(target) < MIN_PROBE_POINTS or len(source) < MIN_PROBE_POINTS:
        return -1.0
    tgt, src = PreparedCloud(target, 1), PreparedCloud(source, 1)
    best: tuple[float, NDArray[np.float64]] | None = None
    for start in (np.eye(4), undo_jump(placed, rows, k)):
        T, result = start, None
        for level, gate in ((2 * v, 3 * v), (v, 2.5 * v)):
            result = register_prepared(tgt, src, T, voxel_size_m=level, max_correspondence_m=gate, num_threads=1)
            T = result.T_target_source
        share = float(np.mean(nearest_distances(tgt, src, T, v) <= HYPOTHESIS_WITHIN * v))
        if result is not None and result.fitness >= cfg.min_fitness and (best is None or share > best[0]):
            best = (share, T)
    if best is None:
        return -1.0
    T = best[1]
    origin = placed.origins_world[b]
    moved_m = float(np.linalg.norm(T[:3, :3] @ origin + T[:3, 3] - origin))
    return max(moved_m / cfg.max_detectable_m, float(geometry.rotation_angle_deg(np.eye(4), T)) / cfg.max_detectable_deg)


def undo_jump(placed: PlacedCloud, rows: NDArray[np.int64], k: int) -> NDArray[np.float64]:
    """The world correction that would put frame ``rows[k]`` where the motion of the frames before it predicts
    (constant velocity from ``rows[k - 2]`` to ``rows[k - 1]``; standing still after the first frame): the start of a
    second hypothesis of a jump, that it is a pose error."""
    before = placed.poses[rows[k - 1]]
    velocity = np.linalg.inv(placed.poses[rows[k - 2]]) @ before if k >= 2 else np.eye(4)
    return before @ velocity @ np.linalg.inv(placed.poses[rows[k]])
