"""Two merge sessions that are one recording built twice.

``driftmap merge`` refuses the same store twice by its uuid, but two builds of one log (another ``--out``, another
pose source) have uuids of their own: merged, every physical frame sat in the map twice, with no warning (hostile
trial 27 W8: a ground-truth build and an odometry build of one 20-frame log made a 40-frame store whose surfaces were
all doubled). A frame is identified by the file it was read from, its index in that file and its stamp (the
provenance every store records, through a merge too); sessions that share any such frame are refused, naming both
and the first shared frame. Sessions of one log split by ``--frames`` ranges that do not overlap are not refused.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from driftmap.errors import ConfigError
from driftmap.store.frame_store import FrameStore

Reading = tuple[str, int, int]
"""(source file or log URI, index in it, stamp_ns) of a stored frame."""


OriginOf = Callable[[dict[str, Any]], "tuple[str | None, int | None] | None"]
"""A merged store's frame provenance -> its origin's (source URI, index); None for a frame no merge made."""


def frame_readings(store: FrameStore, frame_ids: Sequence[int] | None = None,
                   origin_of: OriginOf | None = None) -> dict[Reading, int]:
    """``{reading: frame id}`` of the store's frames (``frame_ids``: only these) that record where they were read;
    with ``origin_of`` a merged store's frames give their origin's."""
    stamps = dict(zip(map(int, store.ledger.frame_ids), map(int, store.ledger.stamps_ns), strict=True))
    readings: dict[Reading, int] = {}
    for fid in (store.frame_ids if frame_ids is None else frame_ids):
        provenance = store.frame_info(int(fid)).get("provenance") or {}
        if not provenance.get("source_uri"):
            continue
        origin = origin_of(provenance) if origin_of is not None else None
        uri, index = origin if origin is not None else (provenance["source_uri"], provenance.get("index"))
        if uri is None or index is None:
            continue
        readings[(str(uri), int(index), stamps[int(fid)])] = int(fid)
    return readings


def refuse_same_recording(sessions: Sequence[tuple[str, dict[Reading, int]]]) -> None:
    """Raise :class:`ConfigError` when two of ``sessions`` (``(name, frame_readings)``) hold a frame read from the
    same file at the same index and stamp."""
    for k, (name_b, b) in enumerate(sessions):
        for name_a, a in sessions[:k]:
            shared = sorted(a.keys() & b.keys(), key=lambda r: a[r])
            if not shared:
                continue
            uri, index, stamp_ns = shared[0]
            raise ConfigError(
                f"{name_a} and {name_b}: the same recording built twice, not two sessions: {len(shared)} of their "
                f"frames were read from the same files at the same stamps (the first: frame {a[shared[0]]} of "
                f"{name_a} and frame {b[shared[0]]} of {name_b}, item {index} of {uri}, stamp {stamp_ns} ns); merged, "
                f"every such frame would sit in the map twice. Merge each recording once (to compare two builds of one "
                f"log, use `driftmap decide --against` or `diagnose`)")
