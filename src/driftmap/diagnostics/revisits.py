"""The revisit check: where the map sees a place again, does the later frame fit the earlier map at all?

The double-wall detector, the attribution and the smearing score compare surfaces that fall into one voxel and
residuals within a gate (a separation up to about the largest voxel size; 10 cm residuals indoors). A pose error
larger than that -- a 30 cm or 30 deg step, a map broken by a bad correction -- puts the two copies of a wall into
different voxels and beyond every gate: each copy looks like a clean single surface, and the figures came out
*clean* (trial 10: 0 regions, 0 % doubled, verdict valid). This check looks with a much wider window: it registers
frames that revisit a place (seen again after ``revisit_min_path_m`` of travel) onto the map of the frames before
them (GICP, coarse to fine from a gate of ``coarse_gate_m``; :func:`~driftmap.registration.pairwise.register_prepared`)
and reports the correction each needs at its sensor. A consistent map needs ~0 (the registration's noise); the
figures are a verdict only when the corrections stay within what the detector can see
(:attr:`RevisitCheckConfig.max_detectable_m`, :attr:`RevisitCheckConfig.max_detectable_deg`).

The probes are chosen by overlap measured on a coarse voxel grid (``coarse_gate_m``), so a frame placed
30 cm or 30 deg off its true place still counts as a revisit: half those that overlap most, half those revisiting
what was seen longest ago (a loop's closing frames). A registration counts only with ``min_fitness`` of its points
on the earlier map and a well-constrained translation (``min_constraint``). The reported disagreement is the
``min_probes``-th largest correction, so one registration that slid along a corridor does not decide it alone;
probes that overlap the earlier map but too few of which fit it (:attr:`RevisitCheck.unfit`: a 3 m step, a 180 deg
turn) are a reason to judge nothing either.

Known limits (docs/diagnostics.md): a probe is compared with *all* frames before its revisit path, so a step among
the first few frames or in the last two, and on LiDAR steps that the earlier map already holds, escape it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import ConfigDict, Field

from driftmap import geometry
from driftmap.config import SettingsModel
from driftmap.diagnostics.samples import PlacedCloud
from driftmap.registration.pairwise import PreparedCloud, downsample, register_prepared
from driftmap.registration.tracking import translation_degeneracy
from driftmap.voxels import dense_ids, keys_on_bounding_grid, voxel_coords

logger = logging.getLogger(__name__)

MIN_PROBE_POINTS = 50
"""A frame with fewer diagnostic samples is not registered (GICP needs neighbourhoods to fit planes in)."""


class RevisitCheckConfig(SettingsModel):
    """Which revisits are registered onto the earlier map and when their corrections leave the detector's range."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    enabled: bool = Field(True, description="register revisiting frames onto the earlier map (the check of pose errors beyond the double-wall detector's range)")
    revisit_min_path_m: float = Field(1.0, gt=0.0, description="the earlier map holds the frames at least this much travel before the probe (m)")
    registration_voxel_m: float = Field(0.05, gt=0.0, description="finest GICP voxel (m); the coarse levels are 2x and 4x")
    coarse_gate_m: float = Field(0.8, gt=0.0, description="correspondence gate of the coarsest level and the overlap grid (m): pose errors up to about this are measured")
    max_probes: int = Field(12, ge=1, le=1000, description="frames registered at most (half those overlapping the earlier map most, half those revisiting what was seen longest ago)")
    min_overlap: float = Field(0.5, gt=0.0, le=1.0, description="a probe has at least this share of its points in coarse voxels the earlier map occupies")
    min_fitness: float = Field(0.6, gt=0.0, le=1.0, description="a registration counts with at least this share of the probe's points on the earlier map")
    min_constraint: float = Field(0.03, gt=0.0, le=1.0, description="... and sqrt(lambda_min / lambda_max) of its translational information at least this (no slide along a corridor)")
    min_probes: int = Field(3, ge=1, description="registrations the check needs; its disagreement is the min_probes-th largest correction")
    max_detectable_m: float = Field(0.2, gt=0.0, description="the largest separation the double-wall detector reports (m): beyond it the figures cannot judge the map")
    max_detectable_deg: float = Field(10.0, gt=0.0, description="the largest rotation the detector's normal grouping tolerates (deg)")


@dataclass(frozen=True)
class RevisitProbe:
    """One revisiting frame registered onto the earlier map."""

    frame_id: int
    overlap: float
    fitness: float
    rmse_m: float
    constraint: float | None
    correction_m: float
    """How far the registration moves the frame's sensor origin (m)."""
    correction_deg: float
    counted: bool

    def to_json(self) -> dict:
        return {"frame_id": self.frame_id, "overlap": round(self.overlap, 4), "fitness": round(self.fitness, 4),
                "rmse_m": round(self.rmse_m, 5) if np.isfinite(self.rmse_m) else None,
                "constraint": None if self.constraint is None else round(self.constraint, 4),
                "correction_m": round(self.correction_m, 5), "correction_deg": round(self.correction_deg, 4),
                "counted": self.counted}


@dataclass(frozen=True)
class RevisitCheck:
    """The probes and the check's verdict (:func:`check_revisits`)."""

    config: RevisitCheckConfig
    probes: list[RevisitProbe]
    n_candidates: int
    """Frames with an earlier map (after ``revisit_min_path_m`` of travel) overlapping them enough."""

    @property
    def counted(self) -> list[RevisitProbe]:
        return [p for p in self.probes if p.counted]

    @property
    def judged(self) -> bool:
        return len(self.counted) >= self.config.min_probes

    def _kth_largest(self, values: list[float]) -> float | None:
        if not self.judged:
            return None
        return float(sorted(values, reverse=True)[self.config.min_probes - 1])

    @property
    def disagreement_m(self) -> float | None:
        """The ``min_probes``-th largest correction at a probe's sensor (None: too few registrations)."""
        return self._kth_largest([p.correction_m for p in self.counted])

    @property
    def disagreement_deg(self) -> float | None:
        return self._kth_largest([p.correction_deg for p in self.counted])

    @property
    def beyond_detector(self) -> bool:
        """The revisits disagree by more than the double-wall detector can see."""
        m, deg = self.disagreement_m, self.disagreement_deg
        return m is not None and deg is not None and (m > self.config.max_detectable_m or deg > self.config.max_detectable_deg)

    @property
    def unfit(self) -> bool:
        """Frames overlap the earlier map (at least ``min_probes`` registered) but too few of them fit it: a pose
        error beyond what the registration reaches from ``coarse_gate_m`` (a 3 m step, a 180 deg turn) cannot be
        ruled out. Every consistent map in the tests fits 8 to 12 of its 12 probes."""
        return len(self.probes) >= self.config.min_probes and not self.judged

    def reason(self) -> str | None:
        """Why the double-wall figures cannot judge this map (None when they can, as far as this check sees)."""
        if self.unfit:
            return (f"only {len(self.counted)} of {len(self.probes)} revisiting frames fit the earlier map (revisit "
                    f"check; {self.config.min_probes} needed, GICP from a {100 * self.config.coarse_gate_m:.0f} cm "
                    f"gate): a pose error larger than the check and the double-wall detector measure cannot be "
                    f"ruled out")
        if not self.beyond_detector:
            return None
        worst = max(self.counted, key=lambda p: p.correction_m / self.config.max_detectable_m
                    + p.correction_deg / self.config.max_detectable_deg)
        return (f"revisiting frames disagree with the earlier map by {100 * self.disagreement_m:.0f} cm / "
                f"{self.disagreement_deg:.1f} deg (frame {worst.frame_id}: {100 * worst.correction_m:.0f} cm / "
                f"{worst.correction_deg:.1f} deg; revisit check): beyond the "
                f"{100 * self.config.max_detectable_m:.0f} cm / {self.config.max_detectable_deg:g} deg the "
                f"double-wall detector sees, the map is inconsistent by more than its figures show")

    def to_json(self) -> dict:
        return {"judged": self.judged, "beyond_detector": self.beyond_detector, "unfit": self.unfit,
                "disagreement_m": self.disagreement_m, "disagreement_deg": self.disagreement_deg,
                "max_detectable_m": self.config.max_detectable_m, "max_detectable_deg": self.config.max_detectable_deg,
                "n_candidates": self.n_candidates, "n_registered": len(self.probes), "n_counted": len(self.counted),
                "probes": [p.to_json() for p in self.probes]}


def _candidates(placed: PlacedCloud, cfg: RevisitCheckConfig) -> tuple[list[tuple[int, float]], int]:
    """``([(frame row, overlap)], n)``: the rows to register and how many rows overlapped their earlier map by
    ``min_overlap`` at all. A point overlaps when its coarse voxel was first seen at least ``revisit_min_path_m`` of
    travel before its frame (one pass over all points). Half the probes are the rows that overlap most, half those
    whose overlapping points were first seen longest ago (a loop's closing frames: on a long loop the frames that
    overlap most are the ones just past ``revisit_min_path_m``, which see none of the loop's drift)."""
    rows, path = placed.frame_index, placed.path_length_m
    if len(rows) == 0:
        return [], 0
    keys, _ = keys_on_bounding_grid(voxel_coords(placed.points_world, cfg.coarse_gate_m), "revisit check voxels")
    inverse, _ = dense_ids(keys)
    first_path = np.full(int(inverse.max()) + 1, np.inf)
    np.minimum.at(first_path, inverse, path[rows])
    travelled = path[rows] - first_path[inverse]
    seen_before = travelled >= cfg.revisit_min_path_m
    n_points = np.bincount(rows, minlength=len(path))
    n_before = np.bincount(rows, weights=seen_before, minlength=len(path))
    overlap = n_before / np.maximum(n_points, 1)
    mean_travel = np.bincount(rows, weights=np.where(seen_before, travelled, 0.0), minlength=len(path)) / np.maximum(n_before, 1)
    good = np.flatnonzero((overlap >= cfg.min_overlap) & (n_points >= MIN_PROBE_POINTS))
    by_overlap = good[np.lexsort((-good, -overlap[good]))]
    by_travel = good[np.lexsort((-good, -mean_travel[good]))]
    chosen: dict[int, None] = {}
    for a, b in zip(by_travel, by_overlap):
        for r in (int(a), int(b)):
            if len(chosen) < cfg.max_probes:
                chosen.setdefault(r, None)
    return [(r, float(overlap[r])) for r in chosen], int(good.size)


def _probe(placed: PlacedCloud, row: int, overlap: float, cfg: RevisitCheckConfig) -> RevisitProbe:
    """Register frame row ``row`` onto the frames at least ``revisit_min_path_m`` of travel before it (a prefix
    of the rows: the path length grows with the row), cropped to the frame's box plus the coarse gate."""
    offsets = placed.samples.offsets
    earlier = int(np.searchsorted(placed.path_length_m, placed.path_length_m[row] - cfg.revisit_min_path_m, "right"))
    source = placed.points_world[offsets[row]:offsets[row + 1]]
    target = placed.points_world[: offsets[earlier]]
    lo, hi = source.min(axis=0) - cfg.coarse_gate_m, source.max(axis=0) + cfg.coarse_gate_m
    v = cfg.registration_voxel_m
    target = downsample(target[np.all((target >= lo) & (target <= hi), axis=1)], v)
    tgt, src = PreparedCloud(target, 1), PreparedCloud(downsample(source, v), 1)
    T = np.eye(4)
    for level, gate in ((4 * v, cfg.coarse_gate_m), (2 * v, max(6 * v, cfg.coarse_gate_m / 4)), (v, 2.5 * v)):
        result = register_prepared(tgt, src, T, voxel_size_m=level, max_correspondence_m=gate, num_threads=1)
        T = result.T_target_source
    origin = placed.origins_world[row]
    moved_m = float(np.linalg.norm(T[:3, :3] @ origin + T[:3, 3] - origin))
    turned_deg = float(geometry.rotation_angle_deg(np.eye(4), T))
    constraint = translation_degeneracy(result.information_6x6[:3, :3])
    counted = (result.fitness >= cfg.min_fitness and constraint is not None and constraint >= cfg.min_constraint)
    probe = RevisitProbe(int(placed.frame_ids[row]), overlap, float(result.fitness), float(result.rmse_m), constraint,
                         moved_m, turned_deg, bool(counted))
    logger.debug("revisit probe %s", probe)
    return probe


def check_revisits(placed: PlacedCloud, config: RevisitCheckConfig | None = None) -> RevisitCheck:
    """Register up to ``max_probes`` revisiting frames of ``placed`` onto the map of the frames before them (see the
    module docstring)."""
    cfg = config or RevisitCheckConfig()
    if not cfg.enabled:
        return RevisitCheck(cfg, [], 0)
    chosen, n = _candidates(placed, cfg)
    probes = [_probe(placed, row, overlap, cfg) for row, overlap in sorted(chosen)]
    check = RevisitCheck(cfg, probes, n)
    if check.reason():
        logger.warning("revisit check: %s", check.reason())
    return check
