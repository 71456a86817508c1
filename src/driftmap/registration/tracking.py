"""Tracking health of a scan-to-map odometry, and the retry that survives fast turns and stops.

A constant-velocity prediction is the start of every frame-to-map registration (KISS-ICP's, and
:class:`~driftmap.registration.odometry.GicpMapOdometry`'s). Real robots break it: a scan after a 43 deg turn is
followed by one of 9 deg, a walk ends in a stop. The registration then starts tens of degrees off and ICP settles
in a wrong minimum that still matches a good part of the map; every later pose keeps the error (a real Livox log
went from 2.3 cm to 2.9 m ATE this way, docs/build.md).

This module measures each registration against the local map (:func:`fit_to_map`: the share of points with a map
point within a radius, their RMS distance, and the degeneracy of the point-to-plane information) and, when the
prediction's result fits clearly worse than the frames before it (or fits too little),
:func:`register_robustly` tries other initial guesses (zero motion, half the velocity, the prediction turned about
the sensor's up axis by +-15 / 30 / 45 deg) and keeps the one that fits best. No guess that fits: the frame is
lost (flagged, its pose bridged by the best guess, its scan kept out of the map).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import small_gicp
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.frame import TrackingHealth, TrackingStatus

logger = logging.getLogger(__name__)

UP_AXIS_LIDAR = (0.0, 0.0, 1.0)
"""A LiDAR's sensor frame is z-up (as Scan Context assumes)."""
UP_AXIS_OPTICAL = (0.0, -1.0, 0.0)
"""A camera's optical frame is y-down."""


@dataclass(frozen=True, slots=True)
class MapFit:
    """How registered points fit a map (see :func:`fit_to_map`)."""

    fitness: float
    rmse_m: float
    degeneracy: float | None


@dataclass(frozen=True, slots=True)
class Attempt:
    """One registration: the initial guess it started from and where it ended."""

    hypothesis: str
    T_init: NDArray[np.float64]
    T_world_sensor: NDArray[np.float64]
    fit: MapFit


def _unit_normals(neighbours: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, k, 3) neighbourhoods -> (M, 3) normals: the eigenvector of the smallest covariance eigenvalue."""
    centred = neighbours - neighbours.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", centred, centred)
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0]


def fit_to_map(points_world: NDArray[np.float64], map_points: NDArray[np.float64], tree: small_gicp.KdTree,
               radius_m: float, *, with_degeneracy: bool = False, num_threads: int = 1) -> MapFit:
    """Share of ``points_world`` with a map point within ``radius_m`` (``fitness``), the RMS distance of those
    (``rmse_m``) and, with ``with_degeneracy``, ``sqrt(lambda_min / lambda_max)`` of ``sum n n^T`` over the fitting
    points, ``n`` the map's normal at each (from its 8 nearest map points): 1 when the surfaces constrain every
    direction of translation alike, near 0 when one direction is free (a corridor, a single wall)."""
    if len(points_world) == 0 or len(map_points) == 0:
        return MapFit(0.0, 0.0, None)
    _, d2 = tree.batch_nearest_neighbor_search(points_world, num_threads=num_threads)
    d2 = np.asarray(d2, dtype=np.float64)
    inside = d2 <= radius_m * radius_m
    fitness = float(np.mean(inside))
    rmse = float(np.sqrt(np.mean(d2[inside]))) if inside.any() else 0.0
    degeneracy = None
    if with_degeneracy and np.count_nonzero(inside) >= 10 and len(map_points) >= 8:
        idx, _ = tree.batch_knn_search(points_world[inside], 8, num_threads=num_threads)
        normals = _unit_normals(map_points[np.asarray(idx)])
        degeneracy = translation_degeneracy(normals.T @ normals)
    return MapFit(fitness, rmse, degeneracy)


def translation_degeneracy(information_3x3: NDArray[np.float64]) -> float | None:
    """``sqrt(lambda_min / lambda_max)`` of a translational information block (None when it is empty)."""
    eig = np.linalg.eigvalsh(0.5 * (information_3x3 + information_3x3.T))
    if not np.all(np.isfinite(eig)) or eig[-1] <= 0:
        return None
    return float(np.sqrt(max(eig[0], 0.0) / eig[-1]))


def hessian_degeneracy(H: NDArray[np.float64]) -> float | None:
    """:func:`translation_degeneracy` of a small_gicp registration Hessian (tangent order rotation, translation)."""
    return translation_degeneracy(np.asarray(H, dtype=np.float64)[3:, 3:])


@dataclass(frozen=True, slots=True)
class WeakDirections:
    """What :func:`keep_prediction_along_weak_directions` replaced: the weak directions (unit vectors, world frame,
    one per row), the smallest degeneracy among them, and how far the registration had moved along them from the
    prediction (m)."""

    directions_world: NDArray[np.float64]
    degeneracy: float
    replaced_m: float

    def directions_text(self) -> str:
        """The weak directions as ``(x, y, z); ...`` for a frame's reason."""
        return "; ".join(f"({x:+.2f}, {y:+.2f}, {z:+.2f})" for x, y, z in self.directions_world)


def degenerate_status(status: TrackingStatus, reason: str, why: str) -> tuple[TrackingStatus, str]:
    """A frame bridged along weak directions (``why``): an ``ok`` one becomes ``degenerate``; another keeps its status
    with ``why`` added to its reason."""
    if status is TrackingStatus.OK:
        return TrackingStatus.DEGENERATE, why
    return status, f"{reason}; {why}" if reason else why


def keep_prediction_along_weak_directions(T: NDArray[np.float64], predicted: NDArray[np.float64],
                                          H: NDArray[np.float64], min_degeneracy: float
                                          ) -> tuple[NDArray[np.float64], WeakDirections | None]:
    """Solution remapping (Zhang, Kaess & Singh, "On degeneracy of optimization-based state estimation problems",
    ICRA 2016) on a registration's translation: along each eigenvector of the translational information block of
    ``H`` (a small_gicp Hessian: tangent order rotation, translation; a right perturbation, so in the sensor frame)
    whose ``sqrt(lambda / lambda_max)`` is below ``min_degeneracy``, the scan does not constrain the motion and the
    translation of ``T`` is replaced by the ``predicted`` pose's; the rotation and the constrained directions stay
    ``T``'s. Returns ``T`` unchanged and None when no direction is that weak (or the block is empty)."""
    info = np.asarray(H, dtype=np.float64)[3:, 3:]
    eig, vectors = np.linalg.eigh(0.5 * (info + info.T))
    if min_degeneracy <= 0 or not np.all(np.isfinite(eig)) or eig[-1] <= 0:
        return T, None
    ratio = np.sqrt(np.clip(eig, 0.0, None) / eig[-1])
    weak = ratio < min_degeneracy
    if not weak.any():
        return T, None
    R = T[:3, :3]
    d_sensor = R.T @ (T[:3, 3] - predicted[:3, 3])
    along = vectors[:, weak] @ (vectors[:, weak].T @ d_sensor)
    out = T.copy()
    out[:3, 3] = T[:3, 3] - R @ along
    return out, WeakDirections((R @ vectors[:, weak]).T, float(ratio[weak].min()), float(np.linalg.norm(along)))


def _turn(axis: Sequence[float], deg: float) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, dtype=np.float64)).as_matrix()
    return T


def half_motion(delta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Half of a rigid motion (half the rotation angle about the same axis, half the translation)."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(0.5 * Rotation.from_matrix(delta[:3, :3]).as_rotvec()).as_matrix()
    out[:3, 3] = 0.5 * delta[:3, 3]
    return out


def initial_guesses(last_pose: NDArray[np.float64], last_delta: NDArray[np.float64], up_axis: Sequence[float],
                    yaw_deg: Sequence[float]) -> list[tuple[str, NDArray[np.float64]]]:
    """The retry's initial guesses after the constant-velocity prediction ``last_pose @ last_delta``: zero motion,
    half the velocity, the prediction turned about the sensor's ``up_axis`` by each of +-``yaw_deg`` (``yaw+30``: a
    turn that sped up), and zero motion turned alike (``turn+30``: a vehicle that stopped and turns in place)."""
    predicted = last_pose @ last_delta
    guesses = [("zero_motion", last_pose.copy()), ("half_velocity", last_pose @ half_motion(last_delta))]
    for deg in yaw_deg:
        for sign in (1.0, -1.0):
            guesses.append((f"yaw{sign * deg:+g}", predicted @ _turn(up_axis, sign * deg)))
    for deg in yaw_deg:
        for sign in (1.0, -1.0):
            guesses.append((f"turn{sign * deg:+g}", last_pose @ _turn(up_axis, sign * deg)))
    return guesses


def deviation(predicted: NDArray[np.float64], T: NDArray[np.float64]) -> tuple[float, float]:
    """How far ``T`` is from ``predicted``: (metres, degrees)."""
    D = geometry.invert(predicted) @ T
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(geometry.relative_rotation_angle_rad(np.eye(3), D[:3, :3])))


@dataclass(frozen=True, slots=True)
class RetryPolicy:
    """When :func:`register_robustly` tries other initial guesses, and when it gives up (metres and degrees)."""

    min_fitness: float
    """below this no guess is trusted: the frame is lost"""
    retry_fitness_ratio: float
    """the prediction's result is retried when its fitness is below this share of the recent frames' median"""
    min_gain: float
    """another guess replaces the prediction's result only when it fits better by at least this (fitness)"""
    yaw_deg: tuple[float, ...]
    up_axis: tuple[float, float, float]
    retry: bool = True
    """False: only the prediction is registered (a poor fit is still lost)"""
    deviation_m: float = float("inf")
    deviation_deg: float = float("inf")
    """a registration that fits but ended this far from the prediction (ICP came a long way: a turn that stopped,
    a stop) is cross-checked from zero motion and half the velocity"""
    min_rmse_gain: float = 0.1
    max_attempts: int = 8
    """a retry registers from at most this many of the :func:`initial_guesses`: those that fit best before registering"""
    """... and another guess that fits as well (within ``min_gain``) replaces it when its RMSE is lower by this share"""

    def pick(self, attempts: Sequence[Attempt]) -> Attempt:
        """The attempt to keep: the first (the prediction's) unless another is :meth:`better`; among those that fit
        within ``min_gain`` of the best fitness, the one of lowest RMSE (the others stopped in a nearby, worse
        minimum: a turn registered from 23 deg off ended 6 cm away with the same fitness)."""
        first = attempts[0]
        challengers = [a for a in attempts[1:] if self.better(a, first)]
        if not challengers:
            return first
        top = max(a.fit.fitness for a in challengers)
        return min((a for a in challengers if a.fit.fitness >= top - self.min_gain), key=lambda a: a.fit.rmse_m)

    def better(self, a: Attempt, b: Attempt) -> bool:
        """``a`` fits the map clearly better than ``b``: more of its points by ``min_gain``, or as many with an RMSE
        lower by ``min_rmse_gain``."""
        if a.fit.fitness >= b.fit.fitness + self.min_gain:
            return True
        return a.fit.fitness > b.fit.fitness - self.min_gain and a.fit.rmse_m < (1.0 - self.min_rmse_gain) * b.fit.rmse_m


def register_robustly(align: Callable[[NDArray[np.float64]], NDArray[np.float64]],
                      evaluate: Callable[[NDArray[np.float64]], MapFit],
                      last_pose: NDArray[np.float64], last_delta: NDArray[np.float64], recent_fitness: Sequence[float],
                      policy: RetryPolicy, *, frame_id: int) -> tuple[Attempt, TrackingStatus, str, float, float]:
    """Register from the constant-velocity prediction and, when that result fits poorly (see :class:`RetryPolicy`),
    from the other :func:`initial_guesses`; ``align(T_init) -> T`` registers the scan, ``evaluate(T) -> MapFit``
    measures it against the map. Returns the kept attempt, its status (``OK``, ``RECOVERED`` or ``LOST``), the
    reason for a status other than ``OK``, and its deviation from the prediction (m, deg)."""
    predicted = last_pose @ last_delta
    T = align(predicted)
    best = Attempt("constant_velocity", predicted, T, evaluate(T))
    dev_m, dev_deg = deviation(predicted, T)
    median = float(np.median(recent_fitness)) if len(recent_fitness) else None
    why = []
    if median is not None and best.fit.fitness < policy.retry_fitness_ratio * median:
        why.append(f"fitness {best.fit.fitness:.2f} < {policy.retry_fitness_ratio:g} x the recent median {median:.2f}")
    if best.fit.fitness < policy.min_fitness:
        why.append(f"fitness {best.fit.fitness:.2f} < {policy.min_fitness:g}")
    if not why and policy.retry and (dev_m > policy.deviation_m or dev_deg > policy.deviation_deg):
        return _cross_check(align, evaluate, best, last_pose, last_delta, policy, frame_id, dev_m, dev_deg)
    if not why:
        return best, TrackingStatus.OK, "", dev_m, dev_deg
    if not policy.retry:
        if best.fit.fitness >= policy.min_fitness:
            return best, TrackingStatus.OK, "", dev_m, dev_deg
        reason = f"{'; '.join(why)} (retries are off)"
        logger.warning("frame %d: tracking lost: %s", frame_id, reason)
        return best, TrackingStatus.LOST, reason, dev_m, dev_deg
    tried = [best]
    guesses = initial_guesses(last_pose, last_delta, policy.up_axis, policy.yaw_deg)
    if len(guesses) > policy.max_attempts:  # register from the guesses that fit best as they are (cheap to measure)
        prefit = [evaluate(g).fitness for _, g in guesses]
        keep = sorted(np.argsort(prefit, kind="stable")[::-1][:policy.max_attempts])
        guesses = [guesses[k] for k in keep]
    for name, guess in guesses:
        T2 = align(guess)
        tried.append(Attempt(name, guess, T2, evaluate(T2)))
    best = policy.pick(tried)
    dev_m, dev_deg = deviation(predicted, best.T_world_sensor)
    summary = ", ".join(f"{a.hypothesis} {a.fit.fitness:.2f}" for a in sorted(tried, key=lambda a: -a.fit.fitness)[:3])
    logger.debug("frame %d attempts: %s", frame_id, "; ".join(f"{a.hypothesis} fit {a.fit.fitness:.3f} rmse {100 * a.fit.rmse_m:.2f} cm" for a in tried))
    if best.fit.fitness < policy.min_fitness:
        reason = f"no initial guess fits the map ({'; '.join(why)}; best: {summary})"
        logger.warning("frame %d: tracking lost: %s; the pose is bridged by %s", frame_id, reason, best.hypothesis)
        return best, TrackingStatus.LOST, reason, dev_m, dev_deg
    if best.hypothesis != "constant_velocity":
        reason = f"{'; '.join(why)}: {best.hypothesis} fits better ({summary})"
        logger.info("frame %d: tracking recovered: %s", frame_id, reason)
        return best, TrackingStatus.RECOVERED, reason, dev_m, dev_deg
    logger.debug("frame %d: retried (%s); the prediction's registration fits best (%s)", frame_id, "; ".join(why), summary)
    return best, TrackingStatus.OK, "", dev_m, dev_deg


def _cross_check(align: Callable[[NDArray[np.float64]], NDArray[np.float64]],
                 evaluate: Callable[[NDArray[np.float64]], MapFit], best: Attempt, last_pose: NDArray[np.float64],
                 last_delta: NDArray[np.float64], policy: RetryPolicy, frame_id: int, dev_m: float,
                 dev_deg: float) -> tuple[Attempt, TrackingStatus, str, float, float]:
    """The prediction's registration fits but came far: register from zero motion and half the velocity too, and
    keep the one that fits clearly better (:meth:`RetryPolicy.better`)."""
    predicted = last_pose @ last_delta
    tried = [best]
    for name, guess in initial_guesses(last_pose, last_delta, policy.up_axis, ())[:2]:
        T = align(guess)
        tried.append(Attempt(name, guess, T, evaluate(T)))
    kept = policy.pick(tried)
    if kept is best:
        return best, TrackingStatus.OK, "", dev_m, dev_deg
    reason = (f"the registration ended {dev_m:.2f} m / {dev_deg:.1f} deg from the prediction; {kept.hypothesis} fits "
              f"better (fitness {kept.fit.fitness:.2f} vs {best.fit.fitness:.2f}, RMSE {100 * kept.fit.rmse_m:.1f} vs "
              f"{100 * best.fit.rmse_m:.1f} cm)")
    logger.info("frame %d: tracking recovered: %s", frame_id, reason)
    dev_m, dev_deg = deviation(predicted, kept.T_world_sensor)
    return kept, TrackingStatus.RECOVERED, reason, dev_m, dev_deg


def health(attempt: Attempt, status: TrackingStatus, reason: str, deviation_m: float, deviation_deg: float,
           n_points: int, radius_m: float, degeneracy: float | None) -> TrackingHealth:
    """The :class:`TrackingHealth` record of a kept attempt."""
    return TrackingHealth(status=status, fitness=attempt.fit.fitness, rmse_m=attempt.fit.rmse_m,
                          degeneracy=degeneracy, deviation_m=deviation_m, deviation_deg=deviation_deg,
                          hypothesis=attempt.hypothesis, n_points=n_points, fitness_radius_m=radius_m, reason=reason)
