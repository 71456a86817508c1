"""Decisions: what a map revision lets a robot do -- clearance, collision, grasp, foothold and exploration queries
answered on a store's revision, with the margin, uncertainty, freshness and representation of every answer, and
what changed between two revisions or two stores (docs/decisions.md).

One concept per module: ``query_file`` (the queries and their file), ``settings``, ``records`` (decisions and their
JSON), ``walls`` (double walls in reach), ``evidence`` (frames, freshness, uncertainty), ``space`` (clearance,
collision, explore), ``surface`` (grasp, foothold), ``decide`` (the entry points), ``compare``, ``figure`` (the top
view), ``synthetic_truth`` and ``synthetic_queries`` (a query set with its truth for the synthetic room).
"""

from driftmap.decisions.compare import Comparison, Flip, compare
from driftmap.decisions.decide import decide, decide_revisions
from driftmap.decisions.errors import QueryError
from driftmap.decisions.query_file import KINDS, QuerySet, load_queries, parse_queries
from driftmap.decisions.records import Decision, DecisionSet, Representation
from driftmap.decisions.settings import DecideConfig

__all__ = ["KINDS", "Comparison", "DecideConfig", "Decision", "DecisionSet", "Flip", "QueryError", "QuerySet",
           "Representation", "compare", "decide", "decide_revisions", "load_queries", "parse_queries"]
