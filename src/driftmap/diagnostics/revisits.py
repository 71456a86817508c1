"""The revisit check: where the map sees a place again, do the frames of the two visits fit each other at all?

The double-wall detector, the attribution and the smearing score compare surfaces that fall into one voxel and
residuals within a gate (a separation up to about the largest voxel size; 10 cm residuals indoors). A pose error
larger than that -- a 30 cm or 30 deg step, a map broken by a bad correction -- puts the two copies of a wall into
different voxels and beyond every gate: each copy looks like a clean single surface, and the figures came out
*clean* (trial 10: 0 regions, 0 % doubled, verdict valid). This check looks with a much wider window. It registers
*revisit pairs*: a frame (the probe) onto an earlier frame at least ``revisit_min_path_m`` of travel before it and the
frames up to ``window_m`` of travel before that one (the target, at most ``max_window_frames``), with GICP coarse to
fine from a gate of ``coarse_gate_m`` (:func:`~driftmap.registration.pairwise.register_prepared`), and reports the
correction the probe needs at its sensor. A consistent map needs ~0 (the registration's noise). A registration counts
only with ``min_fitness`` of the probe's points on the target and a well-constrained translation
(``min_constraint``); one that fits worse than the poses as placed slid off a partial overlap and reports no
correction.

The pairs are chosen by overlap on a coarse voxel grid (``coarse_gate_m``), so that a frame placed 30 cm or 30 deg
off still overlaps its partner: in turn the pair furthest apart in travel (a loop's closing frames) and the one
overlapping most, each frame in at most :data:`PAIRS_PER_FRAME` pairs. A pair shows every pose error between its
two frames; the target is a short stretch, not all the earlier map, so a step among the first frames is not outvoted
by the frames after it (trial 11: on LiDAR, where every scan sees the whole room, fitting a later scan onto *all*
earlier ones found its own side of a step already there). Beside the pairs, up to ``max_probes`` *whole-map probes*
register the frames overlapping most what was seen ``revisit_min_path_m`` before them onto all those earlier frames
(trial 10's check, kept: many frames constrain a drift or a step that one short stretch does not, and they still
overlap after a 3 m step that leaves no pair overlapping). The disagreement is the ``min_probes``-th largest
correction of each kind, the larger of the two, so one registration that slid along a corridor does not decide it
alone; the pairs' corrections per metre of travel between their two frames give a drift rate
(:attr:`RevisitCheck.drift_percent_per_m`). Third, the trajectory's *jumps* (:func:`~driftmap.diagnostics.jumps.find_jumps`: consecutive frames
whose relative motion differs from their neighbours' by a quarter of the detectable error or more) have the frames after the
jump registered onto the frames before it, the poses as placed and the jump undone as two hypotheses (trial 12: a
block of frames moved and moved back escaped the pairs, which ran end-on-start, and the whole-map probes, which
fitted the unmoved majority; a 180 deg flip left no pair overlapping).

The figures are a verdict only when the disagreement stays within what the detector sees
(:attr:`RevisitCheckConfig.max_detectable_m`, :attr:`RevisitCheckConfig.max_detectable_deg`), and when the pairs fit
at all (:attr:`RevisitCheck.unfit`: a 3 m step, a 180 deg turn are beyond what the registration reaches from its
gate; among the pairs or among the whole-map probes). Either failing makes every headline figure 'cannot judge' (:func:`~driftmap.diagnostics.coverage.assess`).

Known limits (docs/diagnostics.md): a pose error that is no jump of the trajectory and moves fewer than ``min_probes``
pairs' worth of frames, or lies along a direction the revisiting frames do not constrain, is not measured.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.diagnostics.jumps import StepJump, find_jumps, undo_jump
from driftmap.diagnostics.revisit_config import FREE_OVER_LOCAL, HYPOTHESIS_WITHIN, MIN_PROBE_POINTS, RevisitCheckConfig
from driftmap.diagnostics.samples import PlacedCloud
from driftmap.registration.pairwise import PreparedCloud, downsample, nearest_distances, register_prepared
from driftmap.registration.tracking import translation_degeneracy
from driftmap.voxels import dense_ids, keys_on_bounding_grid, voxel_coords

logger = logging.getLogger(__name__)


PAIRS_PER_FRAME = 2
"""A frame is the probe (or the target frame) of at most this many pairs: the pairs spread over the log, yet a pose
error that moved only two revisiting frames still shows in more than one pair."""


STRETCH, MAP, STEP, FLOOR = "stretch", "map", "step", "floor"
"""The kinds of probe (:attr:`RevisitProbe.kind`, the ``target`` key of the JSON). :data:`FLOOR` probes
(:attr:`RevisitCheck.floor_probes`) register a pair's probe onto the frames just before it: what the registration
moves a frame that no drift moved, the registration's floor on this sensor and scene."""

MIN_SESSION_PAIRS = 2
"""A merged store's two sessions are judged against each other from this many counted frame pairs across them."""


MAX_OVERLAP_FRAMES = 2000
"""Pairs are chosen among at most this many frames (evenly spread over a longer log): the overlap table is square."""


@dataclass(frozen=True)
class RevisitProbe:
    """One revisiting frame (the probe) registered onto a stretch of earlier frames (its target)."""

    frame_id: int
    overlap: float
    fitness: float
    rmse_m: float
    constraint: float | None
    correction_m: float
    """How far the registration moves the probe's sensor origin (m)."""
    correction_deg: float
    counted: bool
    target_frame_id: int = -1
    """The last (latest) frame of the target."""
    target_first_frame_id: int = -1
    path_between_m: float = 0.0
    """Travel from the target frame to the probe (m)."""
    kind: str = "stretch"
    """:data:`STRETCH` (a revisit pair), :data:`MAP` (the target is every frame up to the target frame: the earlier
    map) or :data:`STEP` (the probe is at or just after a jump in the trajectory, the target the frames before it)."""
    cross_session: bool = False
    """A merged store's probe and target frame belong to different sessions: no travel lies between them
    (``path_between_m`` is NaN, None in JSON), and the pair counts for the map's consistency, not for a drift rate."""

    @property
    def whole_map(self) -> bool:
        return self.kind == MAP

    def to_json(self) -> dict:
        return {"frame_id": self.frame_id, "overlap": round(self.overlap, 4), "fitness": round(self.fitness, 4),
                "rmse_m": round(self.rmse_m, 5) if np.isfinite(self.rmse_m) else None,
                "constraint": None if self.constraint is None else round(self.constraint, 4),
                "correction_m": round(self.correction_m, 5), "correction_deg": round(self.correction_deg, 4),
                "counted": self.counted, "target_frame_id": self.target_frame_id,
                "target_first_frame_id": self.target_first_frame_id,
                "path_between_m": round(self.path_between_m, 4) if np.isfinite(self.path_between_m) else None,
                "target": self.kind, "cross_session": self.cross_session}


@dataclass(frozen=True)
class RevisitCheck:
    """The pairs and the check's verdict (:func:`check_revisits`)."""

    config: RevisitCheckConfig
    probes: list[RevisitProbe]
    n_candidates: int
    """Frame pairs at least ``revisit_min_path_m`` of travel apart that overlap enough."""
    jumps: tuple[StepJump, ...] = ()
    """The trajectory's jumps whose frames were registered onto the frames before them (:data:`STEP` probes)."""
    frame_sessions: dict[int, int] = field(default_factory=dict)
    """A merged store's session of each frame id (empty: one session); the reasons name them."""
    floor_probes: tuple[RevisitProbe, ...] = ()
    """Each counted pair's probe registered onto the frames just before it (:data:`FLOOR`): no drift lies between
    them, so what they move a frame is the registration's own floor (:attr:`measured_floor`)."""

    @property
    def measured_floor(self) -> tuple[float, float] | None:
        """The median correction (m, deg) of the counted :attr:`floor_probes` (None: fewer than two): how far the
        registration moves a frame on its own neighbours. Single frames of a rosette LiDAR (70 deg field of view,
        a pattern that differs from scan to scan) on exact poses move 0-18 cm there (hostile trial 17 B2), single
        spinning-LiDAR scans 0 cm, so a fixed floor cannot serve both."""
        counted = [p for p in self.floor_probes if p.counted]
        if len(counted) < 2:
            return None
        return (float(np.median([p.correction_m for p in counted])),
                float(np.median([p.correction_deg for p in counted])))

    @property
    def counted(self) -> list[RevisitProbe]:
        return [p for p in self.probes if p.counted]

    def _name(self, frame_id: int) -> str:
        session = self.frame_sessions.get(int(frame_id))
        return f"frame {frame_id}" if session is None else f"frame {frame_id} (session {session})"

    def _names(self, a: int, b: int) -> str:
        if not self.frame_sessions:
            return f"frames {a} and {b}"
        return f"{self._name(a)} and {self._name(b)}"

    def _drift_pairs(self) -> list[RevisitProbe] | None:
        """The counted pairs within one session (the travel between them is known); None: fewer than ``min_probes``."""
        pairs = [p for p in self._group(False) if p.counted and not p.cross_session]
        return pairs if len(pairs) >= self.config.min_probes else None

    def _group(self, whole_map: bool) -> list[RevisitProbe]:
        kind = MAP if whole_map else STRETCH
        return [p for p in self.probes if p.kind == kind]

    def _group_judged(self, whole_map: bool) -> bool:
        return sum(p.counted for p in self._group(whole_map)) >= self.config.min_probes

    @property
    def judged(self) -> bool:
        return self._group_judged(False) or self._group_judged(True)

    def deciding_group(self) -> list[RevisitProbe]:
        """The probes a verdict of "not judged" rests on: when :attr:`unfit`, the group (pairs, or whole-map probes)
        with enough registered and the fewest fitting; else the group with the most fitting. Counting every probe at
        once read "3 of 5 revisiting frames fit; 3 needed" beside NOT FIT (2 of 3 pairs, 1 of 2 whole-map)."""
        groups = [self._group(m) for m in (False, True)]
        if self.unfit:
            enough = [g for g in groups if len(g) >= self.config.min_probes]
            if enough:
                return min(enough, key=lambda g: sum(p.counted for p in g))
        return max(groups, key=lambda g: (sum(p.counted for p in g), len(g)))

    def group_disagreement(self, whole_map: bool, degrees: bool = False) -> float | None:
        """The ``min_probes``-th largest counted correction (m, or deg) of the pairs (``whole_map`` False) or of the
        whole-map probes (None: fewer counted)."""
        if not self._group_judged(whole_map):
            return None
        group = [p.correction_deg if degrees else p.correction_m for p in self._group(whole_map) if p.counted]
        return float(sorted(group, reverse=True)[self.config.min_probes - 1])

    def _jump_probes(self, jump: StepJump) -> list[RevisitProbe]:
        return [p for p in self.probes if p.kind == STEP and p.target_frame_id == jump.before_frame_id]

    def jump_correction(self, jump: StepJump, degrees: bool = False) -> float | None:
        """The correction the frames from ``jump`` on need onto the frames before it, at the sensor of the first of
        them (None: their registration does not count)."""
        values = [p.correction_deg if degrees else p.correction_m for p in self._jump_probes(jump) if p.counted]
        return float(max(values)) if values else None

    def steps_disagreement(self, degrees: bool = False) -> float | None:
        """The largest :meth:`jump_correction` (None: no jump checked, or none fitted)."""
        values = [v for v in (self.jump_correction(j, degrees) for j in self.jumps) if v is not None]
        return float(max(values)) if values else None

    @property
    def unfit_jumps(self) -> list[StepJump]:
        """Jumps larger than the log's own motion ever makes (:attr:`StepJump.implausible`) whose frames fit nothing
        before them: a 180 deg flip, a 5 m step."""
        return [j for j in self.jumps if j.implausible and self.jump_correction(j) is None]

    def session_disagreements(self) -> dict[tuple[int, int], tuple[float, float, int]]:
        """A merged store's counted pairs across each two sessions ``(a, b)``: ``(m, deg, n)``, the ``min(n,
        min_probes)``-th largest corrections of the ``n >= MIN_SESSION_PAIRS`` pairs. One session placed off the
        others shows in every pair across it, however few of all the pairs those are (trial 14: two of twelve pairs
        measured a third session 40 cm off, the third largest of all the pairs was 0.9 cm)."""
        groups: dict[tuple[int, int], list[RevisitProbe]] = {}
        for p in self.probes:
            if p.counted and p.cross_session and p.kind == STRETCH:
                a, b = self.frame_sessions.get(p.frame_id), self.frame_sessions.get(p.target_frame_id)
                if a is not None and b is not None and a != b:
                    groups.setdefault((min(a, b), max(a, b)), []).append(p)
        out = {}
        for key, group in groups.items():
            if len(group) >= MIN_SESSION_PAIRS:
                k = min(len(group), self.config.min_probes) - 1
                out[key] = (float(sorted((p.correction_m for p in group), reverse=True)[k]),
                            float(sorted((p.correction_deg for p in group), reverse=True)[k]), len(group))
        return out

    def _kth_largest(self, degrees: bool) -> float | None:
        """:meth:`group_disagreement` of the pairs and of the whole-map probes, :meth:`steps_disagreement` and, on a
        merged store, :meth:`session_disagreements`: the largest."""
        values = [v for v in (*(self.group_disagreement(m, degrees) for m in (False, True)),
                              self.steps_disagreement(degrees)) if v is not None]
        values += [v[1] if degrees else v[0] for v in self.session_disagreements().values()]
        return float(max(values)) if values else None

    @property
    def disagreement_m(self) -> float | None:
        """The ``min_probes``-th largest correction at a probe's sensor, of the pairs or of the whole-map probes
        (the larger; None: too few registrations)."""
        return self._kth_largest(False)

    @property
    def disagreement_deg(self) -> float | None:
        return self._kth_largest(True)

    @property
    def drift_percent_per_m(self) -> float | None:
        """Median over the counted pairs (not the whole-map probes, whose target spans all earlier travel) of
        correction / travel between the two frames (%; None: too few pairs); a merged store's pairs across sessions
        have no travel between them and do not count."""
        pairs = self._drift_pairs()
        if pairs is None:
            return None
        return float(100.0 * np.median([p.correction_m / max(p.path_between_m, 1e-9) for p in pairs]))

    @property
    def drift_deg_per_m(self) -> float | None:
        pairs = self._drift_pairs()
        if pairs is None:
            return None
        return float(np.median([p.correction_deg / max(p.path_between_m, 1e-9) for p in pairs]))

    def drift_floor(self, floor_m: float, floor_deg: float) -> tuple[float, float]:
        """The registration floor the pairs' corrections count beyond: the larger of the given one and
        :attr:`measured_floor`."""
        measured = self.measured_floor
        if measured is None:
            return floor_m, floor_deg
        return max(floor_m, measured[0]), max(floor_deg, measured[1])

    def drift_beyond_floor(self, floor_m: float, floor_deg: float) -> tuple[float, float] | None:
        """:attr:`drift_percent_per_m` and :attr:`drift_deg_per_m` of the pairs' corrections beyond a registration
        floor (each pair's correction less the floor, not below 0, over its travel; the floor is ``floor_m`` /
        ``floor_deg`` or, when larger, :attr:`measured_floor`): what of the pairs' disagreement drift must explain
        (hostile trial 17 B2: single 7-Scenes frames on exact poses register 2.5-4.2 cm / 1.3-1.6 deg apart at their
        sensors, 4-5 m of travel apart, which read as 0.91 %/m; single rosette scans 0-12 cm). None: too few
        pairs."""
        pairs = self._drift_pairs()
        if pairs is None:
            return None
        floor_m, floor_deg = self.drift_floor(floor_m, floor_deg)
        travel = np.array([max(p.path_between_m, 1e-9) for p in pairs])
        m = np.maximum(np.array([p.correction_m for p in pairs]) - floor_m, 0.0)
        deg = np.maximum(np.array([p.correction_deg for p in pairs]) - floor_deg, 0.0)
        return float(100.0 * np.median(m / travel)), float(np.median(deg / travel))

    @property
    def beyond_detector(self) -> bool:
        """The pairs disagree by more than the double-wall detector can see."""
        m, deg = self.disagreement_m, self.disagreement_deg
        return m is not None and deg is not None and (m > self.config.max_detectable_m or deg > self.config.max_detectable_deg)

    @property
    def unfit(self) -> bool:
        """Frames overlap (at least ``min_probes`` pairs registered) but too few of them fit: a pose error beyond
        what the registration reaches from ``coarse_gate_m`` (a 3 m step, a 180 deg turn) cannot be ruled out. Every
        consistent map in the tests fits 8 to 12 of its 12 pairs. Or a jump of the trajectory larger than the log's
        own motion ever makes fits nothing before it (:attr:`unfit_jumps`)."""
        return bool(self.unfit_jumps) or any(len(self._group(m)) >= self.config.min_probes and not self._group_judged(m)
                                             for m in (False, True))

    def reason(self) -> str | None:
        """Why the double-wall figures cannot judge this map (None when they can, as far as this check sees)."""
        cfg = self.config
        if self.unfit_jumps:
            j = max(self.unfit_jumps, key=lambda j: j.excess_m / cfg.max_detectable_m + j.excess_deg / cfg.max_detectable_deg)
            return (f"the trajectory jumps by {100 * j.excess_m:.0f} cm / {j.excess_deg:.1f} deg between "
                    f"{self._names(j.before_frame_id, j.frame_id)} (beyond what its neighbours move, and more than "
                    f"{cfg.implausible_factor:g}x the log's 90th-percentile motion between frames), and the frames from "
                    f"there on do not fit the frames before it (revisit check, GICP from a "
                    f"{100 * cfg.coarse_gate_m:.0f} cm gate): a pose error larger than the check and the double-wall "
                    f"detector measure cannot be ruled out")
        if self.unfit:
            group = self.deciding_group()
            return (f"only {sum(p.counted for p in group)} of {len(group)} revisiting frames fit the earlier frames they "
                    f"revisit (revisit check; {cfg.min_probes} needed, GICP from a {100 * cfg.coarse_gate_m:.0f} cm "
                    f"gate): a pose error larger than the check and the double-wall detector measure cannot be ruled "
                    f"out{self._measured_jump_note()}")
        if not self.beyond_detector:
            return None
        sessions = {k: v for k, v in self.session_disagreements().items()
                    if v[0] > cfg.max_detectable_m or v[1] > cfg.max_detectable_deg}
        if sessions:
            (a, b), (m, deg, n) = max(sessions.items(), key=lambda kv: kv[1][0] / cfg.max_detectable_m
                                      + kv[1][1] / cfg.max_detectable_deg)
            w = max((p for p in self.counted if p.cross_session and p.kind == STRETCH
                     and {self.frame_sessions.get(p.frame_id), self.frame_sessions.get(p.target_frame_id)} == {a, b}),
                    key=lambda p: p.correction_m / cfg.max_detectable_m + p.correction_deg / cfg.max_detectable_deg)
            return (f"sessions {a} and {b} disagree by {100 * m:.0f} cm / {deg:.1f} deg ({n} frame pairs across them, "
                    f"the largest {self._name(w.frame_id)} on {self._name(w.target_frame_id)}: "
                    f"{100 * w.correction_m:.0f} cm / {w.correction_deg:.1f} deg; revisit check): one of them is placed off the other, beyond the {100 * cfg.max_detectable_m:.0f} "
                    f"cm / {cfg.max_detectable_deg:g} deg the double-wall detector sees; the map is inconsistent by "
                    f"more than its figures show")
        worst = max(self.counted, key=lambda p: p.correction_m / cfg.max_detectable_m
                    + p.correction_deg / cfg.max_detectable_deg)
        between = "in another session" if worst.cross_session else f"{worst.path_between_m:.3g} m of travel earlier"
        return (f"revisiting frames disagree with the earlier map by {100 * self.disagreement_m:.0f} cm / "
                f"{self.disagreement_deg:.1f} deg ({self._name(worst.frame_id)} on {self._name(worst.target_frame_id)}, "
                f"{between}: {100 * worst.correction_m:.0f} cm / "
                f"{worst.correction_deg:.1f} deg; revisit check): beyond the {100 * cfg.max_detectable_m:.0f} cm / "
                f"{cfg.max_detectable_deg:g} deg the double-wall detector sees, the map is inconsistent by more than "
                f"its figures show")

    def _measured_jump_note(self) -> str:
        """``; the trajectory jumps ...`` naming the jump whose frames needed the largest correction onto the frames
        before it (beyond the registration's noise: a quarter of ``jump_min_share`` of the detectable error), or ''."""
        cfg = self.config
        floor = cfg.jump_min_share / 4
        measured = [(j, self.jump_correction(j), self.jump_correction(j, True)) for j in self.jumps]
        measured = [(j, m, d) for j, m, d in measured if m is not None and d is not None
                    and (m >= floor * cfg.max_detectable_m or d >= floor * cfg.max_detectable_deg)]
        if not measured:
            return ""
        j, m, d = max(measured, key=lambda x: x[1] / cfg.max_detectable_m + x[2] / cfg.max_detectable_deg)
        return (f"; the trajectory jumps between {self._names(j.before_frame_id, j.frame_id)}, and the "
                f"frames from {j.frame_id} on fit the frames before it only moved by {100 * m:.1f} cm / {d:.1f} deg: a pose error "
                f"there")

    def to_json(self) -> dict:
        return {"judged": self.judged, "beyond_detector": self.beyond_detector, "unfit": self.unfit,
                "disagreement_m": self.disagreement_m, "disagreement_deg": self.disagreement_deg,
                "max_detectable_m": self.config.max_detectable_m, "max_detectable_deg": self.config.max_detectable_deg,
                "drift_percent_per_m": self.drift_percent_per_m, "drift_deg_per_m": self.drift_deg_per_m,
                "pairs_disagreement_m": self.group_disagreement(False), "pairs_disagreement_deg": self.group_disagreement(False, True),
                "map_disagreement_m": self.group_disagreement(True), "map_disagreement_deg": self.group_disagreement(True, True),
                "steps_disagreement_m": self.steps_disagreement(), "steps_disagreement_deg": self.steps_disagreement(True),
                "jumps": [{**j.to_json(), "correction_m": self.jump_correction(j),
                           "correction_deg": self.jump_correction(j, True)} for j in self.jumps],
                "n_candidates": self.n_candidates, "n_registered": len(self.probes), "n_counted": len(self.counted),
                "sessions": [{"session_a": a, "session_b": b, "disagreement_m": m, "disagreement_deg": deg,
                              "n_pairs": n} for (a, b), (m, deg, n) in sorted(self.session_disagreements().items())],
                "probes": [p.to_json() for p in self.probes],
                "floor_probes": [p.to_json() for p in self.floor_probes],
                "measured_floor_m": None if self.measured_floor is None else self.measured_floor[0],
                "measured_floor_deg": None if self.measured_floor is None else self.measured_floor[1]}


def _overlap_table(placed: PlacedCloud, rows: NDArray[np.int64], cfg: RevisitCheckConfig) -> NDArray[np.float64]:
    """``O[i, j]``: the share of frame ``rows[i]``'s points in coarse voxels that frame ``rows[j]`` occupies."""
    keep = np.full(len(placed.path_length_m), -1, dtype=np.int64)
    keep[rows] = np.arange(len(rows))
    point_rows = keep[placed.frame_index]
    mine = point_rows >= 0
    keys, _ = keys_on_bounding_grid(voxel_coords(placed.points_world[mine], cfg.coarse_gate_m), "revisit check voxels")
    voxel, unique = dense_ids(keys)
    counts = scipy.sparse.csr_matrix((np.ones(len(voxel)), (point_rows[mine], voxel)), shape=(len(rows), len(unique)))
    counts.sum_duplicates()
    occupied = counts.copy()
    occupied.data[:] = 1.0
    shared = (counts @ occupied.T).toarray()
    n_points = np.asarray(counts.sum(axis=1)).ravel()
    return shared / np.maximum(n_points, 1.0)[:, None]


def _choose_pairs(a: NDArray[np.int64], b: NDArray[np.int64], overlap: NDArray[np.float64],
                  travel: NDArray[np.float64], cfg: RevisitCheckConfig) -> list[int]:
    """Indices of up to ``max_probes`` candidate pairs ``(a, b)``: in turn the next admissible pair furthest apart in
    travel and the next overlapping most; a pair is admissible while its target frame and its probe are each in fewer
    than :data:`PAIRS_PER_FRAME` chosen pairs."""
    chosen: dict[int, None] = {}
    uses: dict[tuple[str, int], int] = {}
    queues = [iter(np.lexsort((-b, -travel)).tolist()), iter(np.lexsort((-b, -overlap)).tolist())]
    while len(chosen) < cfg.max_probes and queues:
        for queue in list(queues):
            for k in queue:
                ends = (("target", int(a[k])), ("probe", int(b[k])))
                if k not in chosen and all(uses.get(e, 0) < PAIRS_PER_FRAME for e in ends):
                    chosen[k] = None
                    for e in ends:
                        uses[e] = uses.get(e, 0) + 1
                    break
            else:
                queues.remove(queue)
            if len(chosen) >= cfg.max_probes:
                break
    return list(chosen)


def _map_pairs(placed: PlacedCloud, cfg: RevisitCheckConfig) -> list[tuple[int, int, float]]:
    """``[(last target row, probe row, overlap)]``: up to ``max_probes`` frames with ``min_overlap`` of their points in
    coarse voxels first seen at least ``revisit_min_path_m`` of travel before them, those overlapping most, each paired
    with all the frames before that travel (the whole-map probes: they see a drift or a step that the short stretches
    of the pairs do not constrain, and a 3 m step or a 180 deg turn leaves no frame pair overlapping while the
    stepped frames still overlap the room)."""
    rows, path = placed.frame_index, placed.path_length_m
    keys, _ = keys_on_bounding_grid(voxel_coords(placed.points_world, cfg.coarse_gate_m), "revisit check voxels")
    inverse, _ = dense_ids(keys)
    first_path = np.full(int(inverse.max()) + 1, np.inf)
    np.minimum.at(first_path, inverse, path[rows])
    seen_before = path[rows] - first_path[inverse] >= cfg.revisit_min_path_m
    n_points = np.bincount(rows, minlength=len(path))
    overlap = np.bincount(rows, weights=seen_before, minlength=len(path)) / np.maximum(n_points, 1)
    good = np.flatnonzero((overlap >= cfg.min_overlap) & (n_points >= MIN_PROBE_POINTS))
    best = good[np.lexsort((-good, -overlap[good]))][: cfg.max_probes]
    ends = np.searchsorted(path, path[best] - cfg.revisit_min_path_m, "right") - 1
    return [(int(e), int(r), float(overlap[r])) for e, r in sorted(zip(ends, best), key=lambda x: x[1]) if e >= 0]


def _register(placed: PlacedCloud, target_row: int, row: int, overlap: float, cfg: RevisitCheckConfig,
              kind: str = STRETCH, last_row: int | None = None,
              start_guess: NDArray[np.float64] | None = None, cross_session: bool = False) -> RevisitProbe:
    """Register frame row ``row`` (with the rows up to ``last_row``) onto the frames up to ``window_m`` of travel
    before ``target_row`` (at most ``max_window_frames``; :data:`MAP`: all frames up to it), cropped to the probe's box
    plus the coarse gate. With ``start_guess`` the poses as placed and the guess are refined from a 15 cm gate, and the
    one with more of the probe within :data:`HYPOTHESIS_WITHIN` finest voxels is kept (the free registration only when
    it does not count): a free registration from an 80 cm gate slides a 30 cm step along the room to 1.14 m, which
    fits 0.678 of the probe against 0.665 at the truth."""
    offsets, path, ids = placed.samples.offsets, placed.path_length_m, placed.frame_ids
    first = 0 if kind == MAP else max(int(np.searchsorted(path, path[target_row] - cfg.window_m, "left")),
                                    target_row + 1 - cfg.max_window_frames)
    source = placed.points_world[offsets[row]:offsets[(row if last_row is None else last_row) + 1]]
    target = placed.points_world[offsets[first]:offsets[target_row + 1]]
    lo, hi = source.min(axis=0) - cfg.coarse_gate_m, source.max(axis=0) + cfg.coarse_gate_m
    if start_guess is not None:  # and where the guess puts the probe
        guessed = source @ start_guess[:3, :3].T + start_guess[:3, 3]
        lo, hi = np.minimum(lo, guessed.min(axis=0) - cfg.coarse_gate_m), np.maximum(hi, guessed.max(axis=0) + cfg.coarse_gate_m)
    v = cfg.registration_voxel_m
    target = downsample(target[np.all((target >= lo) & (target <= hi), axis=1)], v)
    pair = (int(ids[target_row]), int(ids[first]), math.nan if cross_session else float(path[row] - path[target_row]))
    if len(target) < MIN_PROBE_POINTS:
        return RevisitProbe(int(ids[row]), overlap, 0.0, float("nan"), None, 0.0, 0.0, False, *pair, kind, cross_session)
    tgt, src = PreparedCloud(target, 1), PreparedCloud(downsample(source, v), 1)

    def inliers(T: NDArray[np.float64], within: float = 1.5) -> float:
        return float(np.mean(nearest_distances(tgt, src, T, v) <= within * v))

    free = ((4 * v, cfg.coarse_gate_m), (2 * v, max(6 * v, cfg.coarse_gate_m / 4)), (v, 2.5 * v))
    local = ((2 * v, 3 * v), (v, 2.5 * v))

    def refine(T: NDArray[np.float64], levels: tuple) -> tuple[NDArray[np.float64], Any]:
        for level, gate in levels:
            result = register_prepared(tgt, src, T, voxel_size_m=level, max_correspondence_m=gate, num_threads=1)
            T = result.T_target_source
        return T, result

    def counts(fitness: float, constraint: float | None) -> bool:
        return fitness >= cfg.min_fitness and constraint is not None and constraint >= cfg.min_constraint

    def constraint_of(result: Any) -> float | None:
        return translation_degeneracy(result.information_6x6[:3, :3])

    def free_registration() -> tuple[NDArray[np.float64], Any, float]:
        T, result = refine(np.eye(4), free)
        fitness = float(result.fitness)
        unmoved = inliers(np.eye(4))
        # the poses as placed fit as well or better, by the same measure (the registration's own fitness counts the
        # points within its last gate, 2.5 voxels, and favoured it: trial 16 B4, a 7-Scenes frame slid 89 cm along
        # a wall with fitness 0.64): the registration slid off a partial overlap
        if unmoved >= inliers(T):
            T, fitness = np.eye(4), unmoved
        return T, result, fitness

    if start_guess is None:
        T, result, fitness = free_registration()
    else:  # two hypotheses refined where they start, the better kept; the free registration only if neither counts
        starts = [np.eye(4)]
        if geometry.translation_distance_m(np.eye(4), start_guess) > 1e-6 or geometry.rotation_angle_deg(
                np.eye(4), start_guess) > 1e-6:
            starts.append(start_guess)
        origin = placed.origins_world[row]

        def stayed(start: NDArray[np.float64], T: NDArray[np.float64]) -> bool:
            """A local refinement that carried the probe's sensor beyond its first gate from where it started slid
            along a wall (trial 15: frame 1 of a room on frame 0 alone, both starts the poses as placed to 2e-16 m,
            one ended 51 cm away with more tight inliers on a weakly constrained view)."""
            return float(np.linalg.norm((T[:3, :3] @ origin + T[:3, 3]) - (start[:3, :3] @ origin + start[:3, 3]))) \
                <= local[0][1]

        hypotheses = [h for h in ((refine(start, local), start) for start in starts) if stayed(h[1], h[0][0])]
        result = None
        if hypotheses:
            (T, result), _ = max(hypotheses, key=lambda h: inliers(h[0][0], HYPOTHESIS_WITHIN))
            fitness = float(result.fitness)
        if result is None or not counts(fitness, constraint_of(result)):
            # as above: a free registration that fits less than the poses as placed slid
            local_best = None if result is None else (T, result, fitness)
            T, result, fitness = free_registration()
            if local_best is not None and inliers(T, HYPOTHESIS_WITHIN) < inliers(local_best[0], HYPOTHESIS_WITHIN) + FREE_OVER_LOCAL:
                # ... and one that does not fit clearly better than a hypothesis of the jump refined where it
                # started slid too (trial 16 B4: a 7-Scenes frame of exact poses 89 cm along the cupboards, 0.64
                # of its points within 2.5 voxels against 0.60 as placed): the probe keeps the hypothesis (uncounted)
                T, result, fitness = local_best
    origin = placed.origins_world[row]
    moved_m = float(np.linalg.norm(T[:3, :3] @ origin + T[:3, 3] - origin))
    turned_deg = float(geometry.rotation_angle_deg(np.eye(4), T))
    constraint = constraint_of(result)
    counted = counts(fitness, constraint)
    probe = RevisitProbe(int(ids[row]), overlap, fitness, float(result.rmse_m), constraint, moved_m, turned_deg,
                         bool(counted), *pair, kind, cross_session)
    logger.debug("revisit pair %s", probe)
    return probe


def _floor_probes(placed: PlacedCloud, rows: NDArray[np.int64], pairs: list[tuple[int, RevisitProbe]],
                  cfg: RevisitCheckConfig, sessions: NDArray[np.int64] | None) -> tuple[RevisitProbe, ...]:
    """Each counted pair's probe (row, once) registered as a pair is onto the frames just before it, within its
    session and less than ``revisit_min_path_m`` of travel away (:data:`FLOOR`)."""
    out = []
    path = placed.path_length_m
    for row in sorted({row for row, p in pairs if p.counted and not p.cross_session}):
        k = int(np.searchsorted(rows, row))
        if k == 0 or (sessions is not None and sessions[rows[k - 1]] != sessions[row]) \
                or path[row] - path[rows[k - 1]] >= cfg.revisit_min_path_m:
            continue
        out.append(_register(placed, int(rows[k - 1]), row, 1.0, cfg, FLOOR))
    return tuple(out)


def check_revisits(placed: PlacedCloud, config: RevisitCheckConfig | None = None,
                   sessions: NDArray[np.int64] | None = None) -> RevisitCheck:
    """Register up to ``max_probes`` revisit pairs of ``placed`` (see the module docstring). ``sessions``: a merged
    store's session of each frame row (pairs across sessions are revisits whatever the travel, with no travel between
    them; a session's start is no jump of the trajectory)."""
    cfg = config or RevisitCheckConfig()
    n_rows = len(placed.path_length_m)
    rows = np.flatnonzero(np.bincount(placed.frame_index, minlength=n_rows) >= MIN_PROBE_POINTS)
    names = {} if sessions is None else {int(f): int(k) for f, k in zip(placed.frame_ids, sessions)}
    if not cfg.enabled or len(rows) < 2:
        return RevisitCheck(cfg, [], 0, frame_sessions=names)
    all_rows = rows
    if len(rows) > MAX_OVERLAP_FRAMES:
        rows = rows[np.linspace(0, len(rows) - 1, MAX_OVERLAP_FRAMES).round().astype(np.int64)]
    table = _overlap_table(placed, rows, cfg)
    j, i = np.nonzero(np.triu(table.T >= cfg.min_overlap, k=1))  # target rows[j] before probe rows[i]
    a, b, overlap = rows[j], rows[i], table[i, j]
    travel = placed.path_length_m[b] - placed.path_length_m[a]
    cross = np.zeros(len(a), dtype=bool) if sessions is None else sessions[a] != sessions[b]
    far = (travel >= cfg.revisit_min_path_m) | cross
    a, b, overlap, travel, cross = a[far], b[far], overlap[far], travel[far], cross[far]
    chosen = sorted(_choose_pairs(a, b, overlap, travel, cfg), key=lambda k: (int(b[k]), int(a[k])))
    probes = [_register(placed, int(a[k]), int(b[k]), float(overlap[k]), cfg, cross_session=bool(cross[k]))
              for k in chosen]
    probes += [_register(placed, end, row, ov, cfg, MAP,
                         cross_session=sessions is not None and bool(sessions[end] != sessions[row]))
               for end, row, ov in _map_pairs(placed, cfg)]
    jumps = find_jumps(placed, all_rows, cfg, sessions)
    starts = [k for k, _ in jumps]
    for i, k in enumerate(starts):
        stop = min([k + cfg.step_probes, len(all_rows), *starts[i + 1:]])
        path = placed.path_length_m[all_rows[k:stop]]
        stop = k + max(1, int(np.sum(path - path[0] <= cfg.window_m / 2)))  # fast motion: fewer frames overlap
        before, first, last = int(all_rows[k - 1]), int(all_rows[k]), int(all_rows[stop - 1])
        overlap_first = float(_overlap_table(placed, np.array([before, first]), cfg)[1, 0])
        probes.append(_register(placed, before, first, overlap_first, cfg, STEP, last, undo_jump(placed, all_rows, k)))
    check = RevisitCheck(cfg, probes, int(far.sum()), tuple(j for _, j in jumps), names,
                         _floor_probes(placed, all_rows, [(int(b[k]), p) for k, p in zip(chosen, probes)], cfg, sessions))
    if check.reason():
        logger.warning("revisit check: %s", check.reason())
    return check
