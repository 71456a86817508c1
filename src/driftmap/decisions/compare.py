"""What changed for the robot between two decision sets of the same queries -- two revisions of a store, or two
stores built from the same log: the decisions that flipped, how far every margin moved, and why (the contributing
frames whose poses moved, and how far that carried the decision's evidence point; the double walls in reach)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from driftmap.decisions.errors import QueryError
from driftmap.decisions.query_file import query_to_json
from driftmap.decisions.records import Decision, DecisionSet

MOVED_M = 0.005
"""A contributing frame counts as moved when its pose change carries the evidence point at least this far (m)."""


@dataclass(frozen=True)
class Flip:
    """One decision that differs: before (``a``) and after (``b``), the margin's change, and why."""

    id: str
    kind: str
    before: str
    after: str
    margin_delta: float | None
    why: dict = field(default_factory=dict)
    anchor_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def to_json(self) -> dict:
        return {"id": self.id, "before": self.before, "after": self.after,
                "margin_delta": None if self.margin_delta is None else float(self.margin_delta),
                "kind": self.kind, "why": self.why, "anchor_m": [float(v) for v in self.anchor_m]}


@dataclass(frozen=True)
class Comparison:
    """The flips of ``b`` against ``a`` and every margin's change."""

    a: DecisionSet
    b: DecisionSet
    flipped: list[Flip]
    margin_deltas: dict[str, float | None]

    @property
    def flipped_fraction(self) -> float:
        return len(self.flipped) / max(len(self.margin_deltas), 1)

    def flipped_ids(self) -> list[str]:
        return [f.id for f in self.flipped]

    def to_json(self) -> dict:
        deltas = [v for v in self.margin_deltas.values() if v is not None]
        return {
            "flipped": [f.to_json() for f in self.flipped],
            "compared": {"a": self.a.representation.to_json(), "b": self.b.representation.to_json()},
            "comparison_summary": {
                "n_compared": len(self.margin_deltas), "n_flipped": len(self.flipped),
                "flipped_fraction": self.flipped_fraction,
                "max_abs_margin_delta": max((abs(v) for v in deltas), default=None),
            },
            "margin_deltas": [{"id": k, "margin_delta": v} for k, v in self.margin_deltas.items()],
        }


def compare(a: DecisionSet, b: DecisionSet) -> Comparison:
    """Compare two decision sets of the same query ids (``a`` before, ``b`` after)."""
    da, db = a.by_id(), b.by_id()
    if set(da) != set(db):
        missing = sorted(set(da) ^ set(db))[:5]
        raise QueryError(f"the two decision sets answer different queries (e.g. {missing}): compare the same query "
                         f"file", query_id=missing[0] if missing else None)
    queries = b.queries.by_id()
    for qid, qa in a.queries.by_id().items():  # the same ids must ask the same (hostile trial 25 W10)
        ja, jb = query_to_json(qa), query_to_json(queries[qid])
        if ja != jb:
            fields = sorted(k for k in set(ja) | set(jb) if ja.get(k) != jb.get(k))
            raise QueryError(f"query {qid!r} differs between the two decision sets ({', '.join(fields)}): a change "
                             f"of the query would read as a flip of the map; compare the same query file",
                             query_id=qid, field=fields[0] if fields else None)
    flipped: list[Flip] = []
    deltas: dict[str, float | None] = {}
    for qid, before in da.items():
        after = db[qid]
        delta = None if before.margin is None or after.margin is None else float(after.margin - before.margin)
        deltas[qid] = delta
        if before.decision != after.decision:
            anchor = tuple(float(v) for v in queries[qid].anchor_m())
            flipped.append(Flip(qid, before.kind, before.decision, after.decision, delta, _why(a, b, before, after),
                                anchor))  # type: ignore[arg-type]
    return Comparison(a, b, flipped, deltas)


def _why(a: DecisionSet, b: DecisionSet, before: Decision, after: Decision) -> dict:
    """The contributing frames (of either side) whose pose moved the evidence point, and the walls in reach."""
    point = after.evidence_m if after.evidence_m is not None else before.evidence_m
    moved: list[dict] = []
    for f in sorted(set(before.frames) | set(after.frames)):
        Ta, Tb = a.pose_of(f), b.pose_of(f)
        if Ta is None or Tb is None:
            continue
        if point is None:
            shift = float(np.linalg.norm(Tb[:3, 3] - Ta[:3, 3]))
        else:
            p = np.append(np.asarray(point, dtype=np.float64), 1.0)
            shift = float(np.linalg.norm((Tb @ np.linalg.solve(Ta, p))[:3] - p[:3]))
        if shift >= MOVED_M:
            moved.append({"frame": int(f), "evidence_shift_m": round(shift, 4)})
    walls = [*before.details.get("double_walls_in_reach", []), *after.details.get("double_walls_in_reach", [])]
    return {"frames_moved": moved, "max_evidence_shift_m": max((m["evidence_shift_m"] for m in moved), default=0.0),
            "double_walls_in_reach": walls,
            "uncertainty_before": before.uncertainty, "uncertainty_after": after.uncertainty}


def output_json(decisions: DecisionSet, comparison: Comparison | None = None) -> dict:
    """What ``driftmap decide --json`` writes: the representation and decisions of ``decisions`` (with a
    comparison: of its ``b``), and with a comparison ``flipped``, ``compared`` and the decisions of ``a``
    (``decisions_a``)."""
    out = decisions.to_json()
    if comparison is not None:
        out.update(comparison.to_json())
        out["decisions_a"] = [d.to_json() for d in comparison.a.decisions]
    return out
