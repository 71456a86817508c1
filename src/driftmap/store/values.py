"""Small helpers the store modules share: integer and pose-source checks, read-only arrays, and short previews of
id lists for messages."""

from __future__ import annotations

import numbers
from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import StoreError, parse_enum
from driftmap.frame import PoseSource


def preview(values: Iterable[Any], limit: int = 10) -> str:
    """``[1, 2, 3]`` or ``[1, 2, ..., 40] (40 in all)`` for error messages."""
    values = list(values)
    if len(values) <= limit:
        return str(values)
    return f"[{', '.join(str(v) for v in values[:limit])}, ...] ({len(values)} in all)"


def id_sample(ids: NDArray[np.int64]) -> str:
    """``0, 5, 10, ..., 95`` for messages."""
    shown = ", ".join(str(int(i)) for i in ids[:3])
    return f"{shown}, ..., {int(ids[-1])}" if len(ids) > 4 else ", ".join(str(int(i)) for i in ids)


def as_int(value: Any, what: str) -> int:
    """``value`` as an ``int``; a bool or a non-integer is a :class:`StoreError` naming ``what``."""
    if type(value) is int:  # the common case, without the (slow) ABC check below
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise StoreError(f"{what} must be an integer, got {value!r}")
    return int(value)


def as_source(value: Any) -> PoseSource:
    return parse_enum(PoseSource, value, "unknown pose source", StoreError)


def readonly(array: NDArray[Any]) -> NDArray[Any]:
    """``array``, made read-only in place."""
    array.setflags(write=False)
    return array
