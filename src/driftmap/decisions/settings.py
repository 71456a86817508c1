"""The settings of the decisions (thresholds with units) and the hash that names them with the volumetric settings.

A query may override its own thresholds (``min_points``, ``max_normal_spread_deg``, ``max_flatness_m``,
``unknown_is``); everything else is :class:`DecideConfig`, the ``[decide]`` table of a config file
(:class:`driftmap.config.DriftmapConfig`; defined there, below the decisions, and re-exported here).
"""

from __future__ import annotations

import hashlib
import json

from driftmap.config import DecideConfig, VolumeConfig

__all__ = ["DecideConfig", "settings_hash"]


def settings_hash(volume: VolumeConfig, decide: DecideConfig) -> str:
    """16 hex digits of the SHA-256 of the resolved volumetric settings and the decision settings (canonical JSON):
    two decision sets with the same hash were made with the same settings."""
    payload = {"volume": volume.model_dump(mode="json"), "decide": decide.model_dump(mode="json")}
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]
