"""One diagnosis of a stored map: :func:`diagnose_store` samples the store and calls :func:`diagnose_cloud`,
the one function that runs the steps in order on samples placed with a revision's poses:

1. place the samples (:meth:`~driftmap.diagnostics.samples.DiagnosticCloud.place`);
2. double walls and smearing (:func:`~driftmap.diagnostics.detector.detect_double_walls`);
3. attribution: per-frame disagreement, change points, drift rate (:func:`~driftmap.diagnostics.attribution.attribute`);
4. Mean Map Entropy / Mean Plane Variance (:func:`~driftmap.diagnostics.entropy.map_entropy`);
5. the revisit check (:func:`~driftmap.diagnostics.revisits.check_revisits`: pose errors beyond the detector's
   range), coverage and the causes of the double walls (:func:`~driftmap.diagnostics.coverage.assess`,
   :func:`~driftmap.diagnostics.causes.explain_regions`);
6. with ground truth, ATE / RPE / segment errors (:func:`~driftmap.diagnostics.ground_truth.ground_truth_errors`);
7. for a store of several sessions (a merged store), :func:`diagnose_store` adds the changes between the sessions
   (:func:`~driftmap.diagnostics.changes.session_changes`): ``changed`` regions, and per double-wall region the
   sessions on each side and whether a change explains it.

The result is a :class:`Diagnosis` (and its JSON, :meth:`Diagnosis.to_json`); nothing here writes a file
(figures: :mod:`driftmap.diagnostics.figures`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeVar

import numpy as np
from numpy.typing import NDArray

from driftmap.diagnostics.attribution import Attribution, attribute
from driftmap.diagnostics.causes import RegionCause, explain_regions
from driftmap.diagnostics.changes import ChangeConfig, SessionChanges, session_changes
from driftmap.diagnostics.coverage import Coverage, assess
from driftmap.diagnostics.detector import detect_double_walls
from driftmap.diagnostics.diagnose_config import DiagnoseConfig
from driftmap.diagnostics.entropy import MapEntropy, map_entropy
from driftmap.diagnostics.ground_truth import MIN_GT_FRAMES, ground_truth_errors
from driftmap.diagnostics.revisits import RevisitCheck, check_revisits
from driftmap.diagnostics.samples import DiagnosticCloud, PlacedCloud
from driftmap.diagnostics.verify import RegionCheck, verification_summary
from driftmap.diagnostics.wall_results import DoubleWallResult
from driftmap.errors import ConfigError, StoreError
from driftmap.preprocess.noise import NoiseModel

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore

T = TypeVar("T")
logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Diagnosis:
    """Everything ``diagnose`` found for one revision (``placed`` is kept for the figures)."""

    revision: int
    double_walls: DoubleWallResult
    attribution: Attribution
    entropy: MapEntropy
    trajectory: dict | None
    config: DiagnoseConfig
    placed: PlacedCloud
    seconds: dict[str, float] = field(default_factory=dict)
    verification: list[RegionCheck] | None = None
    """Per region (same order), the independent check of :func:`driftmap.diagnostics.verify.verify_regions`."""
    coverage: Coverage | None = None
    """How much of the map was judged, why the rest not, and which headline figures are a verdict."""
    causes: list[RegionCause] | None = None
    """Per double-wall region (same order), what caused it (:mod:`driftmap.diagnostics.causes`)."""
    revisits: RevisitCheck | None = None
    """Revisiting frames registered onto the earlier map: pose errors beyond the detector's range
    (:mod:`driftmap.diagnostics.revisits`)."""
    session_changes: SessionChanges | None = None
    """A store of several sessions: the regions where the world changed between them
    (:mod:`driftmap.diagnostics.changes`)."""
    sessions: dict[int, list[int]] | None = None
    """A store of several sessions: ``{session: [frame ids]}``."""
    session_changes_skipped: str | None = None
    """A store of several sessions whose changes could not be judged: why (e.g. a LiDAR store without a max range)."""
    store_uuid: str | None = None
    """The diagnosed store's id (:attr:`FrameStore.uuid`; None for a diagnosis of a cloud), so that a tool reading the
    diagnosis (``decide --diagnosis``) can tell it is of the store it is given."""

    @property
    def smearing_score_m(self) -> float:
        return self.double_walls.smearing_score_m

    def to_json(self) -> dict:
        dw, at = self.double_walls, self.attribution
        out = {
            "revision": int(self.revision),
            "store_uuid": self.store_uuid,
            "smearing_score_m": _num(dw.smearing_score_m),
            "smearing_score_per_scale_m": {f"{k:g}": _num(v) for k, v in dw.score_per_scale_m.items()},
            "smearing_score_revisit_m": _num(dw.revisit_score_m(at.config.revisit_min_path_m)),
            "smearing_score_frames_m": _num(dw.frame_smearing_score_m),
            "double_wall": dw.to_json(),
            "frames": at.frames_json(),
            "change_points": [c.to_json() for c in at.change_points],
            "revisit_fraction": float(at.revisit_fraction),
            "revisit_note": at.revisit_note,
            "drift_rate": {"percent_per_m": at.drift.percent_per_m, "deg_per_m": at.drift.deg_per_m,
                           "n_frames": at.drift.n_frames, "path_span_m": at.drift.path_span_m,
                           "noise_floor_m": at.drift.noise_floor_m, "noise_floor_deg": at.drift.noise_floor_deg},
            "mme": _num(self.entropy.mme),
            "mpv": _num(self.entropy.mpv_m2),
            "entropy": {"mme_unit": "nats", "mpv_unit": "m^2",
                        "mpv_definition": "mean smallest eigenvalue of the neighbourhood covariance",
                        "radius_m": self.entropy.radius_m, "min_neighbors": self.entropy.min_neighbors,
                        "max_neighbors": self.entropy.max_neighbors, "n_points_used": self.entropy.n_points_used,
                        "n_points_queried": self.entropy.n_points_queried},
            "valid": None if self.coverage is None else self.coverage.valid,
            "reasons": [] if self.coverage is None else self.coverage.reasons,
            "fraction_inconsistent": None if self.coverage is None else self.coverage.fraction_inconsistent,
            "coverage": None if self.coverage is None else self.coverage.to_json(),
            "revisit_check": None if self.revisits is None else self.revisits.to_json(),
            "n_frames": int(len(at.frame_ids)),
            "n_points_sampled": int(self.placed.samples.n_points),
            "config": self.config.model_dump(mode="json"),
            "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
        }
        if self.causes is not None:
            for region_json, cause in zip(out["double_wall"]["regions"], self.causes):
                region_json["cause"] = cause.cause
                region_json["cause_explanation"] = cause.explanation
                region_json["cause_evidence"] = cause.evidence
            counts: dict[str, int] = {}
            for cause in self.causes:
                counts[cause.cause] = counts.get(cause.cause, 0) + 1
            out["double_wall"]["causes"] = counts
        if self.trajectory is not None:
            out["trajectory"] = self.trajectory
        if self.verification is not None:
            for region_json, check in zip(out["double_wall"]["regions"], self.verification):
                region_json["verification"] = check.to_json()
            out["double_wall"]["verified"] = verification_summary(self.verification, dw.regions, dw.voxels_evaluated)
        if self.session_changes_skipped is not None:
            out["session_changes"] = {"regions": [], "skipped": self.session_changes_skipped}
        if self.session_changes is not None:
            out["session_changes"] = self.session_changes.to_json()
            self._annotate_sessions(out["double_wall"], out["session_changes"])
        return out

    def double_wall_verdicts(self) -> list[tuple[str, int | None]]:
        """Per double-wall region (same order), ``("changed", k)`` when its centre lies in change region ``k`` (the
        world changed there between sessions: not a misalignment), else ``("double_wall", None)``."""
        changes = self.session_changes
        out: list[tuple[str, int | None]] = []
        for region in self.double_walls.regions:
            k = None if changes is None else changes.region_at(region.center_m, changes.voxel_size_m)
            out.append(("double_wall", None) if k is None else ("changed", k))
        return out

    def region_sessions(self, frame_ids: NDArray[np.int64]) -> dict[int, int]:
        """How many of the frames belong to each session (of :attr:`sessions`; sessions without one left out)."""
        if not self.sessions:
            return {}
        ids = np.asarray(frame_ids, dtype=np.int64)
        counts = {s: int(np.isin(ids, np.asarray(members, np.int64)).sum()) for s, members in sorted(self.sessions.items())}
        return {s: n for s, n in counts.items() if n}

    def _annotate_sessions(self, double_wall: dict, changes: dict) -> None:
        """Per double-wall region: the sessions of layers A and B (frames per session, and the session holding most
        of them) and the verdict (``changed`` wins where a change
        region holds the region's centre); per change region the double-wall regions it explains."""
        for c in changes["regions"]:
            c["double_wall_regions"] = []
        for k, (region_json, region, (verdict, ck)) in enumerate(zip(double_wall["regions"], self.double_walls.regions,
                                                                      self.double_wall_verdicts())):
            for side, frames in (("a", region.frames_a), ("b", region.frames_b)):
                counts = self.region_sessions(frames)
                region_json[f"session_frames_{side}"] = {str(k): v for k, v in counts.items()}
                region_json[f"session_{side}"] = max(counts, key=lambda k: (counts[k], -k)) if counts else None
            region_json["verdict"] = verdict
            if ck is not None:
                region_json["change_region"] = int(ck)
                changes["regions"][ck]["double_wall_regions"].append(k)
        verdicts = [v for v, _ in self.double_wall_verdicts()]
        changes["double_wall_regions_changed"] = verdicts.count("changed")
        changes["double_wall_regions_misaligned"] = verdicts.count("double_wall")


def _num(v: float | None) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def _timed(seconds: dict[str, float], name: str, step: Callable[[], T]) -> T:
    """Run ``step`` and add its wall time to ``seconds[name]``."""
    t = time.perf_counter()
    result = step()
    seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t
    return result


def diagnose_cloud(cloud: DiagnosticCloud, poses: NDArray[np.float64], *, revision: int = 0,
                   config: DiagnoseConfig | None = None, ground_truth: NDArray[np.float64] | None = None,
                   ground_truth_rows: NDArray[np.int64] | None = None,
                   row_sessions: NDArray[np.int64] | None = None) -> Diagnosis:
    """Diagnose samples placed with ``poses`` (rows in the cloud's frame order): the steps of the module
    docstring, in order, each timed in :attr:`Diagnosis.seconds`.

    ``ground_truth``: (K, 4, 4) poses of the frame rows ``ground_truth_rows`` (default: all rows) for ATE/RPE.
    ``row_sessions``: a merged store's session of each frame row (the revisit check's pairs across sessions have no
    travel between them, and a session's start is no jump of the trajectory).
    """
    cfg = config or DiagnoseConfig()
    seconds: dict[str, float] = {}
    placed = _timed(seconds, "place", lambda: cloud.place(poses))
    walls = _timed(seconds, "double_walls", lambda: detect_double_walls(placed, cfg.double_wall))
    attribution = _timed(seconds, "attribution", lambda: attribute(placed, cfg.attribution, row_sessions))
    e = cfg.entropy
    entropy = _timed(seconds, "mme_mpv", lambda: map_entropy(placed.points_world, radius_m=e.radius_m,
                                                             min_neighbors=e.min_neighbors, max_neighbors=e.max_neighbors,
                                                             max_query_points=e.max_query_points))
    revisits = _timed(seconds, "revisit_check", lambda: check_revisits(placed, cfg.revisits, row_sessions))
    coverage = _timed(seconds, "coverage", lambda: assess(placed, walls, attribution.drift.n_frames, cfg.coverage,
                                                          revisits, attribution.drift.percent_per_m,
                                                          attribution.drift.deg_per_m))
    causes = _timed(seconds, "coverage", lambda: explain_regions(placed, walls))
    trajectory = None
    if ground_truth is not None:
        trajectory = _trajectory_errors(placed, cloud.n_frames, ground_truth, ground_truth_rows)
    return Diagnosis(revision, walls, attribution, entropy, trajectory, cfg, placed, seconds, coverage=coverage,
                     causes=causes, revisits=revisits)


def _trajectory_errors(placed: PlacedCloud, n_frames: int, ground_truth: NDArray[np.float64],
                       ground_truth_rows: NDArray[np.int64] | None) -> dict:
    """ATE / RPE / segment errors of the placed poses of ``ground_truth_rows`` against ``ground_truth``."""
    rows = np.arange(n_frames) if ground_truth_rows is None else np.asarray(ground_truth_rows, dtype=np.int64)
    gt = np.asarray(ground_truth, dtype=np.float64).reshape(-1, 4, 4)
    if len(rows) != len(gt):
        raise ConfigError(f"ground truth: {len(gt)} poses for {len(rows)} frame rows")
    if len(rows) < MIN_GT_FRAMES:
        raise ConfigError(f"ground truth matched only {len(rows)} frames; ATE needs at least {MIN_GT_FRAMES}")
    trajectory = ground_truth_errors(placed.poses[rows], gt)
    trajectory["n_frames_matched"] = int(len(rows))
    return trajectory


def _ground_truth_rows(cloud: DiagnosticCloud, ground_truth: tuple[NDArray[np.int64], NDArray[np.float64]]
                       ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The cloud's frame rows that have a ground-truth pose (ascending), and those poses."""
    gt_ids, gt_all = ground_truth
    row_of = {int(f): k for k, f in enumerate(cloud.frame_ids)}
    pairs = [(row_of[int(f)], k) for k, f in enumerate(gt_ids) if int(f) in row_of]
    gt_rows = np.array([p[0] for p in pairs], dtype=np.int64)
    gt_poses = np.asarray(gt_all)[[p[1] for p in pairs]]
    order = np.argsort(gt_rows)
    return gt_rows[order], gt_poses[order]


def diagnose_store(store: FrameStore, revision: int | None = None, *, config: DiagnoseConfig | None = None,
                   cloud: DiagnosticCloud | None = None, ground_truth: tuple[NDArray[np.int64], NDArray[np.float64]] | None = None,
                   noise: NoiseModel | None = None, sessions: dict[int, list[int]] | None = None,
                   change_config: ChangeConfig | None = None) -> Diagnosis:
    """Diagnose a store's map in ``revision`` (default: head): sample it (unless ``cloud`` reuses samples across
    revisions), then :func:`diagnose_cloud` with the revision's poses. ``ground_truth`` is ``(frame_ids, poses)``
    as from :func:`~driftmap.pipeline.pose_files.read_ground_truth`. ``sessions`` (``{session: [frame ids]}``, e.g.
    :func:`driftmap.pipeline.merge.store_sessions`): with two or more, the changes between them are added
    (:func:`~driftmap.diagnostics.changes.session_changes` with ``change_config``)."""
    rev = store.head if revision is None else int(revision)
    store.ledger.revision(rev)  # raises for an unknown revision
    if len(store) == 0:
        raise StoreError(f"{store.path}: the store has no frames")
    if config is None:
        config = DiagnoseConfig.for_store(store)
    members = store.members(rev)  # the frames the revision places (not those stored after it)
    if sessions is not None:
        placed = set(members.tolist())
        sessions = {k: [f for f in ids if int(f) in placed] for k, ids in sessions.items()}
        sessions = {k: ids for k, ids in sessions.items() if ids}
    t = time.perf_counter()
    if cloud is None:
        cloud = DiagnosticCloud.from_store(store, config.sampling, noise,
                                           sessions=sessions if sessions is not None and len(sessions) >= 2 else None)
    sampling_s = time.perf_counter() - t
    if not np.all(np.isin(cloud.frame_ids, members)):
        logger.info("diagnose: revision %d places %d of the %d sampled frames (the others were stored after it, or "
                    "left out by a rollback)", rev, int(np.isin(cloud.frame_ids, members).sum()), cloud.n_frames)
        cloud = cloud.subset(np.flatnonzero(np.isin(cloud.frame_ids, members)))
    poses = store.poses(rev)[np.searchsorted(store.frame_ids, cloud.frame_ids)]
    gt_rows = gt_poses = None
    if ground_truth is not None:
        gt_rows, gt_poses = _ground_truth_rows(cloud, ground_truth)
    row_sessions = None
    if sessions is not None and len(sessions) >= 2:
        of = {int(f): k for k, ids in sessions.items() for f in ids}
        row_sessions = np.array([of.get(int(f), -1) for f in cloud.frame_ids], dtype=np.int64)
    diagnosis = diagnose_cloud(cloud, poses, revision=rev, config=config, ground_truth=gt_poses, ground_truth_rows=gt_rows,
                               row_sessions=row_sessions)
    diagnosis.seconds["sampling"] = sampling_s
    diagnosis = dataclasses.replace(diagnosis, store_uuid=store.uuid)
    if sessions is not None and len(sessions) >= 2:
        t = time.perf_counter()
        try:
            changes = session_changes(store, sessions, rev, change_config or ChangeConfig(
                margin_m=config.revisits.max_detectable_m))  # the detector's range: a misalignment is no change
        except ConfigError as exc:  # e.g. a LiDAR store without a max range: the rest of the diagnosis stands
            logger.warning("diagnose: the changes between the sessions of %s are not judged: %s", store.path, exc)
            diagnosis = dataclasses.replace(diagnosis, sessions=sessions, session_changes_skipped=str(exc))
        else:
            diagnosis = dataclasses.replace(diagnosis, session_changes=changes, sessions=sessions)
        diagnosis.seconds["session_changes"] = time.perf_counter() - t
    return diagnosis
