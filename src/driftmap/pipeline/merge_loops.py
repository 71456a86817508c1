"""Loops between sessions for ``driftmap merge``: candidates from the place descriptors only (no shared frame or
start pose is assumed), verified as ``build`` verifies its own, then a consensus check per session pair, and which
sessions that connects to session 0.

* **Candidates.** Every keyframe of the newer session ``j`` is compared with every keyframe of the older session
  ``i``: on depth cameras by the shape descriptor (:func:`driftmap.registration.loops.shape_descriptor`, the
  ``session_descriptor_candidates`` best per keyframe within the L1 distance gate ``session_descriptor_max_distance``,
  looser than ``build``'s: between sessions the descriptor is the only way to a candidate, and real depth clouds of
  one place seen on two passes are farther apart than the synthetic room's; the pair is then aligned globally by
  FPFH + RANSAC inside :func:`~driftmap.registration.loops.verify`), on LiDAR by the Scan Context (ring-key
  pre-selection, the full distance gate ``scan_context_max_distance`` and the yaw of the best column shift as the
  initial guess), the ``descriptor_candidates`` best per keyframe, as in ``build``.
* **Verification.** :func:`~driftmap.registration.loops.verify` with the same gates (convergence, fitness, RMSE).
  Its agreement-with-odometry gate has no meaning between sessions (no odometry links them): it is opened
  (``path_length_m = inf``), and the consensus check below takes its place.
* **Consensus.** Each verified loop ``a <-> b`` says where session ``j``'s world lies in session ``i``'s:
  ``T_i_j = T_wi_a @ T_a_b @ inv(T_wj_b)``. Two loops agree when their ``T_i_j`` place both loops' ``b`` keyframes
  within ``max_correction_m`` plus ``descriptor_max_drift_fraction`` of the path (in both sessions) between the two
  loops, and turn them alike within ``max_correction_deg``: what the two sessions' residual drift allows. The largest
  set of loops agreeing with one of them is kept; the others are refused ("inconsistent"). A pair of sessions is
  connected by at least :data:`MIN_CONSISTENT_LOOPS` agreeing loops: a single loop has nothing to be checked against.
* **Free space.** Agreeing loops can still agree on a wrong placement: sessions of one place agree with each other
  whatever they are registered to, so a session of another room, registered with fitness 0.5 onto a room whose
  other sessions are alike, found three "independent" confirmations (hostile trial 14 F4). Each agreeing loop's two
  keyframe clouds are therefore checked against each other's free space
  (:func:`~driftmap.registration.visibility.free_space_conflict`, both ways, margin ``2 * registration_voxel_m`` or
  5 % of the range): pooled over the loops, the larger of the two shares of points lying where the other keyframe's
  sensor saw through (of those it saw through or onto) must stay within :data:`MAX_FREE_SPACE_CONFLICT`. A refused set
  does not end the pair: the next largest agreeing set without its loops is tried (a symmetric room turned by half a
  turn is the case: the true set is smaller).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.registration.loops import CandidateKind, Keyframe, LoopCandidate, LoopClosureConfig, verify
from driftmap.registration.place import scan_context_distance, yaw_guess
from driftmap.registration.visibility import FreeSpaceConflict, free_space_conflict

logger = logging.getLogger(__name__)

MIN_CONSISTENT_LOOPS = 2
"""A pair of sessions is connected by at least this many verified loops that agree on where one lies in the other."""

MAX_FREE_SPACE_CONFLICT = 0.06
"""The agreeing loops' keyframe clouds may lie in each other's seen-through free space by at most this share of their
judged points (pooled over the loops, the worse direction); above it the pair is not connected (module docstring)."""


@dataclass
class PairLoops:
    """The loops tried between two sessions (``session_a`` older, ``session_b`` newer)."""

    session_a: int
    session_b: int
    candidates: int = 0
    """pairs of keyframes whose place descriptors matched (each was verified)"""
    verified: list[LoopCandidate] = field(default_factory=list)
    """candidates that passed the registration gates"""
    consistent: list[LoopCandidate] = field(default_factory=list)
    """verified loops in the largest agreeing set: the graph's loop edges"""
    T_a_b: NDArray[np.float64] | None = None
    """where session b's world lies in session a's (``T_worlda_worldb``) by the consensus' best loop; None: not
    connected"""
    records: list[dict] = field(default_factory=list)
    """one record per candidate (frame ids, kind, verdict, reason, fitness, RMSE)"""
    free_space_conflict: float | None = None
    """pooled over the agreeing loops, the larger share of one keyframe cloud's points lying in the free space the
    other's sensor saw through: of the set taken, else of the largest set refused (None: not measured, fewer than
    :data:`MIN_CONSISTENT_LOOPS` agreed)"""
    refused_shares: list[float] = field(default_factory=list)
    """the free-space conflict of each agreeing set refused, largest set first"""
    conflicting: list[LoopCandidate] = field(default_factory=list)
    """agreeing loops refused together because their placement conflicts with the free space (a smaller agreeing
    set without them may still connect the pair)"""
    graph_rejected: list[LoopCandidate] = field(default_factory=list)
    """agreeing loops the merge's pose graph rejected where fewer than :data:`MIN_CONSISTENT_LOOPS` would have been
    left (:func:`drop_graph_rejected`): the pair is then not connected"""

    @property
    def connected(self) -> bool:
        return len(self.consistent) >= MIN_CONSISTENT_LOOPS

    def why_not_connected(self) -> str:
        if self.connected:
            return ""
        if self.graph_rejected:
            n = len(self.consistent) + len(self.graph_rejected)
            why = (f"{n} loops agree on where session {self.session_b} lies in session {self.session_a}, but the "
                   f"pose graph rejected {len(self.graph_rejected)} of them (they contradict the sessions' own "
                   f"trajectories): fewer than {MIN_CONSISTENT_LOOPS} left, and one loop cannot be checked")
            return why + (f"; {self._free_space_reason('other ')}" if self.conflicting else "")
        if self.conflicting and not self.consistent:
            return self._free_space_reason("")
        if self.candidates == 0:
            return "no keyframe pair had matching place descriptors"
        if not self.verified:
            return f"none of the {self.candidates} candidate loops passed verification"
        if len(self.consistent) < MIN_CONSISTENT_LOOPS:
            return (f"{len(self.verified)} of {self.candidates} candidates verified, but only {len(self.consistent)} "
                    f"agree on the alignment (at least {MIN_CONSISTENT_LOOPS} needed: one loop cannot be checked)")
        return ""

    def _free_space_reason(self, other: str) -> str:
        lo, hi = (round(100 * min(self.refused_shares)), round(100 * max(self.refused_shares)))
        share = f"{hi} %" if lo == hi else f"{lo}-{hi} %"
        how = (f"there {share} of one session's points lie" if len(self.refused_shares) == 1 else
               f"the {len(self.refused_shares)} placements they agree on put {share} of one session's points")
        return (f"{len(self.conflicting)} {other}loops agree on where session {self.session_b} lies in session "
                f"{self.session_a}, but {how} in free space the other saw through (at most "
                f"{100 * MAX_FREE_SPACE_CONFLICT:.0f} % for one place seen twice): another place, or a "
                f"symmetric one the loops see turned?")

    def summary(self) -> dict:
        return {"session_a": self.session_a, "session_b": self.session_b, "tried": self.candidates,
                "verified": len(self.verified), "accepted": len(self.consistent), "connected": self.connected,
                "reason": self.why_not_connected(), "free_space_conflict": self.free_space_conflict,
                "loops": self.records,
                "T_a_b": None if self.T_a_b is None else [float(v) for v in self.T_a_b.ravel()]}


def cross_candidates(older: Sequence[Keyframe], newer: Sequence[Keyframe],
                     lc: LoopClosureConfig) -> list[tuple[int, int, CandidateKind, NDArray[np.float64] | None]]:
    """``(i, j, kind, initial T_a_b or None)``: positions in ``older`` and ``newer`` whose place descriptors match
    (module docstring); per keyframe of ``newer`` the ``descriptor_candidates`` best within the gate."""
    if not older or not newer:
        return []
    out: list[tuple[int, int, CandidateKind, NDArray[np.float64] | None]] = []
    if lc.place_descriptor == "scan_context":
        if lc.descriptor_candidates == 0:
            return []
        contexts_a = [k.scan_context for k in older]
        ring_a = np.array([c.ring_key for c in contexts_a])  # type: ignore[union-attr]
        for j, kb in enumerate(newer):
            cb = kb.scan_context
            if cb is None or cb.is_empty:
                continue
            by_ring = np.argsort(np.linalg.norm(ring_a - cb.ring_key, axis=1), kind="stable")
            near = by_ring[: lc.scan_context_ring_candidates]
            scored = sorted((*scan_context_distance(contexts_a[i], cb), int(i)) for i in near)  # type: ignore[arg-type]
            for distance, yaw, i in scored[: lc.descriptor_candidates]:
                if distance <= lc.scan_context_max_distance:
                    out.append((i, j, CandidateKind.SCAN_CONTEXT, yaw_guess(yaw)))
        return out
    desc_a = np.array([k.descriptor for k in older])
    for j, kb in enumerate(newer):
        dist = np.abs(desc_a - kb.descriptor).sum(axis=1)
        for i in np.argsort(dist, kind="stable")[: lc.session_descriptor_candidates]:
            if dist[i] <= lc.session_descriptor_max_distance:
                out.append((int(i), j, CandidateKind.DESCRIPTOR, None))
    return out


def _path(keyframes: Sequence[Keyframe]) -> NDArray[np.float64]:
    """Distance travelled to each keyframe along its session (m)."""
    if not keyframes:
        return np.zeros(0)
    p = np.array([k.T_world_sensor[:3, 3] for k in keyframes])
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def find_pair_loops(session_a: int, session_b: int, older: Sequence[Keyframe], newer: Sequence[Keyframe],
                    lc: LoopClosureConfig, progress: Callable[[int, int], None] | None = None) -> PairLoops:
    """Candidates between two sessions, verified, and their consensus (module docstring)."""
    pair = PairLoops(session_a, session_b)
    todo = cross_candidates(older, newer, lc)
    pair.candidates = len(todo)
    by_id_a = {k.frame_id: n for n, k in enumerate(older)}
    by_id_b = {k.frame_id: n for n, k in enumerate(newer)}
    for n, (i, j, kind, guess) in enumerate(todo):
        cand = verify(older[i], newer[j], kind, lc, path_length_m=math.inf, init_T_a_b=guess)
        pair.records.append({"a": cand.a, "b": cand.b, "kind": kind.value, "verified": cand.accepted,
                             "accepted": False, "reason": cand.reason,
                             "fitness": None if cand.result is None else cand.result.fitness,
                             "rmse_m": None if cand.result is None else cand.result.rmse_m})
        if cand.accepted:
            pair.verified.append(cand)
        if progress:
            progress(n + 1, len(todo))
    if not pair.verified:
        return pair
    path_a, path_b = _path(older), _path(newer)
    align = []
    for c in pair.verified:
        ka, kb = older[by_id_a[c.a]], newer[by_id_b[c.b]]
        assert c.T_a_b is not None
        align.append(ka.T_world_sensor @ c.T_a_b @ geometry.invert(kb.T_world_sensor))
    n = len(pair.verified)
    agree = np.zeros((n, n), dtype=bool)
    for p in range(n):
        for q in range(n):
            agree[p, q] = _agree(pair.verified[p], pair.verified[q], align[p], align[q], older, newer, by_id_a,
                                 by_id_b, path_a, path_b, lc)
    fitness = np.array([c.result.fitness if c.result is not None else 0.0 for c in pair.verified])
    # the loop that most others agree with (ties: the best fitting), and every loop agreeing with it; a set whose
    # placement conflicts with the free space is refused and the next largest set not holding a refused loop tried
    shares: dict[tuple[int, int], float] = {}
    refused_rows: set[int] = set()
    for best in sorted(range(n), key=lambda p: (-int(agree[p].sum()), -float(fitness[p]))):
        if best in refused_rows:
            continue
        keep = [int(q) for q in np.flatnonzero(agree[best]) if int(q) not in refused_rows]
        loops = [pair.verified[q] for q in keep]
        if len(loops) < MIN_CONSISTENT_LOOPS:
            if not pair.conflicting:  # the largest set is too small: so is every other
                pair.consistent, pair.T_a_b = loops, align[best]
                break
            continue  # this loop's others were refused; another loop may still have enough of its own
        share, per_loop = _free_space_conflict(loops, older, newer, by_id_a, by_id_b, lc)
        shares |= per_loop
        if pair.free_space_conflict is None or share <= MAX_FREE_SPACE_CONFLICT:
            pair.free_space_conflict = share
        if share <= MAX_FREE_SPACE_CONFLICT:
            pair.consistent, pair.T_a_b = loops, align[best]
            break
        logger.info("sessions %d <-> %d: %d agreeing loops refused: %.1f %% of their points in the other's free space",
                    session_a, session_b, len(loops), 100 * share)
        pair.conflicting += loops
        pair.refused_shares.append(share)
        refused_rows |= set(keep)
    kept = {(c.a, c.b): c for c in pair.consistent}
    refused = {(c.a, c.b) for c in pair.conflicting}
    for r in pair.records:
        if (r["a"], r["b"]) in shares:
            r["free_space_conflict"] = shares[(r["a"], r["b"])]
        if (r["a"], r["b"]) in kept:
            r["accepted"] = True
            r |= loop_measurement(kept[(r["a"], r["b"])])
        elif (r["a"], r["b"]) in refused:
            r["reason"] = ("passed the registration gates and agrees with others, but their placement puts one "
                           "session's points in free space the other saw through (another place, or a symmetric one "
                           "turned)" + (f"; {len(kept)} other loops were taken" if pair.connected else ""))
        elif r["verified"]:
            r["reason"] = (f"passed the registration gates, but disagrees with the {len(kept)} agreeing loops on "
                           f"where session {session_b} lies in session {session_a}")
    logger.info("sessions %d <-> %d: %d candidates, %d verified, %d agree%s", session_a, session_b, pair.candidates,
                len(pair.verified), len(pair.consistent),
                "" if pair.connected else f" (not connected: {pair.why_not_connected()})")
    return pair


def _free_space_conflict(loops: Sequence[LoopCandidate], older: Sequence[Keyframe], newer: Sequence[Keyframe],
                         by_id_a: dict[int, int], by_id_b: dict[int, int],
                         lc: LoopClosureConfig) -> tuple[float, dict[tuple[int, int], float]]:
    """Each loop's two keyframe clouds in each other's free space (module docstring): the pooled share (the worse
    direction) and each loop's own."""
    margin_m = 2.0 * lc.registration_voxel_m
    b_in_a, a_in_b = FreeSpaceConflict(0, 0, 0), FreeSpaceConflict(0, 0, 0)
    shares = {}
    for c in loops:
        ka, kb = older[by_id_a[c.a]], newer[by_id_b[c.b]]
        assert c.T_a_b is not None
        one = free_space_conflict(ka.points_m, geometry.transform_points(c.T_a_b, kb.points_m), margin_m=margin_m)
        other = free_space_conflict(kb.points_m, geometry.transform_points(geometry.invert(c.T_a_b), ka.points_m),
                                    margin_m=margin_m)
        b_in_a, a_in_b = b_in_a + one, a_in_b + other
        shares[(c.a, c.b)] = max(one.share, other.share)
    return max(b_in_a.share, a_in_b.share), shares


def loop_measurement(c: LoopCandidate) -> dict:
    """What the pose graph takes of an accepted loop (``T_a_b``, 16 numbers row-major, and its 6x6 ``information``,
    36), recorded with it so that an append (:mod:`driftmap.pipeline.merge_append`) reuses it without verifying the
    loop again."""
    info = c.result.information_6x6 if c.result is not None else None
    return {"T_a_b": None if c.T_a_b is None else [float(v) for v in np.asarray(c.T_a_b).ravel()],
            "information": None if info is None else [float(v) for v in np.asarray(info).ravel()]}


def _agree(p: LoopCandidate, q: LoopCandidate, T_p: NDArray[np.float64], T_q: NDArray[np.float64],
           older: Sequence[Keyframe], newer: Sequence[Keyframe], by_id_a: dict[int, int], by_id_b: dict[int, int],
           path_a: NDArray[np.float64], path_b: NDArray[np.float64], lc: LoopClosureConfig) -> bool:
    """Two loops' alignments place both loops' newer keyframes alike, within what the drift between them allows."""
    if p is q:
        return True
    ia, ja = by_id_a[p.a], by_id_b[p.b]
    ib, jb = by_id_a[q.a], by_id_b[q.b]
    travelled = abs(path_a[ia] - path_a[ib]) + abs(path_b[ja] - path_b[jb])
    allowed_m = lc.max_correction_m + lc.descriptor_max_drift_fraction * travelled
    D = T_p @ geometry.invert(T_q)
    for k in (ja, jb):
        x = T_q @ newer[k].T_world_sensor[:, 3]
        if float(np.linalg.norm((D @ x - x)[:3])) > allowed_m:
            return False
    return geometry.rotation_angle_deg(T_p, T_q) <= lc.max_correction_deg


def drop_graph_rejected(pairs: Sequence[PairLoops], rejected: set[tuple[int, int]]) -> list[PairLoops]:
    """The connected pairs whose agreeing loops the pose graph rejected (``rejected``: ``(a, b)`` frame ids) so that
    fewer than :data:`MIN_CONSISTENT_LOOPS` are left: those loops move to ``graph_rejected`` and the pair is no longer
    connected (returned; the caller places the sessions again and optimises without them). Two loops that agree with
    each other but not with either session's trajectory are the footprint of another place registered with middling
    fitness (``tests/test_merge.py``, the 7-Scenes kitchen against the synthetic room: RANSAC found such a pair in
    one run of four). A pair keeping enough loops stays connected; the graph has down-weighted the rest."""
    broken = []
    for p in pairs:
        if not p.connected:
            continue
        gone = [c for c in p.consistent if (c.a, c.b) in rejected]
        if not gone or len(p.consistent) - len(gone) >= MIN_CONSISTENT_LOOPS:
            continue
        p.graph_rejected += gone
        p.consistent = [c for c in p.consistent if (c.a, c.b) not in rejected]
        for r in p.records:
            if (r["a"], r["b"]) in rejected:
                r["accepted"] = False
                r["reason"] = (f"agreed with others, but the pose graph rejected it and fewer than "
                               f"{MIN_CONSISTENT_LOOPS} agreeing loops were left")
        logger.warning("sessions %d <-> %d: the pose graph rejected %d of their %d agreeing loops; fewer than %d left, "
                       "they are not connected", p.session_a, p.session_b, len(gone), len(gone) + len(p.consistent),
                       MIN_CONSISTENT_LOOPS)
        broken.append(p)
    return broken


def connected_sessions(n_sessions: int, pairs: Sequence[PairLoops]) -> tuple[list[int], dict[int, NDArray[np.float64]]]:
    """The sessions connected to session 0 through pairs with enough agreeing loops, in session order, and for each
    the initial ``T_world0_worldk`` chained along the connecting pairs (breadth first from session 0)."""
    T: dict[int, NDArray[np.float64]] = {0: np.eye(4)}
    frontier = [0]
    while frontier:
        nxt = []
        for s in frontier:
            for pair in pairs:
                if not pair.connected or pair.T_a_b is None:
                    continue
                if pair.session_a == s and pair.session_b not in T:
                    T[pair.session_b] = T[s] @ pair.T_a_b
                    nxt.append(pair.session_b)
                elif pair.session_b == s and pair.session_a not in T:
                    T[pair.session_a] = T[s] @ geometry.invert(pair.T_a_b)
                    nxt.append(pair.session_a)
        frontier = nxt
    return sorted(k for k in T if k < n_sessions), T
