"""Every file name inside a store folder, in one place (the store's own files, the copies recovery keeps, and what
``build`` writes beside them); nothing else spells them."""

from __future__ import annotations

import re

FORMAT_NAME = "driftmap-store"
"""the manifest's ``format``: what marks a folder as a driftmap store"""
MANIFEST = "store.json"
"""the manifest: segments, ledger revisions, the store's id and version"""
LOCK_FILE = "writer.lock"
"""held by the one process that appends (readers need no lock)"""
SEGMENT_GLOB = "segment-*.mcap"
SEGMENT_FILE = re.compile(r"segment-[0-9]{6,}\.mcap")
"""a segment's name: ``segment-NNNNNN.mcap`` (frames and ledger records, MCAP)"""
SEGMENT_FILES_GLOB = "segment-*"
"""every file named after a segment: the segments and the copies recovery keeps beside them"""
SEGMENT_INDEX = re.compile(r"segment-([0-9]+)\.")
"""the index in the name of a segment or of a file named after one (``segment-000003.mcap.damaged``)"""
DAMAGED_SUFFIX = ".damaged"
"""a damaged file that recovery replaced, kept beside it (``segment-NNNNNN.mcap.damaged``, ``store.json.damaged``)"""
BEFORE_DAMAGE_SUFFIX = ".before-damage.json"
"""beside a segment recovery found damaged, kept for good: its size before the damage and the manifest's record of what
it held (``segment-NNNNNN.mcap.before-damage.json``)"""
RECOVERING_SUFFIX = ".recovering"
"""a segment being rewritten by recovery (renamed over the damaged one when complete)"""
TMP_SUFFIX = ".tmp"
"""a file being written, renamed into place when complete"""
BUILD_SOURCE_FILE = "build_source.json"
"""what ``build`` read: the source's path, format and options (``--resume`` must read the same)"""
BUILD_CONFIG_FILE = "build_config.json"
"""the settings ``build`` ran with"""
BUILD_SUMMARY_FILE = "build_summary.json"
"""what ``build`` found: frames, tracking health, the odometry's settings, loops, timings"""
MERGE_SUMMARY_FILE = "merge_summary.json"
"""what ``merge`` found: the sessions, their origins, the loops between them, the merge revision"""
SESSION_ID_STRIDE = 1_000_000_000
"""A merged store's frame id is ``session * SESSION_ID_STRIDE + the source frame id`` (session 1's frame 500 is
1000000500): ids stay unique, sorted in session order, and the source id readable; source ids must be below it."""


def segment_name(index: int) -> str:
    """The file name of segment ``index``."""
    return f"segment-{index:06d}.mcap"


def segment_index(name: str) -> int | None:
    """The segment index in ``name`` (a segment's name, or that of a file named after one), or None."""
    m = SEGMENT_INDEX.match(name)
    return None if m is None else int(m.group(1))


def dropped_tail_name(segment: str) -> str:
    """Where the unfinished tail of a crashed writer's segment is kept: ``segment-NNNNNN.dropped-tail.bin``."""
    return f"{segment.removesuffix('.mcap')}.dropped-tail.bin"
