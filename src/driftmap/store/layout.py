"""Every file name inside a store folder, in one place (the store's own files and what ``build`` writes beside
them); nothing else spells them."""

from __future__ import annotations

import re

MANIFEST = "store.json"
"""the manifest: segments, ledger revisions, the store's id and version"""
LOCK_FILE = "writer.lock"
"""held by the one process that appends (readers need no lock)"""
SEGMENT_GLOB = "segment-*.mcap"
SEGMENT_FILE = re.compile(r"segment-\d{6,}\.mcap")
"""a segment's name: ``segment-NNNNNN.mcap`` (frames and ledger records, MCAP)"""
BUILD_SOURCE_FILE = "build_source.json"
"""what ``build`` read: the source's path, format and options (``--resume`` must read the same)"""
BUILD_CONFIG_FILE = "build_config.json"
"""the settings ``build`` ran with"""
BUILD_SUMMARY_FILE = "build_summary.json"
"""what ``build`` found: frames, tracking health, the odometry's settings, loops, timings"""


def segment_name(index: int) -> str:
    """The file name of segment ``index``."""
    return f"segment-{index:06d}.mcap"
