"""The settings of the decisions (thresholds with units) and the hash that names them with the volumetric settings.

A query may override its own thresholds (``min_points``, ``max_normal_spread_deg``, ``max_flatness_m``,
``unknown_is``); everything else is :class:`DecideConfig`, the ``[decide]`` table of a config file
(:class:`driftmap.config.DriftmapConfig`; defined there, below the decisions, and re-exported here).
"""

from __future__ import annotations

import hashlib
import json
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from driftmap.config import DecideConfig, VolumeConfig
from driftmap.errors import ConfigError

__all__ = ["DecideConfig", "check_decide_table", "settings_hash"]


def settings_hash(volume: VolumeConfig, decide: DecideConfig) -> str:
    """16 hex digits of the SHA-256 of the resolved volumetric settings and the decision settings (canonical JSON):
    two decision sets with the same hash were made with the same settings."""
    payload = {"volume": volume.model_dump(mode="json"), "decide": decide.model_dump(mode="json")}
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def check_decide_table(table: Any, where: str | Path | None = None) -> None:
    """The ``[decide]`` table as a config file wrote it: a threshold is a number (``0.1``, not the text ``"0.1"``,
    nor ``true``), ``range_limited_points`` is ``true`` or ``false`` -- as a query file's thresholds are (pydantic
    would read ``sweep_step_m = "0.1"`` as 0.1 m). A :class:`ConfigError` naming the file (``where``, when known)
    and the key; keys and values of other kinds are left to :class:`DecideConfig`, which names them."""
    if not isinstance(table, Mapping):
        return
    prefix = f"{where}: " if where is not None else ""
    for key, value in table.items():
        field = DecideConfig.model_fields.get(key) if isinstance(key, str) else None
        if field is None:
            continue
        kinds = _kinds(field.annotation)
        if value is None and type(None) in kinds:
            continue
        if bool in kinds:
            ok, expected = isinstance(value, bool), "true or false"
        else:
            ok, expected = isinstance(value, (int, float)) and not isinstance(value, bool), "a number"
        if ok:
            continue
        hint = ""
        if isinstance(value, str):
            hint = " (text, in quotes: write the number without quotes)" if expected == "a number" and \
                _is_number_text(value) else " (text, in quotes)"
            if expected != "a number" and value.strip().lower() in ("true", "false"):
                hint = " (text, in quotes: write true or false without quotes)"
        raise ConfigError(f"{prefix}decide.{key}: expected {expected}, got {_shown(value)}{hint}")


def _kinds(annotation: Any) -> set[type]:
    """The types of an annotation (``float | None`` -> {float, NoneType})."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return {t for a in typing.get_args(annotation) for t in _kinds(a)}
    return {annotation} if isinstance(annotation, type) else set()


def _is_number_text(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _shown(value: Any) -> str:
    """The value for an error line: TOML / JSON spelling of true and false, long values shortened."""
    if isinstance(value, bool):
        return str(value).lower()
    text = repr(value)
    return text if len(text) <= 60 else f"{text[:40]}... ({len(text):,} characters)"
