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
    """Double walls from a Diagnosis, a diagnose JSON file or dict, or a list of regions (objects, dicts or
    :class:`DoubleWall` already converted). A diagnosis of another revision than ``revision`` is refused (its walls
    are elsewhere). A malformed diagnosis is a :class:`QueryError` naming the file (or ``the diagnosis``) and field."""
    if source is None:
        return []
    where = "the diagnosis"
    if isinstance(source, (str, Path)):
        path = Path(source)
        where = f"{path}"
        try:
            source = json.loads(path.read_text(encoding="utf-8-sig"))
        except (OSError, ValueError, RecursionError) as exc:
            raise QueryError(f"{path}: cannot read the diagnosis ({exc})", query_id=None) from None
        if not isinstance(source, dict):
            raise QueryError(f"{path}: not a diagnosis (diagnose --json writes an object with 'revision' and "
                             f"'double_wall', got a {type(source).__name__})", query_id=None)
    if isinstance(source, dict):
        found = source.get("revision")
        if found is not None and (isinstance(found, bool) or not isinstance(found, int) or found < 0):
            raise QueryError(f"{where}: field 'revision' must be a revision id (a whole number >= 0), got {found!r}",
                             query_id=None, field="revision")
        if revision is not None and found is not None and int(found) != int(revision):
            raise QueryError(f"{where}: the diagnosis is of revision {found}, the decisions of revision {revision}: "
                             f"diagnose the same revision", query_id=None)
        block = source.get("double_wall") or {}
        if not isinstance(block, dict):
            raise QueryError(f"{where}: field 'double_wall' must be an object with 'regions', got "
                             f"{type(block).__name__}", query_id=None, field="double_wall")
        regions = block.get("regions") or []
        if not isinstance(regions, list):
            raise QueryError(f"{where}: field 'double_wall.regions' must be a list, got {type(regions).__name__}",
                             query_id=None, field="double_wall.regions")
        return [_from_dict(r, where, f"double_wall.regions[{k}]") for k, r in enumerate(regions)]
    walls = getattr(source, "double_walls", None)
    if walls is not None and hasattr(walls, "regions"):
        found = getattr(source, "revision", None)
        if revision is not None and found is not None and int(found) != int(revision):
            raise QueryError(f"the diagnosis is of revision {found}, the decisions of revision {revision}",
                             query_id=None)
        return [_from_region(r) for r in walls.regions]
    if isinstance(source, (str, bytes)) or not hasattr(source, "__iter__"):
        raise QueryError(f"double walls: expected a diagnosis or a list of regions, got {type(source).__name__}",
                         query_id=None)
    out = []
    for k, r in enumerate(source):
        if isinstance(r, DoubleWall):
            out.append(r)  # converted already (e.g. by the CLI): not again
        elif isinstance(r, dict):
            out.append(_from_dict(r, where, f"regions[{k}]"))
        elif all(hasattr(r, a) for a in ("center_m", "normal", "separation_m", "frames_a", "frames_b")):
            out.append(_from_region(r))
        else:
            raise QueryError(f"{where}: regions[{k}] is not a double-wall region (got {type(r).__name__})",
                             query_id=None, field=f"regions[{k}]")
    return out


def diagnosis_mismatch(source: Any, frame_ids: Iterable[int], stamps_ns: Iterable[int],
                       store_uuid: str) -> tuple[str | None, bool]:
    """Whether a diagnosis (a Diagnosis, or the JSON ``diagnose --json`` wrote, as a path or dict) is of a store: the
    reason it is not (None when it is) and whether it names its store (``store_uuid``; older diagnoses do not). Every
    frame it lists must be in the store with the same stamp, and the store id it names the store's; a frame that
    differs is named first (the plainer reason; hostile trials 6 W16, 24 B3). Unreadable or malformed input: (None,
    True) -- :func:`double_walls_of` names the problem. A bare list of regions is not checked (it names no store)."""
    data: Any = source
    if isinstance(source, (str, Path)):
        try:
            data = json.loads(Path(source).read_text(encoding="utf-8-sig"))
        except (OSError, ValueError, RecursionError):
            return None, True
    elif not isinstance(source, dict) and hasattr(source, "store_uuid") and hasattr(source, "to_json"):
        data = source.to_json()
    if not isinstance(data, dict):
        return None, True
    try:
        uuid = data.get("store_uuid")
        listed = {int(f["frame_id"]): int(f["stamp_ns"]) for f in (data.get("frames") or [])}
    except (TypeError, ValueError, KeyError, AttributeError):
        return None, True
    ours = dict(zip((int(f) for f in frame_ids), (int(t) for t in stamps_ns)))
    for fid, stamp in listed.items():
        if ours.get(fid) != stamp:
            what = "is not in the store" if fid not in ours else f"has stamp {ours[fid]} ns in the store, {stamp} ns there"
            return f"its frame {fid} {what}", isinstance(uuid, str)
    if isinstance(uuid, str) and uuid != store_uuid:
        return f"it is of another store (store_uuid {uuid})", True
    return None, isinstance(uuid, str)


def _from_dict(r: Any, where: str, at: str) -> DoubleWall:
    if not isinstance(r, dict):
        raise QueryError(f"{where}: field '{at}' must be an object, got {type(r).__name__}", query_id=None, field=at)

    def vector(key: str, default: Any = None) -> np.ndarray:
        v = r.get(key, default)
        if v is None:
            raise QueryError(f"{where}: field '{at}.{key}' is missing", query_id=None, field=f"{at}.{key}")
        ok = isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                          for x in v)
        out = np.asarray(v, dtype=np.float64) if ok else None
        if out is None or not np.all(np.isfinite(out)):
            raise QueryError(f"{where}: field '{at}.{key}' must be 3 finite numbers, got {v!r}", query_id=None,
                             field=f"{at}.{key}")
        return out

    center, normal = vector("center_m"), vector("normal", [0, 0, 1])
    sep = r.get("separation_m")
    if sep is None:
        raise QueryError(f"{where}: field '{at}.separation_m' is missing", query_id=None, field=f"{at}.separation_m")
    if isinstance(sep, bool) or not isinstance(sep, (int, float)) or not np.isfinite(sep) or sep < 0:
        raise QueryError(f"{where}: field '{at}.separation_m' must be a finite number >= 0, got {sep!r}",
                         query_id=None, field=f"{at}.separation_m")
    frames: list[int] = []
    for key in ("frames_a", "frames_b"):
        fs = r.get(key, [])
        if not isinstance(fs, list) or not all(isinstance(f, int) and not isinstance(f, bool) for f in fs):
            raise QueryError(f"{where}: field '{at}.{key}' must be a list of frame ids, got {fs!r}", query_id=None,
                             field=f"{at}.{key}")
        frames.extend(int(f) for f in fs)
    return DoubleWall(center, normal, float(sep), tuple(frames))


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
