"""What a decision run returns: one :class:`Decision` per query, the :class:`Representation` it was made on, and
their JSON (the contract of docs/decisions.md: extend, never rename)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.decisions.query_file import QuerySet

OK_DECISIONS = frozenset({"free", "graspable", "stable", "known"})
"""Decisions that let the robot act (figures colour them green)."""
UNKNOWN_DECISIONS = frozenset({"unknown", "go_look", "too_few_points"})
"""Decisions that say the map does not know enough (figures colour them orange); the rest are refusals (red)."""


@dataclass(frozen=True)
class Representation:
    """The map a decision set was made on: enough to make it again with the same command."""

    store: str
    revision: int
    settings_hash: str
    driftmap_version: str
    store_uuid: str | None = None
    n_frames: int = 0
    settings: dict = field(default_factory=dict)
    query_file: str | None = None
    sessions_not_merged: list[int] = field(default_factory=list)
    """sessions the revision shows at their own, unmerged poses because damage took the merge revision (hostile
    trial 21 W6); the decisions whose frames include theirs carry the failure label ``sessions_not_merged``"""
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> dict:
        return {"store": self.store, "revision": int(self.revision), "settings_hash": self.settings_hash,
                "driftmap_version": self.driftmap_version, "store_uuid": self.store_uuid, "n_frames": int(self.n_frames),
                "query_file": self.query_file, "settings": self.settings,
                "sessions_not_merged": [int(k) for k in self.sessions_not_merged], "warnings": list(self.warnings)}


@dataclass
class Decision:
    """One query's answer. ``margin``: metres (clearance, collision) or degrees (grasp, foothold) or a fraction
    (explore) by which the decision clears its threshold (negative: by how much it fails); ``uncertainty``: metres
    (docs/decisions.md), None when nothing measures it; ``details``: the numbers behind the decision."""

    id: str
    kind: str
    decision: str
    margin: float | None
    uncertainty: float | None
    failure_label: str | None
    frames: list[int]
    stamp_ns_newest: int | None
    latency_s: float = 0.0
    evidence_m: NDArray[np.float64] | None = None
    """the world point the decision hinges on (nearest surface, contact, grasp contact, patch, region centre)"""
    details: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "id": self.id, "kind": self.kind, "decision": self.decision, "margin": _num(self.margin),
            "uncertainty": _num(self.uncertainty), "failure_label": self.failure_label,
            "frames": [int(f) for f in self.frames],
            "stamp_ns_newest": None if self.stamp_ns_newest is None else int(self.stamp_ns_newest),
            "latency_s": float(self.latency_s),
            "evidence_m": None if self.evidence_m is None else [float(v) for v in self.evidence_m],
            "details": _jsonable(self.details),
        }


@dataclass
class DecisionSet:
    """The decisions of one query set on one representation (a store's revision), in the query file's order."""

    representation: Representation
    decisions: list[Decision]
    queries: QuerySet
    frame_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    poses: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4, 4)), repr=False)
    """the revision's T_world_sensor of every frame (what a comparison reads to tell which frames moved)"""
    double_walls: list = field(default_factory=list, repr=False)
    seconds: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.decisions)

    def by_id(self) -> dict[str, Decision]:
        return {d.id: d for d in self.decisions}

    def pose_of(self, frame_id: int) -> NDArray[np.float64] | None:
        k = int(np.searchsorted(self.frame_ids, frame_id))
        if k < len(self.frame_ids) and self.frame_ids[k] == frame_id:
            return self.poses[k]
        return None

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for d in self.decisions:
            out[d.decision] = out.get(d.decision, 0) + 1
        return out

    def to_json(self) -> dict:
        return {"representation": self.representation.to_json(), "decisions": [d.to_json() for d in self.decisions],
                "summary": {"n_decisions": len(self.decisions), "counts": self.counts(),
                            "seconds": {k: round(v, 4) for k, v in self.seconds.items()},
                            "n_double_walls": len(self.double_walls)}}


def _num(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)


def _jsonable(value: Any) -> Any:
    """numpy values and arrays (nested in dicts and lists) as plain JSON values; non-finite floats as None."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return _num(float(value))
    return value
