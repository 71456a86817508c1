"""Where a ROS log source's frames come from, and what an MCAP written by driftmap says about its frames: the
``provenance`` URI of a topic, and the ``driftmap.export`` metadata record
(:mod:`driftmap.export.mcap`): per sensor topic the original frame ids, pose sources, sensor name and
kind, and the data set the frames were converted from (``origin``)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from driftmap.sources.ros.msgtypes import EXPORT_METADATA_NAME, StampSource

logger = logging.getLogger(__name__)


def provenance_uri(path: str | Path, topic: str, stamp: StampSource) -> str:
    """``/abs/log.mcap#/topic?stamp=header`` (the message index goes into ``Provenance.index``)."""
    return f"{Path(path).resolve()}#{topic}?stamp={stamp.value}"


def parse_provenance_uri(uri: str) -> tuple[str, str, StampSource]:
    """Inverse of :func:`provenance_uri`: ``(path, topic, stamp source)``."""
    path, _, rest = uri.partition("#")
    topic, _, query = rest.partition("?stamp=")
    return path, topic, StampSource(query or StampSource.HEADER.value)


def export_entry(path: Path, record: dict[str, str] | None, topic: str, count: int | None) -> dict[str, Any] | None:
    """The ``driftmap.export`` metadata ``record`` of ``topic`` (a log of ``count`` messages on it), or ``None`` when
    there is none or it does not fit the topic (a warning says why)."""
    if not record:
        return None
    try:
        sensors = json.loads(record.get("sensors", "[]"))
    except (ValueError, RecursionError) as exc:
        logger.warning("%s: unreadable %s metadata (%s); ignored", path, EXPORT_METADATA_NAME, exc)
        return None
    entry = next((s for s in sensors if s.get("topic") == topic), None)
    if entry is None:
        return None
    if count is not None and len(entry.get("frame_ids", [])) != count:
        logger.warning(
            "%s: %s metadata lists %d frames but %s has %d messages; ignored",
            path,
            EXPORT_METADATA_NAME,
            len(entry.get("frame_ids", [])),
            topic,
            count,
        )
        return None
    return entry


def parse_origin(record: dict[str, str]) -> dict[str, Any] | None:
    """The ``origin`` (``{"format", "path", "options"}``) a ``driftmap.export`` metadata record names, if it is
    well formed."""
    try:
        origin = json.loads(record.get("origin", "null"))
    except (ValueError, RecursionError):
        return None
    ok = isinstance(origin, dict) and isinstance(origin.get("format"), str) and isinstance(origin.get("path"), str)
    if ok and not isinstance(origin.get("options", {}), dict):
        ok = False
    return origin if ok else None


def read_export_origin(path: str | Path) -> dict[str, Any] | None:
    """:meth:`RosLogSource.export_origin` of an MCAP file without opening it as a source: only its metadata
    records are read (milliseconds, whatever the length of the log). ``None`` when it names no origin or cannot
    be read."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as fh:
            for record in make_reader(fh).iter_metadata():
                if record.name == EXPORT_METADATA_NAME:
                    return parse_origin(dict(record.metadata))
    except Exception as exc:
        logger.debug("%s: no export origin (%s)", path, exc)
    return None
