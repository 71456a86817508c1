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
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.registration.pairwise import PreparedCloud, nearest_distances, register_prepared
from driftmap.store.frame_store import FrameStore

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
MIN_DISAGREEING = 3
"""Disagreeing pairs needed (and at least half of those checked) for the warning."""
MIN_POINTS = 50


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
        return self.fit_registered >= MIN_REGISTERED_FIT

    @property
    def disagrees(self) -> bool:
        return self.decisive and self.fit_registered - self.fit_as_given >= MIN_FIT_GAIN and (
            self.correction_m > MAX_CORRECTION_VOXELS * self.voxel_size_m or self.correction_deg > MAX_CORRECTION_DEG)

    voxel_size_m: float = 0.05
    """The registration's finest voxel (m)."""

    def to_json(self) -> dict:
        return {"frame_a": self.frame_a, "frame_b": self.frame_b, "file_moved_m": round(self.file_moved_m, 4),
                "file_turned_deg": round(self.file_turned_deg, 3), "fit_as_given": round(self.fit_as_given, 4),
                "fit_registered": round(self.fit_registered, 4), "correction_m": round(self.correction_m, 4),
                "correction_deg": round(self.correction_deg, 3), "decisive": self.decisive, "disagrees": self.disagrees}


@dataclass(frozen=True)
class GivenPosesCheck:
    """The checked pairs and the verdict (:func:`check_given_poses`)."""

    voxel_size_m: float
    pairs: tuple[GivenPosePair, ...]

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
        a robot that does not move)."""
        if self.n_decisive < MIN_DISAGREEING:
            return None
        return not (self.n_disagreeing >= MIN_DISAGREEING and 2 * self.n_disagreeing >= self.n_decisive)

    def reason(self, what: str) -> str | None:
        """Why ``what`` (the pose file, as the user named it) does not fit the frames (None when it does)."""
        if self.consistent is not False:
            return None
        bad = [p for p in self.pairs if p.disagrees]
        worst = max(bad, key=lambda p: p.fit_registered - p.fit_as_given)
        return (f"{what}: the poses do not move the way the frames do: on {len(bad)} of {self.n_decisive} frame pairs "
                f"a registration of the frames fits them better than the file's relative pose (frames "
                f"{worst.frame_a} -> {worst.frame_b}: {100 * worst.fit_as_given:.0f} % of the points on each other as "
                f"given, {100 * worst.fit_registered:.0f} % moved by {100 * worst.correction_m:.0f} cm / "
                f"{worst.correction_deg:.1f} deg; median over the disagreeing pairs "
                f"{100 * float(np.median([p.correction_m for p in bad])):.0f} cm / "
                f"{float(np.median([p.correction_deg for p in bad])):.1f} deg). Is it another sensor's pose file (a "
                f"camera's poses for a LiDAR, or a copy that lost the data set's extrinsics)? The frames are stored "
                f"with these poses; give this sensor's T_world_sensor poses, or repair the store with `driftmap correct "
                f"STORE --poses FILE --accept-sensor-offset` and this sensor's poses")

    def to_json(self) -> dict:
        return {"consistent": self.consistent, "voxel_size_m": round(self.voxel_size_m, 4),
                "n_pairs": len(self.pairs), "n_decisive": self.n_decisive, "n_disagreeing": self.n_disagreeing,
                "pairs": [p.to_json() for p in self.pairs]}


def _voxel_for(points_sensor: NDArray[np.floating]) -> float:
    """A registration voxel for the scene the frame sees: 1/40 of its median range (5 cm at 2 m, 37 cm at 15 m)."""
    r = float(np.median(np.linalg.norm(points_sensor, axis=1))) if len(points_sensor) else 1.0
    return float(np.clip(r / 40.0, 0.02, 1.0))


def _pair_indices(poses: NDArray[np.float64], voxel_m: float, n_pairs: int) -> list[tuple[int, int]]:
    """Up to ``n_pairs`` (a, b) row pairs spread over the log, b the first row after a the poses move enough."""
    n = len(poses)
    first_b = np.full(n, -1)
    inverse = np.linalg.inv(poses)
    for gap in range(min(MAX_GAP_FRAMES, n - 1), 0, -1):  # the smallest gap that moves enough wins
        T = inverse[:-gap] @ poses[gap:]
        cos = np.clip((np.trace(T[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
        enough = ((np.linalg.norm(T[:, :3, 3], axis=1) >= MIN_MOTION_VOXELS * voxel_m)
                  | (np.degrees(np.arccos(cos)) >= MIN_MOTION_DEG))
        first_b[:-gap][enough] = np.flatnonzero(enough) + gap
    candidates = [(int(a), int(first_b[a])) for a in np.flatnonzero(first_b >= 0)]
    if len(candidates) < n_pairs:  # the file hardly moves: consecutive frames too (do the frames move? trial 13)
        taken = {a for a, _ in candidates}
        still = [a for a in np.linspace(0, n - 2, n_pairs).round().astype(int) if int(a) not in taken]
        candidates = sorted(candidates + [(int(a), int(a) + 1) for a in dict.fromkeys(still)])
    if len(candidates) <= n_pairs:
        return candidates
    pick = np.linspace(0, len(candidates) - 1, n_pairs).round().astype(int)
    return [candidates[i] for i in pick]


def check_given_poses(store: FrameStore, revision: int = 0, n_pairs: int = 8) -> GivenPosesCheck:
    """Register up to ``n_pairs`` frame pairs of ``store`` (see the module docstring) against ``revision``'s poses."""
    ids = store.frame_ids
    poses = store.poses(revision)
    if len(ids) < 2:
        return GivenPosesCheck(0.0, ())
    middle = store.frame(int(ids[len(ids) // 2]), revision)
    voxel = _voxel_for(middle.points_sensor)  # the scene's scale from a frame half way along the log
    pairs = []
    for a, b in _pair_indices(poses, voxel, n_pairs):
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
            if f > best_fit:
                best_T, best_fit = T, f
        origin_file, origin_reg = T_file[:3, 3], best_T[:3, 3]
        pairs.append(GivenPosePair(int(ids[a]), int(ids[b]), float(np.linalg.norm(T_file[:3, 3])),
                                   float(geometry.rotation_angle_deg(np.eye(4), T_file)), as_given, best_fit,
                                   float(np.linalg.norm(origin_reg - origin_file)),
                                   float(geometry.rotation_angle_deg(T_file, best_T)), voxel))
    check = GivenPosesCheck(voxel, tuple(pairs))
    logger.debug("given poses check: %s", check.to_json())
    return check
