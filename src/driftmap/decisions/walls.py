"""The double walls a decision can be told about: the regions ``driftmap diagnose`` flags (a
:class:`~driftmap.diagnostics.diagnosis.Diagnosis`, or the JSON ``diagnose --json`` wrote), and which of them lie in
reach of a query."""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.decisions.errors import QueryError


@dataclass(frozen=True)
class DoubleWall:
    """One flagged region: its centre, normal and the separation of its two layers (m), and the frames of each."""

    center_m: NDArray[np.float64]
    normal: NDArray[np.float64]
    separation_m: float
    frames: tuple[int, ...] = ()

    def to_json(self) -> dict:
        return {"center_m": [float(v) for v in self.center_m], "separation_m": float(self.separation_m)}


def double_walls_of(source: Any, revision: int | None = None) -> list[DoubleWall]:
    """Double walls from a Diagnosis, a diagnose JSON file or dict, or a list of regions (objects or dicts).
    A diagnosis of another revision than ``revision`` is refused (its walls are elsewhere)."""
    if source is None:
        return []
    if isinstance(source, (str, Path)):
        path = Path(source)
        try:
            source = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise QueryError(f"{path}: cannot read the diagnosis ({exc})", query_id=None) from None
    if isinstance(source, dict):
        found = source.get("revision")
        if revision is not None and found is not None and int(found) != int(revision):
            raise QueryError(f"the diagnosis is of revision {found}, the decisions of revision {revision}: diagnose "
                             f"the same revision", query_id=None)
        regions = (source.get("double_wall") or {}).get("regions", [])
        return [_from_dict(r) for r in regions]
    walls = getattr(source, "double_walls", None)
    if walls is not None and hasattr(walls, "regions"):
        found = getattr(source, "revision", None)
        if revision is not None and found is not None and int(found) != int(revision):
            raise QueryError(f"the diagnosis is of revision {found}, the decisions of revision {revision}",
                             query_id=None)
        return [_from_region(r) for r in walls.regions]
    return [_from_dict(r) if isinstance(r, dict) else _from_region(r) for r in source]


def _from_dict(r: dict) -> DoubleWall:
    frames = tuple(int(f) for f in [*r.get("frames_a", []), *r.get("frames_b", [])])
    return DoubleWall(np.asarray(r["center_m"], dtype=np.float64), np.asarray(r.get("normal", [0, 0, 1]), dtype=np.float64),
                      float(r["separation_m"]), frames)


def _from_region(r: Any) -> DoubleWall:
    frames = tuple(int(f) for f in [*np.asarray(r.frames_a).tolist(), *np.asarray(r.frames_b).tolist()])
    return DoubleWall(np.asarray(r.center_m, dtype=np.float64), np.asarray(r.normal, dtype=np.float64),
                      float(r.separation_m), frames)


def walls_in_reach(walls: Iterable[DoubleWall], lo: NDArray[np.float64], hi: NDArray[np.float64],
                   reach_m: float) -> list[DoubleWall]:
    """The walls whose centre lies within ``reach_m`` of the box ``lo .. hi`` (a query's region)."""
    out = []
    for w in walls:
        gap = np.maximum(0.0, np.maximum(lo - w.center_m, w.center_m - hi))
        if float(np.linalg.norm(gap)) <= reach_m:
            out.append(w)
    return out
