"""The perturbation sweep: perturb exactly one geometric assumption of a store's frames at several magnitudes, decide
the same queries on each perturbed copy, and record which decisions flipped against the unperturbed store.

Each assumption (:data:`ASSUMPTIONS`) turns a frame (sensor points and pose) into its perturbed version; a seed
draws what is random about it (which points drop out, where the occluder sits, the drift's direction, the extrinsic
error's axis) and is the same for every magnitude, so that magnitudes differ only in size:

- ``dropout_random``: a fraction of each frame's points lost at random;
- ``dropout_structured``: vertical bands of image columns lost (a fraction of every 32 columns, at a phase per seed
  that wanders from frame to frame), as on dark, shiny or far surfaces;
- ``occlusion``: a rectangle of the image (its area a fraction of the image's, the same place in every frame)
  masked, as by a smudge or a cable across the lens;
- ``depth_scale``: ranges scaled by ``1 + m / 100``;
- ``pose_drift``: a translation drift of ``m`` % of the path travelled, in a horizontal direction per seed;
- ``motion``: a translation step of ``m`` cm at the middle frame (a slip), in a horizontal direction per seed;
- ``focal_length``: back-projection with ``1 + m / 100`` times the true focal length;
- ``extrinsic_rotation``: the sensor's mounting turned by ``m`` deg about an axis per seed.

Image-based assumptions need a depth camera (frames with intrinsics). ``scripts/decision_sweep.py`` runs the whole
sweep and writes the table and plots of docs/decisions.md.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from driftmap.decisions.compare import compare
from driftmap.decisions.decide import as_query_set, decide
from driftmap.decisions.records import DecisionSet
from driftmap.diagnostics import perturb
from driftmap.errors import ConfigError
from driftmap.frame import Frame, PoseEstimate
from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)

BAND_PERIOD_PX = 32
"""``dropout_structured``: the bands repeat every this many image columns."""


@dataclass(frozen=True)
class Assumption:
    """One geometric assumption: its unit, the default magnitudes of the sweep, and how it perturbs a log."""

    name: str
    unit: str
    magnitudes: tuple[float, ...]
    perturb_points: Callable[[Frame, float, np.random.Generator, dict], NDArray[np.float32]] | None = None
    perturb_poses: Callable[[NDArray[np.float64], float, dict], NDArray[np.float64]] | None = None
    needs_image: bool = False


def _pixels(frame: Frame) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    k = frame.intrinsics
    p = frame.points_sensor.astype(np.float64)
    z = np.where(p[:, 2] > 0, p[:, 2], np.nan)
    return k.fx * p[:, 0] / z + k.cx, k.fy * p[:, 1] / z + k.cy


def _dropout_random(frame: Frame, m: float, rng: np.random.Generator, draw: dict) -> NDArray[np.float32]:
    return frame.points_sensor[rng.random(frame.n_points) >= m]


def _dropout_structured(frame: Frame, m: float, rng: np.random.Generator, draw: dict) -> NDArray[np.float32]:
    u, _ = _pixels(frame)
    phase = draw["phase_px"] + 7.0 * frame.frame_id  # the bands wander from frame to frame
    lost = np.mod(u - phase, BAND_PERIOD_PX) < m * BAND_PERIOD_PX
    return frame.points_sensor[~lost]


def _occlusion(frame: Frame, m: float, rng: np.random.Generator, draw: dict) -> NDArray[np.float32]:
    k = frame.intrinsics
    u, v = _pixels(frame)
    w, h = k.width * np.sqrt(m), k.height * np.sqrt(m)  # the rectangle's area is m of the image's
    u0, v0 = draw["corner"][0] * (k.width - w), draw["corner"][1] * (k.height - h)
    lost = (u >= u0) & (u < u0 + w) & (v >= v0) & (v < v0 + h)
    return frame.points_sensor[~lost]


def _depth_scale(frame: Frame, m: float, rng: np.random.Generator, draw: dict) -> NDArray[np.float32]:
    return perturb.scale_depth(frame.points_sensor, 1.0 + m / 100.0)


def _focal_length(frame: Frame, m: float, rng: np.random.Generator, draw: dict) -> NDArray[np.float32]:
    return perturb.scale_focal(frame.points_sensor, 1.0, 1.0 + m / 100.0)


def _extrinsic_rotation(frame: Frame, m: float, rng: np.random.Generator, draw: dict) -> NDArray[np.float32]:
    R = Rotation.from_rotvec(np.radians(m) * draw["axis"]).as_matrix()
    return (frame.points_sensor.astype(np.float64) @ R.T).astype(np.float32)


def _pose_drift(poses: NDArray[np.float64], m: float, draw: dict) -> NDArray[np.float64]:
    return perturb.linear_drift(poses, percent_per_m=m, direction=draw["direction"])


def _motion(poses: NDArray[np.float64], m: float, draw: dict) -> NDArray[np.float64]:
    return perturb.translation_step(poses, len(poses) // 2, draw["direction"] * m / 100.0)


ASSUMPTIONS: dict[str, Assumption] = {a.name: a for a in (
    Assumption("dropout_random", "fraction", (0.5, 0.7, 0.85, 0.95), perturb_points=_dropout_random),
    Assumption("dropout_structured", "fraction", (0.25, 0.5, 0.75, 0.9), perturb_points=_dropout_structured,
               needs_image=True),
    Assumption("occlusion", "fraction of the image", (0.1, 0.2, 0.35, 0.5, 0.7, 0.9), perturb_points=_occlusion,
               needs_image=True),
    Assumption("depth_scale", "%", (0.5, 1.0, 2.0, 4.0), perturb_points=_depth_scale),
    Assumption("pose_drift", "%/m", (0.5, 1.0, 2.0, 4.0), perturb_poses=_pose_drift),
    Assumption("motion", "cm", (2.0, 4.0, 8.0, 16.0), perturb_poses=_motion),
    Assumption("focal_length", "%", (2.0, 4.0, 8.0, 16.0), perturb_points=_focal_length, needs_image=True),
    Assumption("extrinsic_rotation", "deg", (0.25, 0.5, 1.0, 2.0, 4.0, 8.0), perturb_points=_extrinsic_rotation),
)}


def _draw(seed: int) -> dict:
    """What is random about a perturbation, per seed (the same for every magnitude and assumption)."""
    rng = np.random.default_rng(seed)
    heading = rng.uniform(0.0, 2.0 * np.pi)
    axis = rng.normal(size=3)
    return {"direction": np.array([np.cos(heading), np.sin(heading), 0.0]), "axis": axis / np.linalg.norm(axis),
            "phase_px": rng.uniform(0.0, BAND_PERIOD_PX), "corner": rng.uniform(0.2, 0.8, 2)}


def perturbed_frames(store: FrameStore, revision: int, assumption: str, magnitude: float,
                     seed: int = 0) -> Iterable[Frame]:
    """The frames of ``store`` at ``revision`` with ``assumption`` perturbed by ``magnitude`` (its unit), as
    revision-0 frames of a new store. Where the points change, their attributes (normals, intensity, colour)
    are dropped: decisions use the geometry alone."""
    a = ASSUMPTIONS.get(assumption)
    if a is None:
        raise ConfigError(f"perturbation sweep: unknown assumption {assumption!r}; known: {', '.join(ASSUMPTIONS)}")
    if not np.isfinite(magnitude) or magnitude < 0:
        raise ConfigError(f"perturbation sweep: {assumption}: magnitude must be a finite number >= 0, got {magnitude}")
    if a.name.startswith("dropout") and magnitude >= 1.0:
        raise ConfigError(f"perturbation sweep: {assumption}: a fraction below 1 is needed, got {magnitude}")
    draw = _draw(seed)
    placed = store.ledger.member_rows(revision)  # the frames the revision places
    poses = store.poses(revision)[placed]
    if a.perturb_poses is not None:
        poses = a.perturb_poses(poses, magnitude, draw)
    rng = np.random.default_rng([seed, 25])
    for row, fid in enumerate(store.frame_ids[placed]):
        frame = store.frame(int(fid))
        if a.needs_image and frame.intrinsics is None:
            raise ConfigError(f"perturbation sweep: {assumption} masks image pixels; frame {int(fid)} has no camera "
                              "intrinsics (a depth camera is needed)")
        if a.perturb_points is not None:
            points = a.perturb_points(frame, magnitude, rng, draw)
            frame = frame.with_points(points, None)
        yield frame.with_pose(PoseEstimate(poses[row], revision=0, source=frame.pose.source,
                                           world_frame=frame.pose.world_frame))


@dataclass
class SweepRun:
    """One perturbed store's decisions against the unperturbed ones."""

    assumption: str
    magnitude: float
    seed: int
    flipped_fraction: float
    flipped: list[str]
    median_abs_margin_delta_m: float | None
    """over the decisions whose margin is a length (clearance, collision)"""
    max_abs_margin_delta_m: float | None

    def to_json(self) -> dict:
        return dict(self.__dict__)


def spearman_by_assumption(runs: Sequence[dict]) -> dict[str, float | None]:
    """Per assumption (in the order of ``runs``), the Spearman rank correlation of the flipped fraction with the
    magnitude over all its runs (every magnitude and seed); None where either is constant."""
    from scipy.stats import spearmanr

    out: dict[str, float | None] = {}
    for name in dict.fromkeys(r["assumption"] for r in runs):
        m, f = np.array([(r["magnitude"], r["flipped_fraction"]) for r in runs if r["assumption"] == name]).T
        out[name] = None if np.ptp(m) == 0 or np.ptp(f) == 0 else float(spearmanr(m, f).statistic)
    return out


@dataclass
class SweepResult:
    """Every run, and per assumption the Spearman rank correlation of the flipped fraction with the magnitude."""

    baseline: DecisionSet
    runs: list[SweepRun] = field(default_factory=list)

    def spearman(self) -> dict[str, float | None]:
        return spearman_by_assumption([r.to_json() for r in self.runs])

    def to_json(self) -> dict:
        return {"n_queries": len(self.baseline), "runs": [r.to_json() for r in self.runs], "spearman": self.spearman()}


def sweep(store: FrameStore, queries, work_dir: str | Path, *, revision: int | None = None,
          assumptions: Sequence[str] | None = None, magnitudes: dict[str, Sequence[float]] | None = None,
          seeds: Sequence[int] = (0, 1), progress: Callable[[str], None] | None = None) -> SweepResult:
    """Decide ``queries`` on ``store`` (``revision``, default the head) and on a perturbed copy of it per assumption,
    magnitude and seed (each copy written to ``work_dir`` and removed after its decisions); record the flips.
    ``magnitudes``: per assumption, instead of its defaults."""
    qs = as_query_set(queries)
    rev = store.head if revision is None else int(revision)
    names = list(ASSUMPTIONS) if assumptions is None else list(assumptions)
    for name in names:
        if name not in ASSUMPTIONS:
            raise ConfigError(f"perturbation sweep: unknown assumption {name!r}; known: {', '.join(ASSUMPTIONS)}")
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    result = SweepResult(baseline=decide(store, qs, rev))
    for name in names:
        for magnitude in (magnitudes or {}).get(name, ASSUMPTIONS[name].magnitudes):
            for seed in seeds:
                path = work / f"{name}-{magnitude:g}-{seed}"
                shutil.rmtree(path, ignore_errors=True)
                with FrameStore.create(path) as copy:
                    for frame in perturbed_frames(store, rev, name, float(magnitude), seed):
                        copy.append(frame)
                comparison = compare(result.baseline, decide(FrameStore.open(path), qs, 0))
                shutil.rmtree(path, ignore_errors=True)
                metric = {q.id for q in qs if q.kind in ("clearance", "collision")}
                deltas = np.abs([v for k, v in comparison.margin_deltas.items() if v is not None and k in metric])
                run = SweepRun(name, float(magnitude), int(seed), comparison.flipped_fraction, comparison.flipped_ids(),
                               float(np.median(deltas)) if len(deltas) else None,
                               float(deltas.max()) if len(deltas) else None)
                result.runs.append(run)
                logger.info("sweep %s %g (seed %d): %.1f %% flipped", name, magnitude, seed, 100 * run.flipped_fraction)
                if progress is not None:
                    progress(f"{name} {magnitude:g} seed {seed}: {100 * run.flipped_fraction:.1f} % flipped")
    return result
