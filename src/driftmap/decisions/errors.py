"""The error of a bad action query (:class:`driftmap.errors.QueryError`, re-exported here)."""

from __future__ import annotations

from driftmap.errors import QueryError

__all__ = ["QueryError"]
