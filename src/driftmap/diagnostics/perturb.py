"""Pose and sensor perturbations: change exactly one geometric assumption, then record what changes.

Pose perturbations act on ``(N, 4, 4)`` arrays of ``T_world_sensor`` in time order:

* :func:`translation_step` -- from frame index ``k`` on, every pose is shifted by a world-frame vector
  (what an odometry jump does to everything after it).
* :func:`rotation_step` -- from frame index ``k`` on, every pose is rotated about the sensor origin of
  frame ``k`` by a world-frame rotation vector (degrees).
* :func:`linear_drift` -- an error that grows with the distance travelled ``s_k`` (metres along the
  sensor path): a translation of ``percent_per_m / 100 * s_k`` along a fixed world direction and a
  rotation of ``deg_per_m * s_k`` degrees about a fixed world axis through the first sensor origin. (A pure
  scale error along the direction of motion is *not* used: it closes loops exactly and is invisible to
  any consistency measure; a fixed direction is what accumulated odometry error looks like at a revisit.)

Sensor perturbations act on a frame's sensor-frame points (apply them before storing a frame, i.e. at
build time):

* :func:`scale_depth` -- a depth-scale error: every point scaled radially from the sensor origin by
  ``factor`` (a depth camera with a wrong ``depth_scale``, a LiDAR with a range scale error).
* :func:`scale_focal` -- a focal-length error of a pinhole depth camera: the points were back-projected
  with ``f_assumed`` instead of the true ``f_true``, so ``x`` and ``y`` are scaled by ``f_true / f_assumed``
  and ``z`` is unchanged.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from driftmap.errors import ConfigError, GeometryError, parse_enum
from driftmap.frame import Frame, PointAttributes
from driftmap.store.guards import refuse_inside_store
from driftmap.trajectory import Trajectory, read_euroc, read_kitti, read_tum, write_euroc, write_kitti, write_tum
from driftmap.voxels import dense_ids

if TYPE_CHECKING:
    from driftmap.diagnostics.samples import DiagnosticCloud
    from driftmap.diagnostics.surfaces import SurfaceGroups
    from driftmap.diagnostics.wall_results import DoubleWallResult


class PoseFileFormat(enum.Enum):
    TUM = "tum"
    KITTI = "kitti"
    EUROC = "euroc"


def _poses(poses: ArrayLike) -> NDArray[np.float64]:
    T = np.asarray(poses, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise GeometryError(f"perturb: expected (N, 4, 4) poses, got {T.shape}")
    return T.copy()


def _vector(v: ArrayLike, name: str) -> NDArray[np.float64]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: expected 3 finite numbers, got {v!r}")
    return a


def path_length_m(poses: ArrayLike) -> NDArray[np.float64]:
    """Cumulative distance travelled by the sensor origin, ``s[0] = 0``."""
    T = np.asarray(poses, dtype=np.float64)
    if len(T) == 0:
        return np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1))])


def translation_step(poses: ArrayLike, at_index: int, step_m: ArrayLike) -> NDArray[np.float64]:
    """Shift every pose from index ``at_index`` on by the world-frame vector ``step_m``."""
    T = _poses(poses)
    if not 0 <= at_index < len(T):
        raise ConfigError(f"translation_step: index {at_index} outside 0..{len(T) - 1}")
    T[at_index:, :3, 3] += _vector(step_m, "step_m")
    return T


def rotation_step(poses: ArrayLike, at_index: int, rotvec_deg: ArrayLike) -> NDArray[np.float64]:
    """Rotate every pose from index ``at_index`` on about the sensor origin of that frame by the world-frame
    rotation vector ``rotvec_deg`` (direction = axis, length = angle in degrees)."""
    T = _poses(poses)
    if not 0 <= at_index < len(T):
        raise ConfigError(f"rotation_step: index {at_index} outside 0..{len(T) - 1}")
    R = Rotation.from_rotvec(np.radians(_vector(rotvec_deg, "rotvec_deg"))).as_matrix()
    pivot = T[at_index, :3, 3].copy()
    E = np.eye(4)
    E[:3, :3] = R
    E[:3, 3] = pivot - R @ pivot
    T[at_index:] = E @ T[at_index:]
    return T


def _unit(v: NDArray[np.float64], what: str) -> NDArray[np.float64]:
    """``v`` scaled to length 1 (scaled by its largest component first, so that components of 1e300 do not overflow
    the norm into a zero vector); :class:`ConfigError` for a zero vector."""
    big = float(np.max(np.abs(v)))
    if not big > 0:
        raise ConfigError(f"linear_drift: the {what} must be non-zero, got {v.tolist()}")
    v = v / big
    return v / np.linalg.norm(v)


def linear_drift(poses: ArrayLike, *, percent_per_m: float = 0.0, direction: ArrayLike = (1.0, 0.0, 0.0),
                 deg_per_m: float = 0.0, axis: ArrayLike = (0.0, 0.0, 1.0)) -> NDArray[np.float64]:
    """An error growing linearly with the distance travelled (see the module docstring).

    Frame k is moved by ``E_k = [R(axis, deg_per_m * s_k) about the first origin] + percent_per_m/100 * s_k * direction``.
    """
    T = _poses(poses)
    d, a = _unit(_vector(direction, "direction"), "direction"), _unit(_vector(axis, "axis"), "axis")
    s = path_length_m(T)
    pivot = T[0, :3, 3].copy() if len(T) else np.zeros(3)
    R = Rotation.from_rotvec(np.radians(deg_per_m * s)[:, None] * a).as_matrix()
    E = np.tile(np.eye(4), (len(T), 1, 1))
    E[:, :3, :3] = R
    E[:, :3, 3] = pivot - R @ pivot + (percent_per_m / 100.0) * s[:, None] * d
    return E @ T


PERTURBATION_BOUNDS = (("drift_percent_per_m", 100.0, "% of the path"), ("drift_deg_per_m", 360.0, "deg per m"))
"""The magnitudes a :class:`PosePerturbation` takes (per component)."""
MAX_STEP_DEG = 360.0
"""The longest rotation step (the length of ``step_deg``, degrees) a :class:`PosePerturbation` takes: a full turn."""


@dataclass(frozen=True)
class PosePerturbation:
    """A composition of the pose perturbations above (applied in the order: step, rotation step, drift)."""

    step_index: int | None = None
    step_m: tuple[float, float, float] | None = None
    step_deg: tuple[float, float, float] | None = None
    drift_percent_per_m: float = 0.0
    drift_direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    drift_deg_per_m: float = 0.0
    drift_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        for name in ("step_m", "step_deg", "drift_percent_per_m", "drift_direction", "drift_deg_per_m", "drift_axis"):
            value = getattr(self, name)
            if value is not None and not np.all(np.isfinite(np.asarray(value, dtype=np.float64))):
                raise ConfigError(f"PosePerturbation.{name}: must be finite, got {value!r}")
        for name, bound, unit in PERTURBATION_BOUNDS:
            value = getattr(self, name)
            if value is not None and np.any(np.abs(np.asarray(value, dtype=np.float64)) > bound):
                raise ConfigError(f"PosePerturbation.{name}: must be within +-{bound:g} {unit}, got {value!r} (a unit "
                                  f"mistake? no pose estimate drifts or jumps that far)")
        if self.step_deg is not None and float(np.hypot.reduce(np.asarray(self.step_deg, dtype=np.float64))) > MAX_STEP_DEG:
            raise ConfigError(f"PosePerturbation.step_deg: the rotation step must be within {MAX_STEP_DEG:g} deg (the "
                              f"length of the rotation vector), got {self.step_deg!r} (a unit mistake? no pose "
                              f"estimate jumps by more than a full turn)")
        for name, used in (("drift_direction", self.drift_percent_per_m), ("drift_axis", self.drift_deg_per_m)):
            if used and not np.max(np.abs(np.asarray(getattr(self, name), dtype=np.float64))) > 0:
                raise ConfigError(f"PosePerturbation.{name}: a drift needs a non-zero direction, got {getattr(self, name)!r}")

    def apply(self, poses: ArrayLike) -> NDArray[np.float64]:
        T = _poses(poses)
        if (self.step_m is not None or self.step_deg is not None) and self.step_index is None:
            raise ConfigError("a step needs the frame index it happens at")
        if self.step_m is not None:
            T = translation_step(T, self.step_index, self.step_m)
        if self.step_deg is not None:
            T = rotation_step(T, self.step_index, self.step_deg)
        if self.drift_percent_per_m or self.drift_deg_per_m:
            T = linear_drift(T, percent_per_m=self.drift_percent_per_m, direction=self.drift_direction,
                             deg_per_m=self.drift_deg_per_m, axis=self.drift_axis)
        return T


def perturb_pose_file(path_in: str | Path, path_out: str | Path, perturbation: PosePerturbation, *,
                      format: PoseFileFormat | str = PoseFileFormat.TUM, step_frame: int | None = None) -> Trajectory:
    """Read a TUM, KITTI or EuRoC file, perturb it, write it in the same format.

    ``step_frame`` (if given) is the frame at which the step happens: for KITTI the row index (row i is
    frame_id i), for TUM the row index too (rows in file order; the rows are sorted by stamp first).
    """
    fmt = parse_enum(PoseFileFormat, format, f"{path_in}: format")
    refuse_inside_store(path_out, "perturbed pose file")
    reader, writer = {PoseFileFormat.TUM: (read_tum, write_tum), PoseFileFormat.KITTI: (read_kitti, write_kitti),
                      PoseFileFormat.EUROC: (read_euroc, write_euroc)}[fmt]
    traj = reader(path_in)
    order = np.argsort(traj.stamps_ns, kind="stable")
    if step_frame is not None:
        perturbation = PosePerturbation(**{**perturbation.__dict__, "step_index": int(step_frame)})
    k = perturbation.step_index
    if k is not None and not 0 <= k < len(traj):
        raise ConfigError(f"{path_in}: the step frame {k} is not a row of the file (it has rows 0..{len(traj) - 1})")
    poses = perturbation.apply(traj.poses[order])
    out = np.empty_like(poses)
    out[order] = poses
    result = Trajectory(traj.stamps_ns.copy(), out, None if traj.frame_ids is None else traj.frame_ids.copy())
    Path(path_out).parent.mkdir(parents=True, exist_ok=True)
    writer(path_out, result)
    return result


# ---------------------------------------------------------------------------------------------- sensor errors


def scale_depth(points_sensor: ArrayLike, factor: float) -> NDArray[np.float32]:
    """Depth-scale error: points scaled radially from the sensor origin (``p * factor``)."""
    if not (np.isfinite(factor) and factor > 0):
        raise ConfigError(f"scale_depth: factor must be positive, got {factor}")
    return (np.asarray(points_sensor, dtype=np.float64) * factor).astype(np.float32)


def scale_focal(points_sensor: ArrayLike, f_true: float, f_assumed: float) -> NDArray[np.float32]:
    """Focal-length error: back-projection with ``f_assumed`` instead of ``f_true`` scales x and y by
    ``f_true / f_assumed`` (z, the depth, is unchanged). Sensor frame: optical axis z forward."""
    if not (f_true > 0 and f_assumed > 0):
        raise ConfigError(f"scale_focal: focal lengths must be positive, got {f_true} and {f_assumed}")
    p = np.asarray(points_sensor, dtype=np.float64).copy()
    p[:, :2] *= f_true / f_assumed
    return p.astype(np.float32)


def _without_normals(frame: Frame) -> PointAttributes:
    a = frame.attributes
    return PointAttributes(intensity=a.intensity, color_rgb=a.color_rgb, time_offset_ns=a.time_offset_ns)


def with_depth_scale_error(frame: Frame, factor: float) -> Frame:
    """The frame with its points scaled radially by ``factor`` (stored normals are dropped: they no longer hold)."""
    return frame.with_points(scale_depth(frame.points_sensor, factor), _without_normals(frame))


def with_focal_error(frame: Frame, f_assumed_over_true: float) -> Frame:
    """The frame as if back-projected with a focal length ``f_assumed_over_true`` times the true one."""
    return frame.with_points(scale_focal(frame.points_sensor, 1.0, f_assumed_over_true), _without_normals(frame))


def parse_vector(text: str | Sequence[float], name: str) -> tuple[float, float, float]:
    """``"x,y,z"`` -> a 3-tuple (for the command line)."""
    if isinstance(text, str):
        try:
            values = [float(v) for v in text.replace(" ", "").split(",") if v != ""]
        except ValueError as exc:
            raise ConfigError(f"{name}: expected 'x,y,z', got {text!r}") from exc
    else:
        values = [float(v) for v in text]
    if len(values) != 3:
        raise ConfigError(f"{name}: expected 3 comma-separated numbers 'x,y,z', got {text!r}")
    if not all(np.isfinite(values)):
        raise ConfigError(f"{name}: the numbers must be finite, got {text!r}")
    return (values[0], values[1], values[2])


# ---------------------------------------------------------------------------------------------- evaluation


@dataclass(frozen=True)
class StepDetection:
    """How well the double-wall detector found an injected translation step, at one voxel size.

    *Affected* surface groups: normal within ``max_angle_deg`` of the step, seen by at least
    ``min_frames_per_side`` frames on each side of the step (each side at least ``min_side_fraction`` of the
    points, both sides in at least ``min_shared_cells`` common lateral cells), and consistent across the
    step in the unperturbed map (``|offset after - before| <= max_baseline_m`` there, and the frames' mean
    offsets scatter by at most ``max_baseline_smear_m`` beyond noise), so the step is the only inconsistency.
    The expected separation is ``|step . normal|``.
    """

    voxel_size_m: float
    n_evaluated: int
    n_affected: int
    n_detected: int
    n_flagged_unaffected: int
    expected_m: NDArray[np.float64]
    """Per detected affected group: the expected separation."""
    measured_m: NDArray[np.float64]
    """Per detected affected group: the separation the detector reported."""
    affected: NDArray[np.bool_]
    """Per surface group of the scale: affected by the step (as defined above)."""

    @property
    def detection_rate(self) -> float:
        return self.n_detected / self.n_affected if self.n_affected else float("nan")

    @property
    def separation_error_m(self) -> NDArray[np.float64]:
        return self.measured_m - self.expected_m

    def within_tolerance(self, abs_m: float = 0.005, rel: float = 0.15) -> NDArray[np.bool_]:
        """Per detected group: ``|error| <= max(abs_m, rel * expected)``."""
        return np.abs(self.separation_error_m) <= np.maximum(abs_m, rel * self.expected_m)


def dominant_normals(normals_world: ArrayLike, n: int = 3, *, angle_deg: float = 15.0, min_separation_deg: float = 45.0,
                     seed: int = 0) -> list[NDArray[np.float64]]:
    """The ``n`` most common surface-normal directions (sign-free) of a placed cloud's ``normals_world``, each
    at least ``min_separation_deg`` from the others: the step directions of the perturbation protocol (a step
    along a direction no surface faces is invisible to any consistency measure). A direction's support is the
    number of normals within ``angle_deg``; the direction returned is their sign-aligned mean."""
    normals = np.asarray(normals_world, dtype=np.float64)
    if normals.ndim != 2 or normals.shape[1] != 3 or len(normals) < 10:
        raise ConfigError(f"dominant_normals: need (N >= 10, 3) normals, got shape {normals.shape}")
    rng = np.random.default_rng(seed)
    candidates = normals[rng.choice(len(normals), min(3000, len(normals)), replace=False)]
    ref = normals[::10]
    cos = np.cos(np.radians(angle_deg))
    support = (np.abs(candidates @ ref.T) >= cos).sum(axis=1)
    out: list[NDArray[np.float64]] = []
    for i in np.argsort(-support):
        c = candidates[i]
        if all(abs(c @ o) < np.cos(np.radians(min_separation_deg)) for o in out):
            near = ref[np.abs(ref @ c) >= cos]
            m = (near * np.sign(near @ c)[:, None]).mean(axis=0)
            out.append(m / np.linalg.norm(m))
        if len(out) == n:
            break
    return out


def evaluate_step(samples: DiagnosticCloud, base_poses: ArrayLike, step_index: int, step_m: ArrayLike,
                  result: DoubleWallResult, *, max_angle_deg: float = 25.0, min_frames_per_side: int = 2, min_side_fraction: float = 0.1,
                  max_baseline_m: float = 0.003, max_baseline_smear_m: float | None = 0.004) -> list[StepDetection]:
    """Score a :class:`~driftmap.diagnostics.double_wall.DoubleWallResult` computed on ``samples`` placed with
    ``translation_step(base_poses, step_index, step_m)`` against what that step must produce."""
    from driftmap.diagnostics.surfaces import surface_groups

    base = np.asarray(base_poses, dtype=np.float64)
    step = _vector(step_m, "step_m")
    mag = float(np.linalg.norm(step))
    if mag == 0:
        raise ConfigError("evaluate_step: the step is zero")
    perturbed = samples.place(translation_step(base, step_index, step))
    unperturbed = samples.place(base)
    cfg = result.config
    out = []
    for scale in result.scales:
        sg = surface_groups(perturbed, scale.voxel_size_m, normal_max_angle_deg=cfg.normal_max_angle_deg,
                            second_surface=cfg.second_surface, min_points=cfg.min_points, cell_fraction=cfg.cell_fraction,
                            max_cell_m=cfg.max_cell_m)
        G, C = sg.n_groups, sg.n_cells
        if G != len(scale.evaluated):
            raise ConfigError("evaluate_step: the result was not computed on these samples and poses")
        rows = perturbed.frame_index[sg.point_index]
        after = rows >= step_index
        o_base = np.einsum("ij,ij->i", unperturbed.points_world[sg.point_index] - sg.centers_m[sg.group], sg.normals[sg.group])
        nA = np.bincount(sg.cell, weights=~after, minlength=C)
        nB = np.bincount(sg.cell, weights=after, minlength=C)
        shared = (nA > 0) & (nB > 0)
        sA = np.bincount(sg.cell, weights=~after * o_base, minlength=C)
        sB = np.bincount(sg.cell, weights=after * o_base, minlength=C)
        d = np.where(shared, sB / np.maximum(nB, 1) - sA / np.maximum(nA, 1), 0.0)
        w = np.where(shared, nA * nB / np.maximum(nA + nB, 1), 0.0)
        W = np.bincount(sg.cell_group, weights=w, minlength=G)
        baseline = np.bincount(sg.cell_group, weights=w * d, minlength=G) / np.maximum(W, 1e-12)
        n_shared = np.bincount(sg.cell_group, weights=shared.astype(np.float64), minlength=G)
        clean = np.ones(G, bool)
        if max_baseline_smear_m is not None:
            clean = _baseline_smear(sg, rows, o_base, samples.n_frames, G, C) <= max_baseline_smear_m
        # frames per side (with enough points in the group, as the detector counts them)
        ok = scale.gf_points >= cfg.min_points_per_frame
        side = scale.gf_frame >= step_index
        fa = np.bincount(scale.gf_group, weights=ok & ~side, minlength=G)
        fb = np.bincount(scale.gf_group, weights=ok & side, minlength=G)
        pa = np.bincount(scale.gf_group, weights=(ok & ~side) * scale.gf_points, minlength=G)
        pb = np.bincount(scale.gf_group, weights=(ok & side) * scale.gf_points, minlength=G)
        frac = np.minimum(pa, pb) / np.maximum(pa + pb, 1)
        cos = np.abs(sg.normals @ step) / mag
        affected = (scale.evaluated & (cos >= np.cos(np.radians(max_angle_deg))) & (fa >= min_frames_per_side)
                    & (fb >= min_frames_per_side) & (frac >= min_side_fraction) & (n_shared >= cfg.min_shared_cells)
                    & (np.abs(baseline) <= max_baseline_m) & clean)
        detected = affected & scale.flagged
        out.append(StepDetection(
            voxel_size_m=scale.voxel_size_m, n_evaluated=int(scale.evaluated.sum()), n_affected=int(affected.sum()),
            n_detected=int(detected.sum()), n_flagged_unaffected=int((scale.flagged & ~affected).sum()),
            expected_m=np.abs(sg.normals[detected] @ step),
            measured_m=np.abs(scale.separation_m[detected]),
            affected=affected,
        ))
    return out


def _baseline_smear(sg: SurfaceGroups, rows: NDArray[np.int64], offset: NDArray[np.float64], n_frames: int, G: int, C: int) -> NDArray[np.float64]:
    """Per surface group of ``sg``: point-weighted scatter of the frames' mean offsets (relative to the lateral-cell
    means, as the detector computes them) beyond what the pooled within-frame scatter explains."""
    c_n = np.bincount(sg.cell, minlength=C).astype(np.float64)
    r = offset - np.bincount(sg.cell, weights=offset, minlength=C)[sg.cell] / c_n[sg.cell]
    gf, keys = dense_ids(sg.group * n_frames + rows)
    E = len(keys)
    e_g = keys // n_frames
    n = np.bincount(gf, minlength=E).astype(np.float64)
    m = np.bincount(gf, weights=r, minlength=E) / n
    sq = np.bincount(gf, weights=r * r, minlength=E)
    within = np.bincount(e_g, weights=np.maximum(sq - n * m * m, 0.0), minlength=G)
    dof = np.bincount(e_g, weights=n - 1, minlength=G)
    W = np.bincount(e_g, weights=n, minlength=G)
    mbar = np.bincount(e_g, weights=n * m, minlength=G) / np.maximum(W, 1)
    disp = np.bincount(e_g, weights=n * (m - mbar[e_g]) ** 2, minlength=G) / np.maximum(W, 1)
    nf = np.bincount(e_g, minlength=G)
    noise = within / np.maximum(dof, 1) * nf / np.maximum(W, 1)
    return np.sqrt(np.maximum(disp - noise, 0.0))
