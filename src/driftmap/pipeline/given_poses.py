"""Do the given poses move the way the frames do? A check of ``build --poses`` / ``--poses-from-source``.

A pose file is trusted as ``T_world_sensor`` of the frames it is given for; nothing in a TUM or KITTI file says which
sensor it belongs to. A camera's pose file given for a LiDAR's scans (or a copy of it written by ``driftmap perturb``,
which keeps no link to the data set's extrinsics) places every scan with the camera's motion: the relative motion
between two frames is then the LiDAR's motion seen from the camera, rotated by the extrinsic (129 deg in trial 12),
and every figure of the map is computed on scans placed wrong.

The frames themselves say how the sensor moved. :func:`check_given_poses` registers up to ``n_pairs`` frame pairs
spread over the log (each frame onto the next one the file moves by at least :data:`MIN_MOTION_VOXELS` voxels or
:data:`MIN_MOTION_DEG`) with GICP from the file's relative pose and from no motion, and compares the share of the
later frame on the earlier one (within 1.5 voxels) at the file's relative pose with the registration's. A pair
*decides* when the registration fits at least :data:`MIN_REGISTERED_FIT` of the later frame, and *disagrees* when it
also fits at least :data:`MIN_FIT_GAIN` more than the file's relative pose and moves the frame by more than
:data:`MAX_CORRECTION_VOXELS` voxels or :data:`MAX_CORRECTION_DEG`. When at least half of the deciding pairs (and at
least :data:`MIN_DISAGREEING`) disagree, the build warns and ``build_summary.json``
(``given_poses_check``) says so. The frames are stored as given either way: poses are the user's to give (a noisy
LIO or a motion-capture file is no error), the warning says where they and the data part.

A sensor mounted rotated against the file's sensor is seen across the pairs, not in one: the file's relative motions
are then the frames' motions conjugated by the mounting rotation ``R`` (``t_frames = R t_file``, rotation axes turned
the same way), which turns each step's direction by ``R`` but moves a frame by only ``2 |t| sin(angle / 2)`` — within
the inlier distance at short steps (trial 13: 10 and 30 deg offsets passed). :func:`mounting_rotation` fits ``R`` to
the deciding pairs (Kabsch over their translations and their rotation vectors scaled by the scene's range); when it
turns by at least :data:`MIN_MOUNTING_DEG`, leaves at most :data:`MAX_MOUNTING_RESIDUAL` of the residual without it
and lowers it significantly (:data:`MIN_MOUNTING_F`), the file does not fit the frames either.

A depth (or range) scale off by a factor ``s`` is seen across the pairs in the same way: the frames' steps are ``s``
times the file's while they turn alike. :func:`step_scale` fits ``s`` to the deciding pairs' translations; when it is
at least :data:`MIN_SCALE_DEVIATION` from 1 and lowers their disagreement significantly (:data:`MIN_SCALE_F`), the file
does not fit the frames (trial 16: a 1.5x depth scale on 7-Scenes read "yes").
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap import geometry
from driftmap.registration.pairwise import PreparedCloud, nearest_distances, register_prepared
from driftmap.store.frame_store import FrameStore
from driftmap.trajectory_rows import spike_rows

logger = logging.getLogger(__name__)

MIN_MOTION_VOXELS = 3.0
"""A pair's later frame is the first the file moves by at least this many voxels (or :data:`MIN_MOTION_DEG`): a pose
file of another sensor is wrong only where the sensor moves."""
MIN_MOTION_DEG = 5.0
MAX_GAP_FRAMES = 10
"""... among the next this many frames (a robot standing still gives no pair)."""
MIN_REGISTERED_FIT = 0.6
"""A pair decides only when the registration puts at least this share of the later frame on the earlier one: frames
that overlap less (a 10-frame room turning 44 deg between depth frames) let a registration slide a wall onto another
and fit more of it wrongly than the true motion fits."""
MIN_FIT_GAIN = 0.1
"""A registration that fits this much more of the later frame than the file's relative pose found a better motion."""
MAX_CORRECTION_VOXELS = 1.0
"""... and it moved the frame by more than this many voxels or :data:`MAX_CORRECTION_DEG` from the file's pose (at 2, a
1 m sensor offset moving each scan of the LiDAR room by 1.66 voxels went unseen: trial 13)."""
MAX_CORRECTION_DEG = 2.0
SLIDE_MAX_ALONG = 0.9
"""A pair's registration moving the frame farther than twice the file's step is a slide (:attr:`GivenPosePair.slid`)
unless its step points along the file's (cosine at least this): a scale of the steps does that."""
MIN_DISAGREEING = 3
"""Disagreeing pairs needed (and at least half of those checked) for the warning."""
MIN_POINTS = 50
REFINED_FIT_SLACK = 0.01
"""The registration refined from the file's relative pose is taken as the frames' motion unless it fits this much less
of the later frame than the file's pose."""
MOUNTING_NAMED_RESIDUAL = 0.25
"""When the pairs disagree one by one too, the fitted mounting rotation is named only when it leaves at most this
share of their disagreement (a 1 m lever arm fits a 45 deg "rotation" leaving 0.42: not a rotation)."""
MIN_MOUNTING_DEG = 2.5
"""A fitted mounting rotation smaller than this is not reported (the registrations' noise on correct poses fits
0.03-1.7 deg with no drop of the residual; trial 14: a 3 deg offset of the LiDAR room read 2.99 deg)."""
MAX_MOUNTING_RESIDUAL = 0.75
"""... it must leave at most this share of the pairs' disagreement (rms) unexplained: a rotation fitted to noise
leaves 0.93-1.0 of it (the Livox LIO poses, KITTI, 7-Scenes and synthetic ground truth, our own poses), the rosette's
true poses 0.81, a 10 deg offset 0.09-0.65 (on 7-Scenes, whose registrations' own floor is 2.8 cm, 0.65) ..."""
LEVER_AMBIGUITY = 0.05
"""A turn and a lever arm are interchangeable when the joint fit's scaled Jacobian has a singular value below this
share of its largest along a direction mixing both (:func:`mounting_rotation`)."""
MIN_OFFSET_SHARE = 0.85
"""... and one constant offset of the translations must not fit clearly better: a rotation is named only when the
offset leaves at least this share of what the rotation leaves. A steady error of every step fits an offset better
(7-Scenes 920:1000:1 with its true poses: the offset left 0.76 of the 6.0 deg turn's residual, trial 21 W2); a turned
sensor does not (7-Scenes turned 10 deg about y / x: 1.44 / 1.36). Not asked on a path of one curvature (a circle:
``lever_ambiguous_axis``), where the steps are one vector in the sensor frame and a turn, a lever arm and an offset fit
alike (the LiDAR room turned 10 deg: 0.97; a 5 deg turn with a 32 cm lever arm: the offset fits better): the turn is
named there with the lever-arm caveat."""
MIN_MOUNTING_F = 12.0
"""... and its drop of the residual must be significant against what is left: ``F = ((before / after)^2 - 1) (6 n -
3) / 3`` over the n pairs' 6 n numbers and the rotation's 3 (an F-test). Correct poses: 0.1-2.2, the rosette's
8.0; a 10 deg offset on 7-Scenes and on KITTI 20.6 / 20.7 (a 5 deg one on 7-Scenes: 6.0, not seen)."""


@dataclass(frozen=True)
class GivenPosePair:
    """One frame pair: how the file moves the sensor from ``frame_a`` to ``frame_b``, and how the data does."""

    frame_a: int
    frame_b: int
    file_moved_m: float
    file_turned_deg: float
    fit_as_given: float
    """Share of frame b's points (downsampled) within 1.5 voxels of frame a's at the file's relative pose."""
    fit_registered: float
    correction_m: float
    """How far the registration moves frame b's sensor origin from where the file's relative pose puts it (m)."""
    correction_deg: float

    @property
    def decisive(self) -> bool:
        return self.fit_registered >= MIN_REGISTERED_FIT and not self.slid

    @property
    def slid(self) -> bool:
        """The registration kept the file's turn (within :data:`MAX_CORRECTION_DEG`) but moved the frame by more than
        twice the file's whole step, and not along it, on frames that overlap too little as given to decide (less than
        :data:`MIN_REGISTERED_FIT`): a slide along repeated structure, which no other sensor's poses explain (a turned
        mounting moves a frame by at most twice the step, a scale along the step; a file that stands still while the
        frames move is not judged so, it disagrees). Such a pair cannot judge: correct
        synthetic ground truth at every 4th frame of the room read "NO" on three registrations sliding 1.2-1.7 m along
        its walls at 0.47 m steps (hostile trial 22 W6)."""
        file_moves = (self.file_moved_m >= MIN_MOTION_VOXELS * self.voxel_size_m
                      or self.file_turned_deg >= MIN_MOTION_DEG)  # (a file standing still on a moving log disagrees)
        if (not file_moves or self.fit_as_given >= MIN_REGISTERED_FIT or self.correction_deg > MAX_CORRECTION_DEG
                or self.correction_m <= 2.0 * self.file_moved_m or len(self.motion_file) < 3
                or len(self.motion_registered) < 3):
            return False
        t_file, t_reg = np.asarray(self.motion_file[:3]), np.asarray(self.motion_registered[:3])
        norms = float(np.linalg.norm(t_file) * np.linalg.norm(t_reg))
        return norms == 0.0 or abs(float(t_file @ t_reg)) / norms < SLIDE_MAX_ALONG

    @property
    def disagrees(self) -> bool:
        return self.decisive and self.fit_registered - self.fit_as_given >= MIN_FIT_GAIN and (
            self.correction_m > MAX_CORRECTION_VOXELS * self.voxel_size_m or self.correction_deg > MAX_CORRECTION_DEG)

    voxel_size_m: float = 0.05
    """The registration's finest voxel (m)."""
    motion_file: tuple[float, ...] = ()
    """The file's relative motion of frame b in frame a's sensor frame (``tx ty tz rx ry rz``: metres, rotation vector
    in rad); :func:`mounting_rotation` fits the pairs' two motions."""
    motion_registered: tuple[float, ...] = ()
    """The registration's relative motion, in the same form."""

    def to_json(self) -> dict:
        return {"frame_a": self.frame_a, "frame_b": self.frame_b, "file_moved_m": round(self.file_moved_m, 4),
                "file_turned_deg": round(self.file_turned_deg, 3), "fit_as_given": round(self.fit_as_given, 4),
                "fit_registered": round(self.fit_registered, 4), "correction_m": round(self.correction_m, 4),
                "correction_deg": round(self.correction_deg, 3), "decisive": self.decisive, "disagrees": self.disagrees,
                "slid": self.slid}


@dataclass(frozen=True)
class MountingRotation:
    """The rotation ``R`` that best turns the file's relative motions into the frames' (:func:`mounting_rotation`)."""

    rotvec_deg: tuple[float, float, float]
    """``R`` as a rotation vector in the sensor frame (deg)."""
    residual_before_m: float
    """rms of the registrations' motions minus the file's (translations and range-scaled rotations, m)."""
    residual_after_m: float
    """... after turning the file's motions by ``R``."""
    n_pairs: int
    lever_ambiguous_axis: tuple[float, float, float] | None = None
    """The pairs' motions fit a turn about this axis (sensor frame) with a lever arm as well as ``R`` (a path of one
    curvature): that part of the angle is one of a family (:func:`mounting_rotation`). None: told apart."""
    residual_offset_m: float | None = None
    """rms of the disagreement left by one constant offset of the translations instead (as many numbers as ``R``): a
    steady error of every step (a registration bias, a stamp offset) that a turn of steps going one way also fits
    (hostile trial 21 W2: 7-Scenes 920:1000:1 with its true poses read 6.0 deg, leaving 1.37 cm; the offset left
    1.03). None: not measured."""

    @property
    def angle_deg(self) -> float:
        return float(np.linalg.norm(self.rotvec_deg))

    @property
    def lever_ambiguous_deg(self) -> float:
        """The part of the turn about :attr:`lever_ambiguous_axis` (deg; 0 without one): what a lever arm may stand in
        for (a roll on a circle about the vertical has none, and is named without the caveat)."""
        if self.lever_ambiguous_axis is None:
            return 0.0
        return float(np.dot(self.rotvec_deg, self.lever_ambiguous_axis))

    @property
    def f_statistic(self) -> float:
        """How significantly ``R`` lowers the pairs' disagreement (:data:`MIN_MOUNTING_F`)."""
        ratio = (self.residual_before_m / max(self.residual_after_m, 1e-12)) ** 2
        return float((ratio - 1.0) * (6 * self.n_pairs - 3) / 3.0)

    @property
    def explains(self) -> bool:
        """The frames move as the file's poses would with the sensor mounted turned by ``R``."""
        return (self.n_pairs >= MIN_DISAGREEING and self.angle_deg >= MIN_MOUNTING_DEG
                and self.residual_after_m <= MAX_MOUNTING_RESIDUAL * self.residual_before_m
                and self.f_statistic >= MIN_MOUNTING_F
                and (self.residual_offset_m is None or self.lever_ambiguous_axis is not None
                     or self.residual_offset_m >= MIN_OFFSET_SHARE * self.residual_after_m))

    def describe(self) -> str:
        axis = np.asarray(self.rotvec_deg) / max(self.angle_deg, 1e-12)
        family = ""
        if self.lever_ambiguous_axis is not None and abs(self.lever_ambiguous_deg) >= MIN_MOUNTING_DEG:
            a = self.lever_ambiguous_axis
            family = (f" -- of which the {abs(self.lever_ambiguous_deg):.1f} deg about the sensor's ({a[0]:.2f}, "
                      f"{a[1]:.2f}, {a[2]:.2f}) axis may be a lever arm instead: these pairs move along one curve, on "
                      f"which a turn about it and an offset of the sensor look alike")
        return (f"{self.angle_deg:.1f} deg about the sensor's ({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}) axis"
                f"{family} (the pairs' disagreement {100 * self.residual_before_m:.1f} cm rms, "
                f"{100 * self.residual_after_m:.1f} cm with it)")

    def to_json(self) -> dict:
        return {"angle_deg": round(self.angle_deg, 3), "rotvec_deg": [round(v, 3) for v in self.rotvec_deg],
                "lever_ambiguous_axis": None if self.lever_ambiguous_axis is None else [
                    round(v, 3) for v in self.lever_ambiguous_axis],
                "lever_ambiguous_deg": round(self.lever_ambiguous_deg, 3),
                "residual_before_m": round(self.residual_before_m, 5),
                "residual_after_m": round(self.residual_after_m, 5), "n_pairs": self.n_pairs,
                "residual_offset_m": None if self.residual_offset_m is None else round(self.residual_offset_m, 5),
                "f_statistic": round(self.f_statistic, 2), "explains": self.explains}


def _motion(T: NDArray[np.float64]) -> tuple[float, ...]:
    return tuple(float(v) for v in np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()]))


def _kabsch(X: NDArray[np.float64], Y: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation ``R`` minimising ``sum |Y - X R^T|^2`` (rows)."""
    U, _, Vt = np.linalg.svd(X.T @ Y)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    return Vt.T @ D @ U.T


def mounting_rotation(pairs: Sequence[GivenPosePair], range_m: float) -> MountingRotation | None:
    """The rotation ``R`` minimising ``sum |m_registered - R m_file|^2`` over the deciding pairs' translations and
    rotation vectors (scaled by ``range_m``: a rotation error moves points at the scene's range by ``range * angle``);
    None with fewer than :data:`MIN_DISAGREEING` deciding pairs.

    A sensor mounted with a lever arm ``l`` as well moves by ``R (t + (R_file - I) l)``. Along a path of one curvature
    (a circle: the synthetic rooms, a car in a long bend) a turn and a lever arm are interchangeable: every
    point of the body moves on a circle, and the motions fit a family of (angle, offset) equally (hostile trial 14 W1:
    5 deg with a 32 cm lever arm fits exactly as a 13.5 deg turn). ``lever_ambiguous_axis`` says so: the joint problem's
    Jacobian at ``(R, l = 0)``, its columns scaled to unit length, has a singular value below
    :data:`LEVER_AMBIGUITY` of the largest along a direction that mixes the turn and the offset."""
    used = [p for p in pairs if p.decisive and len(p.motion_file) == 6 and len(p.motion_registered) == 6]
    if len(used) < MIN_DISAGREEING:
        return None
    scale = np.array([1.0, 1.0, 1.0, range_m, range_m, range_m])
    X = np.array([np.asarray(p.motion_file) * scale for p in used]).reshape(-1, 3)
    Y = np.array([np.asarray(p.motion_registered) * scale for p in used]).reshape(-1, 3)
    R = _kabsch(X, Y)
    before = float(np.sqrt(np.mean(np.sum((Y - X) ** 2, axis=1)) * 2))  # per pair: translation + rotation rows
    after = float(np.sqrt(np.mean(np.sum((Y - X @ R.T) ** 2, axis=1)) * 2))
    rotvec = np.degrees(Rotation.from_matrix(R).as_rotvec())
    file = np.array([p.motion_file for p in used])
    d = (Y - X).reshape(len(used), 2, 3)  # per pair: translation row, range-scaled rotation row
    d[:, 0] -= d[:, 0].mean(axis=0)  # one constant offset of the translations, its 3 numbers against R's 3
    offset = float(np.sqrt(np.mean(np.sum(d.reshape(-1, 3) ** 2, axis=1)) * 2))
    return MountingRotation((float(rotvec[0]), float(rotvec[1]), float(rotvec[2])), before, after, len(used),
                            _lever_ambiguous(file, R, range_m), offset)


def _lever_ambiguous(file: NDArray[np.float64], R: NDArray[np.float64],
                     range_m: float) -> tuple[float, float, float] | None:
    """Can a lever arm stand in for part of the turn ``R`` (:func:`mounting_rotation`)? The Jacobian of the predicted
    motions ``(R_x R (t + (R_file - I) l), R_x R r range)`` in the small rotation ``x`` and the lever arm ``l`` at 0;
    the axis of the turn a lever arm can stand in for, or None."""
    M = Rotation.from_rotvec(file[:, 3:]).as_matrix() - np.eye(3)
    t, r = file[:, :3] @ R.T, range_m * file[:, 3:] @ R.T
    columns = []
    for axis in np.eye(3):  # d/dx of R_x v = x cross v
        columns.append(np.concatenate([np.cross(axis, t).ravel(), np.cross(axis, r).ravel()]))
    for axis in np.eye(3):  # d/dl of R (R_file - I) l
        columns.append(np.concatenate([(np.einsum("nij,j->ni", M, axis) @ R.T).ravel(), np.zeros(r.size)]))
    J = np.array(columns).T
    norms = np.linalg.norm(J, axis=0)
    live = norms > 1e-9 * max(float(norms.max()), 1e-12)
    if live[:3].sum() == 0 or live[3:].sum() == 0:
        return None
    Jn = J[:, live] / norms[live]
    _, S, Vt = np.linalg.svd(Jn, full_matrices=False)
    n_rot = int(live[:3].sum())
    for value, v in zip(S, Vt, strict=True):
        if value < LEVER_AMBIGUITY * S[0] and np.linalg.norm(v[:n_rot]) > 0.2 and np.linalg.norm(v[n_rot:]) > 0.2:
            turn = np.zeros(3)
            turn[live[:3]] = v[:n_rot] / norms[:3][live[:3]]
            turn = R.T @ turn  # in the sensor's frame, as the rotation vector is named
            turn /= np.linalg.norm(turn)
            turn *= -1.0 if turn[int(np.argmax(np.abs(turn)))] < 0 else 1.0
            turn = np.round(turn, 3) + 0.0  # no "-0.00" in the message
            return (float(turn[0]), float(turn[1]), float(turn[2]))
    return None


MIN_SCALE_DEVIATION = 0.2
"""A fitted ratio of the frames' steps to the file's (:func:`step_scale`) further than this from 1 is reported ...
The registrations have a bias of their own: they read KITTI's true steps 9 % short (F 38), so a smaller scale error
cannot be told from it."""
MAX_SCALE_RESIDUAL = 0.6
"""... it must leave at most this share of the pairs' disagreement (rms) unexplained (hostile trial 21 W2: on two of
twelve 7-Scenes windows with true poses a factor of 0.68 leaving 0.80 passed the F gate alone); a 1.5x depth scale
leaves 0.29, a LiDAR pose file scaled by 0.77 0.02 ..."""
SCALE_NAMED_RESIDUAL = 0.25
"""... and when the pairs disagree one by one too, the factor is named as the cause when it leaves at most this share
(trial 21 W3: a LiDAR pose file scaled by 0.77 read "another sensor's pose file", 98 % explained by the factor)."""
SCALE_OUTLIER_FACTOR = 3.0
"""A pair whose residual after the first fit is over this many times the pairs' median residual (and over one
registration voxel) is left out of the second (trial 21 B3: one pair slid 17 cm hid a 1.3x scale; W1: a pair across a
gap of 26 frames and 174 deg read a factor of -0.04)."""
MIN_SCALE_F = 12.0
"""... when it lowers the pairs' disagreement significantly: ``F = ((before / after)^2 - 1) (3 n - 1)`` over the n
pairs' 3 n translation numbers and the one factor. Measured on 7-Scenes (frames 0:300:3, true poses): factor 0.986,
F 0.3; with a 1.5x depth scale (``--depth-scale 666.67``): 1.449, F 244 (trial 16: it read "given poses fit")."""


@dataclass(frozen=True)
class StepScale:
    """The factor ``s`` that best turns the file's steps into the frames' (:func:`step_scale`)."""

    factor: float
    residual_before_m: float
    """rms over the pairs of the registrations' translations minus the file's (m)."""
    residual_after_m: float
    """... after scaling the file's by ``factor``."""
    n_pairs: int

    @property
    def f_statistic(self) -> float:
        ratio = (self.residual_before_m / max(self.residual_after_m, 1e-12)) ** 2
        return float((ratio - 1.0) * (3 * self.n_pairs - 1))

    @property
    def explains(self) -> bool:
        """The frames move as the file's poses would with their positions scaled by ``factor`` (a positive factor
        at least :data:`MIN_SCALE_DEVIATION` from 1, leaving at most :data:`MAX_SCALE_RESIDUAL` of the disagreement,
        significant by :data:`MIN_SCALE_F`)."""
        return (self.n_pairs >= MIN_DISAGREEING and self.factor > 0.0
                and abs(self.factor - 1.0) >= MIN_SCALE_DEVIATION
                and self.residual_after_m <= MAX_SCALE_RESIDUAL * self.residual_before_m
                and self.f_statistic >= MIN_SCALE_F)

    @property
    def named(self) -> bool:
        """It explains the pairs' disagreement almost whole (:data:`SCALE_NAMED_RESIDUAL`): the cause to name even
        where pairs disagree one by one."""
        return self.explains and self.residual_after_m <= SCALE_NAMED_RESIDUAL * self.residual_before_m

    def to_json(self) -> dict:
        return {"factor": round(self.factor, 4), "residual_before_m": round(self.residual_before_m, 5),
                "residual_after_m": round(self.residual_after_m, 5), "n_pairs": self.n_pairs,
                "f_statistic": round(self.f_statistic, 2), "explains": self.explains, "named": self.named}


def step_scale(pairs: Sequence[GivenPosePair]) -> StepScale | None:
    """The factor ``s`` minimising ``sum |t_registered - s t_file|^2`` over the deciding pairs' translations; None with
    fewer than :data:`MIN_DISAGREEING` of them or no motion.

    A depth (or range) scale off by ``s`` scales every frame's points, and a rigid motion between scaled frames is the
    true one with its translation scaled: the frames' steps are ``s`` times the file's, their turns alike. At short
    steps each pair stays within the registration's inlier distance (a 1.5x scale on 7-Scenes moves a 10 cm step by
    5 cm, under the 7 cm voxel), across the pairs the factor shows (trial 16)."""
    used = [p for p in pairs if p.decisive and len(p.motion_file) == 6 and len(p.motion_registered) == 6]
    if len(used) < MIN_DISAGREEING:
        return None
    X = np.array([p.motion_file[:3] for p in used])
    Y = np.array([p.motion_registered[:3] for p in used])

    def fit(rows: NDArray[np.bool_]) -> float | None:
        norm = float(np.sum(X[rows] * X[rows]))
        return float(np.sum(X[rows] * Y[rows]) / norm) if norm > 0.0 else None

    norms = np.sum(X * X, axis=1)
    moving = norms > 0.0
    if not moving.any():
        return None
    # a robust start: the median of the pairs' own factors (a least-squares start let one wild pair -- a resume
    # across a gap, 1.5 m and a half turn -- drive the factor negative and hide a 1.3x scale: trial 22 B4)
    first = float(np.median(np.sum(X[moving] * Y[moving], axis=1) / norms[moving]))
    # again without the pairs the first fit leaves far out (a registration that slid)
    residual = np.linalg.norm(Y - first * X, axis=1)
    keep = residual <= max(SCALE_OUTLIER_FACTOR * float(np.median(residual)), used[0].voxel_size_m)
    factor = fit(keep) if keep.sum() >= MIN_DISAGREEING else None
    if factor is None:
        return None
    n = int(keep.sum())
    before = float(np.sqrt(np.sum((Y[keep] - X[keep]) ** 2) / n))
    after = float(np.sqrt(np.sum((Y[keep] - factor * X[keep]) ** 2) / n))
    return StepScale(factor, before, after, n)


UNIT_FACTOR = 5.0
"""A pose file whose steps are this many times the frames' own (or this many times smaller), turning alike, is read as
a unit mistake (:attr:`GivenPosesCheck.unit_factor`)."""
UNIT_MIN_STEP_M = 0.02
"""... counted over the frame pairs that move at least this far (m), by the registration."""


@dataclass(frozen=True)
class GivenPosesCheck:
    """The checked pairs and the verdict (:func:`check_given_poses`)."""

    voxel_size_m: float
    pairs: tuple[GivenPosePair, ...]
    range_m: float = 0.0
    """The scene's range the rotations are scaled by (the median range of a frame half way along the log)."""
    spike_frames: tuple[int, ...] = ()
    """Frames whose pose jumps away from both neighbours' and back (:func:`driftmap.trajectory.spike_rows`: a corrupt
    row of the pose file?). The pairs rarely see them (one or two of eight), so the verdict does not say it alone."""
    sensor_kind: str = "depth_camera"
    """What made the frames: a scale of a LiDAR's steps has no ``--depth-scale`` to name (trial 22 W3)."""

    @property
    def mounting(self) -> MountingRotation | None:
        return mounting_rotation(self.pairs, self.range_m) if self.range_m > 0 else None

    @property
    def scale(self) -> StepScale | None:
        return step_scale(self.pairs)

    @property
    def unit_factor(self) -> float | None:
        """The file's steps over the frames' own (median over the disagreeing pairs that move at least
        :data:`UNIT_MIN_STEP_M`), when they turn alike (within :data:`MAX_CORRECTION_DEG`) and the factor is beyond
        :data:`UNIT_FACTOR`: a pose file in millimetres or centimetres (hostile trial 17 W4 was told "another sensor's
        pose file", 1,190 m/s in a 4.6 m room); None otherwise."""
        used = [p for p in self.pairs if p.disagrees and len(p.motion_file) == 6 and len(p.motion_registered) == 6
                and np.linalg.norm(p.motion_registered[:3]) >= UNIT_MIN_STEP_M]
        if len(used) < MIN_DISAGREEING:
            return None
        ratios = [np.linalg.norm(p.motion_file[:3]) / np.linalg.norm(p.motion_registered[:3]) for p in used]
        turns = [np.degrees(np.linalg.norm(np.asarray(p.motion_file[3:]) - np.asarray(p.motion_registered[3:])))
                 for p in used]
        factor = float(np.median(ratios))
        if float(np.median(turns)) > MAX_CORRECTION_DEG or 1.0 / UNIT_FACTOR < factor < UNIT_FACTOR:
            return None
        return factor

    @property
    def pairs_disagree(self) -> bool:
        """At least :data:`MIN_DISAGREEING` and half of the deciding pairs disagree one by one."""
        return self.n_disagreeing >= MIN_DISAGREEING and 2 * self.n_disagreeing >= self.n_decisive

    @property
    def n_disagreeing(self) -> int:
        return sum(p.disagrees for p in self.pairs)

    @property
    def n_decisive(self) -> int:
        return sum(p.decisive for p in self.pairs)

    @property
    def consistent(self) -> bool | None:
        """False: the frames move otherwise than the given poses say (at least :data:`MIN_DISAGREEING` and half of the
        decisive pairs disagree); None: fewer than :data:`MIN_DISAGREEING` pairs decide (frames that overlap too little,
        a robot that does not move); also False when the pairs together show a mounting rotation
        (:attr:`MountingRotation.explains`) or a scale of the steps (:attr:`StepScale.explains`) that no pair shows
        alone; None too for a fit that the pairs that slid could overturn (:attr:`slides_could_disagree`)."""
        if self.n_decisive < MIN_DISAGREEING:
            return None
        mounting, scale = self.mounting, self.scale
        fits = not (self.pairs_disagree or (mounting is not None and mounting.explains)
                    or (scale is not None and scale.explains))
        return None if fits and self.slides_could_disagree else fits

    @property
    def slides_could_disagree(self) -> bool:
        """The pairs that slid (:attr:`GivenPosePair.slid`), which do not decide, would make the pairs disagree if
        they counted as disagreeing: a slide keeps the file's turn, but the pairs of a wrong file slide too (hostile
        trial 23 B6: a 10 deg mounting rotation on the room at every 3rd frame read "yes" on 4 deciding pairs, 1
        disagreeing, with 3 slid; it read "NO: 4 of 7" before slides stopped deciding). A "yes" they could overturn
        cannot judge."""
        slid = sum(p.slid and p.fit_registered >= MIN_REGISTERED_FIT
                   and p.fit_registered - p.fit_as_given >= MIN_FIT_GAIN for p in self.pairs)
        n = self.n_disagreeing + slid
        return slid > 0 and n >= MIN_DISAGREEING and 2 * n >= self.n_decisive + slid

    def reason(self, what: str, then: str | None = None) -> str | None:
        """Why ``what`` (the pose file, as the user named it) does not fit the frames (None when it does); ``then``:
        what became of the poses and the way back (default: ``build``'s, the frames stored with them)."""
        if self.consistent is not False:
            return None
        mounting = self.mounting
        advice = ("Is it another sensor's pose file (a camera's poses for a LiDAR, or a copy that lost the data set's "
                  "extrinsics)? " + (then or "The frames are stored with these poses; give this sensor's T_world_sensor "
                                     "poses, or repair the store with `driftmap correct STORE --poses FILE "
                                     "--accept-sensor-offset` and this sensor's poses"))
        if not self.pairs_disagree and mounting is not None and mounting.explains:
            return (f"{what}: the poses do not move the way the frames do: across {mounting.n_pairs} frame pairs the "
                    f"frames move as the file's poses would with the sensor mounted turned by {mounting.describe()}; "
                    f"each pair alone stays within the registration's inlier distance, but every frame is turned about "
                    f"its own origin, so a surface seen from two places lands apart by about their distance times "
                    f"that angle. {advice}")
        if (factor := self.unit_factor) is not None:
            return (f"{what}: the poses do not move the way the frames do: the file's steps are {factor:.3g} times the "
                    f"frames' own (median over the frame pairs), while they turn alike: are its positions in another "
                    f"unit (millimetres: 1000, centimetres: 100)? driftmap reads metres. "
                    + (then or "The frames are stored with these poses; give the file in metres"))
        scale = self.scale
        if scale is not None and (scale.named or (not self.pairs_disagree and scale.explains)):
            alone = "" if self.pairs_disagree else "; each pair alone stays within the registration's inlier distance"
            return (f"{what}: the poses do not move the way the frames do: across {scale.n_pairs} frame pairs the "
                    f"frames' steps are {scale.factor:.3g} times the file's, while they turn alike (the pairs' "
                    f"disagreement {100 * scale.residual_before_m:.1f} cm rms, {100 * scale.residual_after_m:.1f} cm "
                    f"with the factor){alone}. "
                    + ("Is the frames' depth scale off by that factor (--depth-scale: the depth image's units per "
                       "metre), or are the file's positions in another unit? " if self.sensor_kind == "depth_camera"
                       else "Are the file's positions in another unit or scaled (a LiDAR's ranges are metres as "
                            "read), or is it the pose file of another recording? ")
                    + (then or "The frames are stored with these poses and points; build again with the right scale "
                                "or pose file"))
        bad = [p for p in self.pairs if p.disagrees]
        together = ""
        if mounting is not None and mounting.explains and mounting.residual_after_m <= (
                MOUNTING_NAMED_RESIDUAL * mounting.residual_before_m):
            together = f" Together the pairs fit a sensor mounted turned by {mounting.describe()}."
        worst = max(bad, key=lambda p: p.fit_registered - p.fit_as_given)
        return (f"{what}: the poses do not move the way the frames do: on {len(bad)} of {self.n_decisive} frame pairs "
                f"a registration of the frames fits them better than the file's relative pose (frames "
                f"{worst.frame_a} -> {worst.frame_b}: {100 * worst.fit_as_given:.0f} % of the points on each other as "
                f"given, {100 * worst.fit_registered:.0f} % moved by {100 * worst.correction_m:.0f} cm / "
                f"{worst.correction_deg:.1f} deg; median over the disagreeing pairs "
                f"{100 * float(np.median([p.correction_m for p in bad])):.0f} cm / "
                f"{float(np.median([p.correction_deg for p in bad])):.1f} deg).{together} {advice}")

    def to_json(self) -> dict:
        mounting = self.mounting
        return {"consistent": self.consistent, "voxel_size_m": round(self.voxel_size_m, 4),
                "n_pairs": len(self.pairs), "n_decisive": self.n_decisive, "n_disagreeing": self.n_disagreeing,
                "pairs": [p.to_json() for p in self.pairs],
                "mounting_rotation": None if mounting is None else mounting.to_json(),
                "step_scale": None if (scale := self.scale) is None else scale.to_json(),
                "spike_frames": list(self.spike_frames), "sensor_kind": self.sensor_kind}


def _median_range(points_sensor: NDArray[np.floating]) -> float:
    return float(np.median(np.linalg.norm(points_sensor, axis=1))) if len(points_sensor) else 1.0


def _voxel_for(points_sensor: NDArray[np.floating]) -> float:
    """A registration voxel for the scene the frame sees: 1/40 of its median range (5 cm at 2 m, 37 cm at 15 m)."""
    return float(np.clip(_median_range(points_sensor) / 40.0, 0.02, 1.0))


def _pair_indices(poses: NDArray[np.float64], voxel_m: float, n_pairs: int,
                  ids: NDArray[np.int64] | None = None) -> list[tuple[int, int]]:
    """Up to ``n_pairs`` (a, b) row pairs spread over the log, b the first row after a the poses move enough; with
    ``ids``, no pair spans a gap in them of more than :data:`MAX_GAP_FRAMES` times their median step (the frames a
    resume across a gap in its selection stored apart: trial 22 B4)."""
    n = len(poses)
    first_b = np.full(n, -1)
    inverse = np.linalg.inv(poses)
    for gap in range(min(MAX_GAP_FRAMES, n - 1), 0, -1):  # the smallest gap that moves enough wins
        T = inverse[:-gap] @ poses[gap:]
        cos = np.clip((np.trace(T[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
        enough = ((np.linalg.norm(T[:, :3, 3], axis=1) >= MIN_MOTION_VOXELS * voxel_m)
                  | (np.degrees(np.arccos(cos)) >= MIN_MOTION_DEG))
        first_b[:-gap][enough] = np.flatnonzero(enough) + gap
    step = max(float(np.median(np.diff(ids))), 1.0) if ids is not None else 0.0

    def no_gap(pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
        return pairs if ids is None else [(a, b) for a, b in pairs if ids[b] - ids[a] <= MAX_GAP_FRAMES * step]

    candidates = no_gap([(int(a), int(first_b[a])) for a in np.flatnonzero(first_b >= 0)])
    if len(candidates) < n_pairs:  # the file hardly moves: consecutive frames too (do the frames move? trial 13)
        taken = {a for a, _ in candidates}
        still = [a for a in np.linspace(0, n - 2, n_pairs).round().astype(int) if int(a) not in taken]
        candidates = sorted(candidates + no_gap([(int(a), int(a) + 1) for a in dict.fromkeys(still)]))
    if len(candidates) <= n_pairs:
        return candidates
    pick = np.linspace(0, len(candidates) - 1, n_pairs).round().astype(int)
    return [candidates[i] for i in pick]


def check_given_poses(store: FrameStore, revision: int = 0, n_pairs: int = 8, *,
                      poses: NDArray[np.float64] | None = None,
                      frame_ids: NDArray[np.int64] | None = None) -> GivenPosesCheck:
    """Register up to ``n_pairs`` frame pairs of ``store`` (see the module docstring) against ``revision``'s poses,
    or against ``poses`` of the frames ``frame_ids`` (e.g. ground truth: ``diagnose --gt``)."""
    if poses is None:
        ids, poses = store.frame_ids, store.poses(revision)
    else:
        ids, poses = np.asarray(frame_ids, dtype=np.int64), np.asarray(poses, dtype=np.float64)
    if len(ids) < 2:
        return GivenPosesCheck(0.0, ())
    spikes = tuple(int(ids[k]) for k in spike_rows(poses[:, :3, 3], poses[:, :3, :3]))
    middle = store.frame(int(ids[len(ids) // 2]), revision)
    voxel = _voxel_for(middle.points_sensor)  # the scene's scale from a frame half way along the log
    pairs = []
    for a, b in _pair_indices(poses, voxel, n_pairs, np.asarray(ids, dtype=np.int64)):
        fa, fb = store.frame(int(ids[a]), revision), store.frame(int(ids[b]), revision)
        if fa.n_points < MIN_POINTS or fb.n_points < MIN_POINTS:
            continue
        tgt, src = PreparedCloud(fa.points_sensor, 1), PreparedCloud(fb.points_sensor, 1)
        T_file = np.linalg.inv(poses[a]) @ poses[b]

        def fit(T: NDArray[np.float64]) -> float:
            d = nearest_distances(tgt, src, T, voxel)
            return float(np.mean(d <= 1.5 * voxel)) if len(d) else 0.0

        best_T, best_fit = T_file, fit(T_file)
        as_given = best_fit
        reach = max(6 * voxel, 1.5 * float(np.linalg.norm(T_file[:3, 3])))
        for start in (T_file, np.eye(4)):
            T = start
            for level, gate in ((2 * voxel, reach), (voxel, 3 * voxel)):
                T = register_prepared(tgt, src, T, voxel_size_m=level, max_correspondence_m=gate,
                                      num_threads=1).T_target_source
            f = fit(T)
            # the refinement from the file's pose is the frames' motion when it fits as well: at short steps the
            # share within 1.5 voxels saturates (1.0 as given and registered) and would hide a turned motion
            if f > best_fit or (start is T_file and f >= as_given - REFINED_FIT_SLACK):
                best_T, best_fit = T, f
        origin_file, origin_reg = T_file[:3, 3], best_T[:3, 3]
        pairs.append(GivenPosePair(int(ids[a]), int(ids[b]), float(np.linalg.norm(T_file[:3, 3])),
                                   float(geometry.rotation_angle_deg(np.eye(4), T_file)), as_given, best_fit,
                                   float(np.linalg.norm(origin_reg - origin_file)),
                                   float(geometry.rotation_angle_deg(T_file, best_T)), voxel,
                                   _motion(T_file), _motion(best_T)))
    check = GivenPosesCheck(voxel, tuple(pairs), _median_range(middle.points_sensor), spikes,
                            middle.sensor_kind.value)
    logger.debug("given poses check: %s", check.to_json())
    return check
