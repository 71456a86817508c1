"""Action queries and the query file (docs/decisions.md): ``{"queries": [{"id": ..., "kind": ..., ...}, ...]}`` in
JSON, or the same in YAML when PyYAML is installed.

Every query is checked before anything is computed; a bad one is a :class:`~driftmap.decisions.errors.QueryError`
naming the query id and the field (an unknown kind, a path of one point, a negative radius, a number that is not
finite, a box whose max is below its min, ...). Whether a query's region lies on the map can only be told with the
map: :func:`driftmap.decisions.decide.decide` checks that against the layers' bounds.
"""

from __future__ import annotations

import json
import math
import unicodedata
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.decisions.errors import QueryError
from driftmap.files import json_loads_unique

KINDS = ("clearance", "collision", "grasp", "foothold", "explore")
UNKNOWN_POLICIES = ("occupied", "free")
IGNORED_KEYS = frozenset({"note", "tags", "truth"})
"""Keys a query may carry for its author (a description, labels, the truth of a generated set); decide ignores them."""
MAX_POINTS_PER_QUERY = 100_000
MAX_QUERY_FILE_BYTES = 256 << 20
MAX_LENGTH_M = 1000.0
"""A radius, footprint size or flatness above this (m) is no robot's question: a unit mistake (and would overflow
the voxel counts)."""
MAX_COORDINATE_M = 1.0e6
"""A query point farther than this (m) from the map's origin on any axis is a unit or parsing mistake (and would
overflow the region arithmetic); decide checks the region against the map's bounds anyway."""
MAX_MIN_POINTS = 100_000_000
"""A ``min_points`` above this is no query's threshold (no region of a map holds that many points)."""


@dataclass(frozen=True)
class Query:
    """What every query has: its id and kind (the subclasses add the geometry)."""

    id: str
    kind: str

    def extent_m(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:  # pragma: no cover - abstract
        raise NotImplementedError

    def anchor_m(self) -> NDArray[np.float64]:
        """A representative world point (for figures and distances to double walls): the extent's centre."""
        lo, hi = self.extent_m()
        return 0.5 * (lo + hi)


@dataclass(frozen=True)
class ClearanceQuery(Query):
    points_m: NDArray[np.float64]
    radius_m: float
    unknown_is: str | None = None

    def extent_m(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.points_m.min(axis=0) - self.radius_m, self.points_m.max(axis=0) + self.radius_m


@dataclass(frozen=True)
class CollisionQuery(Query):
    path_m: NDArray[np.float64]
    footprint: str
    """box | cylinder"""
    size_m: tuple[float, ...]
    """box: edge lengths (x, y, z); cylinder: (radius, height), axis vertical"""
    unknown_is: str | None = None

    @property
    def half_extent_m(self) -> NDArray[np.float64]:
        if self.footprint == "box":
            return 0.5 * np.asarray(self.size_m, dtype=np.float64)
        r, h = self.size_m
        return np.array([r, r, 0.5 * h])

    def extent_m(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.path_m.min(axis=0) - self.half_extent_m, self.path_m.max(axis=0) + self.half_extent_m

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.path_m, axis=0), axis=1).sum())


@dataclass(frozen=True)
class GraspQuery(Query):
    roi_min_m: NDArray[np.float64]
    roi_max_m: NDArray[np.float64]
    min_points: int | None = None
    max_normal_spread_deg: float | None = None

    def extent_m(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.roi_min_m, self.roi_max_m


@dataclass(frozen=True)
class FootholdQuery(Query):
    center_m: NDArray[np.float64]
    radius_m: float
    max_slope_deg: float
    max_flatness_m: float | None = None
    min_points: int | None = None

    def extent_m(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.center_m - self.radius_m, self.center_m + self.radius_m


@dataclass(frozen=True)
class ExploreQuery(Query):
    min_m: NDArray[np.float64]
    max_m: NDArray[np.float64]
    max_unknown_fraction: float

    def extent_m(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.min_m, self.max_m


@dataclass(frozen=True)
class QuerySet:
    """The queries of a file (in its order) and where they came from."""

    queries: list[Query]
    source: str = "<memory>"
    raw: list[dict] = field(default_factory=list, repr=False)
    """the queries as given (the truth of a generated set travels here)"""

    def __len__(self) -> int:
        return len(self.queries)

    def __iter__(self):
        return iter(self.queries)

    def by_id(self) -> dict[str, Query]:
        return {q.id: q for q in self.queries}


# ------------------------------------------------------------------------------------------------ loading
def load_queries(path: str | Path) -> QuerySet:
    """Read and check a query file: ``.json``, or ``.yaml`` / ``.yml`` (needs PyYAML)."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise QueryError(f"{path}: no such query file", query_id=None) from None
    if path.is_dir():
        raise QueryError(f"{path}: is a folder, not a query file", query_id=None)
    if size > MAX_QUERY_FILE_BYTES:
        raise QueryError(f"{path}: {size:,} bytes is more than a query file may hold ({MAX_QUERY_FILE_BYTES:,})",
                         query_id=None)
    try:
        text = path.read_text(encoding="utf-8-sig")  # a UTF-8 byte-order mark is accepted, as config files do
    except UnicodeDecodeError as exc:
        raise QueryError(f"{path}: not a UTF-8 text file (byte {exc.start}: {exc.reason}); save the query file as "
                         f"UTF-8", query_id=None) from None
    except OSError as exc:
        raise QueryError(f"{path}: cannot read the query file ({exc.strerror or exc})", query_id=None) from None
    if path.suffix.lower() in (".yaml", ".yml"):
        data = _parse_yaml(text, path)
    else:
        try:
            data = json_loads_unique(text)
        except json.JSONDecodeError as exc:
            raise QueryError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})",
                             query_id=None) from None
        except (ValueError, RecursionError) as exc:  # an integer of thousands of digits, nesting beyond the stack
            raise QueryError(f"{path}: cannot read the query file ({_reading_problem(exc)})", query_id=None) from None
    return parse_queries(data, source=str(path))


def _parse_yaml(text: str, path: Path) -> Any:
    try:
        import yaml
    except ImportError:
        raise QueryError(f"{path}: reading a YAML query file needs PyYAML (pip install pyyaml); or give the same "
                         f"queries as JSON", query_id=None) from None
    merge_tag, error = "tag:yaml.org,2002:merge", yaml.constructor.ConstructorError

    class UniqueKeyLoader(yaml.SafeLoader):
        """A key written twice in one mapping is refused (which one is meant?). Merge keys are standard YAML
        (``<<: *base``, ``<<: {...}``, ``<<: [*a, *b]``): the merged keys are defaults, an explicit key overrides
        them, and of a list the earlier mapping wins (PyYAML's own flattening lets the later one win when the keys
        are distinct string objects)."""

        def flatten_mapping(self, node) -> None:  # noqa: ANN001 - a yaml MappingNode
            explicit, merged, merges = [], [], 0
            for key_node, value_node in node.value:
                if key_node.tag != merge_tag:
                    if key_node.tag == "tag:yaml.org,2002:value":  # as PyYAML does
                        key_node.tag = "tag:yaml.org,2002:str"
                    explicit.append((key_node, value_node))
                    continue
                merges += 1
                if merges > 1:
                    raise error(None, None, "the merge key '<<' appears twice in one mapping (merge several "
                                "mappings with <<: [*a, *b])", key_node.start_mark)
                if isinstance(value_node, yaml.MappingNode):
                    subs = [value_node]
                elif isinstance(value_node, yaml.SequenceNode):
                    subs = value_node.value
                else:
                    raise error("while constructing a mapping", node.start_mark, f"expected a mapping or list of "
                                f"mappings for merging, but found {value_node.id}", value_node.start_mark)
                for sub in subs:
                    if not isinstance(sub, yaml.MappingNode):
                        raise error("while constructing a mapping", node.start_mark, f"expected a mapping for "
                                    f"merging, but found {sub.id}", sub.start_mark)
                    self.flatten_mapping(sub)  # its own duplicates refused, its merges resolved
                    merged.extend(sub.value)
            keys = [self.construct_object(k, deep=True) for k, _ in explicit]
            for k in keys:
                if keys.count(k) > 1:
                    raise error(None, None, f"the key {_shown(k)} appears twice in one mapping (which one is "
                                f"meant?)", node.start_mark)
            if merges:
                seen, defaults = list(keys), []
                for k, v in merged:  # an explicit key, or an earlier merged mapping's, wins
                    key = self.construct_object(k, deep=True)
                    if key not in seen:
                        seen.append(key)
                        defaults.append((k, v))
                node.value = defaults + explicit

    try:
        return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        what = exc.problem or exc.context or str(exc).splitlines()[0]
        raise QueryError(f"{path}: not valid YAML ({what}{where})", query_id=None) from None
    except yaml.YAMLError as exc:
        raise QueryError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})", query_id=None) from None
    except (ValueError, RecursionError) as exc:
        raise QueryError(f"{path}: cannot read the query file ({_reading_problem(exc)})", query_id=None) from None


def _reading_problem(exc: Exception) -> str:
    if isinstance(exc, RecursionError):
        return "nested too deeply: a query file is a list of flat queries"
    if "digits" in str(exc):
        return "a number of thousands of digits"
    return str(exc).splitlines()[0]


def parse_queries(data: Any, source: str = "<memory>") -> QuerySet:
    """Check the parsed file (``{"queries": [...]}``, or a bare list of queries) and build the queries."""
    if data is None:  # an empty (or comments-only) YAML file
        raise QueryError(f"{source}: the query file is empty (expected {{\"queries\": [...]}})", query_id=None)
    items = data.get("queries") if isinstance(data, Mapping) else data
    if isinstance(data, Mapping) and "queries" not in data:
        raise QueryError(f"{source}: no 'queries' list (expected {{\"queries\": [...]}})", query_id=None)
    if not isinstance(items, list):
        raise QueryError(f"{source}: 'queries' must be a list, got {type(items).__name__}", query_id=None)
    if not items:
        raise QueryError(f"{source}: the query list is empty", query_id=None)
    budget = [MAX_VALUES_PER_FILE]
    items = [_from_numpy(item, _Budget(source, n, item, budget)) for n, item in enumerate(items)]  # numpy values as
    # Python ones (hostile trial 25 W5), every value counted: YAML aliases expand (hostile trial 26 B1)
    queries: list[Query] = []
    seen: set[str] = set()
    from_yaml = source.lower().endswith((".yaml", ".yml"))
    named = "" if source == "<memory>" else f"{source}: "  # a file's errors name it (trial 24 W8)
    for n, item in enumerate(items):
        try:
            query = parse_query(item, n, from_yaml=from_yaml)
        except QueryError as exc:
            raise QueryError(f"{named}{exc}", query_id=exc.query_id, field=exc.field) from None
        if query.id in seen:
            raise QueryError(f"{named}query {query.id!r}: the id is used twice (ids name decisions: each must be "
                             f"unique)", query_id=query.id, field="id")
        seen.add(query.id)
        queries.append(query)
    return QuerySet(queries, source, [dict(i) for i in items])


_REQUIRED = {
    "clearance": ("points_m", "radius_m"),
    "collision": ("path_m", "footprint"),
    "grasp": ("roi_min_m", "roi_max_m"),
    "foothold": ("center_m", "radius_m", "max_slope_deg"),
    "explore": ("min_m", "max_m", "max_unknown_fraction"),
}
_OPTIONAL = {
    "clearance": ("unknown_is",),
    "collision": ("unknown_is",),
    "grasp": ("min_points", "max_normal_spread_deg"),
    "foothold": ("max_flatness_m", "min_points"),
    "explore": (),
}


def parse_query(item: Any, index: int = 0, *, from_yaml: bool = False) -> Query:
    """One query (a mapping) checked and built; ``index`` names it when it has no usable id; ``from_yaml``: it
    was read from a YAML file (an id YAML turned into a number, a date or a bool gets the hint to quote it)."""
    if not isinstance(item, Mapping):
        raise QueryError(f"query #{index + 1}: expected a mapping with id and kind, got {type(item).__name__}",
                         query_id=None)
    qid = item.get("id")
    if qid is not None and not isinstance(qid, str) and not isinstance(qid, (Mapping, list)):
        text = _yaml_text(qid) if from_yaml else json.dumps(str(qid))
        if len(text) > MAX_SHOWN_CHARS:
            hint = "in YAML quote it so it stays text" if from_yaml else "give it as a JSON string (in quotes)"
        else:
            hint = f"in YAML quote it (id: \"{text}\") so it stays text" if from_yaml else f"give it as a JSON string (\"id\": {text})"
        raise QueryError(f"query #{index + 1}: 'id' must be a non-empty string, got {_shown(qid)} "
                         f"({type(qid).__name__}); {hint}", query_id=None, field="id")
    if not isinstance(qid, str) or not qid.strip():
        raise QueryError(f"query #{index + 1}: 'id' must be a non-empty string, got {_shown(qid)}", query_id=None,
                         field="id")
    if any(ord(c) < 32 or ord(c) == 127 for c in qid):
        raise QueryError(f"query #{index + 1}: 'id' {_shown(qid)} holds a line break or control character; ids are "
                         f"one line of text (they name the query in every report line)", query_id=None, field="id")
    if qid != qid.strip():  # "c" and "c " would be two queries that every report line shows alike
        raise QueryError(f"query #{index + 1}: 'id' {_shown(qid)} begins or ends with white space; ids are compared "
                         f"exactly, so write it as {_shown(qid.strip())}", query_id=None, field="id")
    invisible = [c for c in qid if unicodedata.category(c) == "Cf"]
    if invisible:  # zero-width spaces, byte-order marks, right-to-left overrides: an id that prints like another
        raise QueryError(f"query #{index + 1}: 'id' {_shown(qid)} holds an invisible formatting character "
                         f"(U+{ord(invisible[0]):04X}); ids are compared exactly and every report line shows them, so "
                         f"write it without", query_id=None, field="id")
    if unicodedata.normalize("NFC", qid) != qid:  # "café" composed and decomposed print alike
        raise QueryError(f"query #{index + 1}: 'id' {_shown(qid)} is not in Unicode's composed form (NFC), so it "
                         f"prints like {_shown(unicodedata.normalize('NFC', qid))} but compares unequal; write it "
                         f"composed", query_id=None, field="id")
    kind = item.get("kind")
    if kind not in KINDS:
        raise QueryError(f"query {qid!r}: unknown kind {_shown(kind)} (kinds: {', '.join(KINDS)})", query_id=qid,
                         field="kind")
    allowed = {"id", "kind", *_REQUIRED[kind], *_OPTIONAL[kind]} | IGNORED_KEYS
    for key in item:
        if key not in allowed:
            raise QueryError(f"query {qid!r}: unknown field {_shown(key)} for a {kind} query (fields: "
                             f"{', '.join(sorted(allowed - IGNORED_KEYS - {'id', 'kind'}))})", query_id=qid, field=str(key))
    for key in _REQUIRED[kind]:
        if key not in item:
            raise QueryError(f"query {qid!r}: a {kind} query needs {key!r}", query_id=qid, field=key)
    return _BUILDERS[kind](qid, item)


MAX_SHOWN_CHARS = 60
"""A value echoed in an error line is shortened beyond this many characters (a 400-digit id is not read back)."""


def _shown(value: Any) -> str:
    """``repr(value)`` for an error line, shortened when long: an integer of hundreds of digits by its digit count,
    a long text or structure by its start and length."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10**18:
        try:
            digits = len(str(abs(value)))
        except ValueError:  # beyond Python's int-to-text limit
            digits = int(abs(value).bit_length() * math.log10(2)) + 1
        return f"an integer of {digits} digits"
    text = repr(value)
    if len(text) <= MAX_SHOWN_CHARS:
        return text
    size = f"{len(value):,} characters" if isinstance(value, str) else (
        f"{len(value):,} items" if isinstance(value, (Sequence, Mapping)) else f"{len(text):,} characters")
    return f"{text[:MAX_SHOWN_CHARS - 20]}... ({type(value).__name__} of {size})"


def _yaml_text(value: Any) -> str:
    """How the author probably wrote a scalar YAML turned into another type (yes -> True, 2024-01-02 -> a date)."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return str(value)


def _clearance(qid: str, item: Mapping) -> ClearanceQuery:
    points = _points(qid, item, "points_m", min_count=1)
    radius = _number(qid, item, "radius_m", lo=0.0, hi=MAX_LENGTH_M)
    return ClearanceQuery(qid, "clearance", points, radius, _policy(qid, item))


def _collision(qid: str, item: Mapping) -> CollisionQuery:
    path = _points(qid, item, "path_m", min_count=2)
    if not np.any(np.linalg.norm(np.diff(path, axis=0), axis=1) > 0):
        raise QueryError(f"query {qid!r}: path_m has length 0 (all its points coincide): a path needs two distinct "
                         f"points", query_id=qid, field="path_m")
    fp = item["footprint"]
    if not isinstance(fp, Mapping) or len(fp) != 1 or next(iter(fp)) not in ("box_m", "cylinder_m"):
        raise QueryError(f"query {qid!r}: footprint must be {{\"box_m\": [lx, ly, lz]}} or {{\"cylinder_m\": "
                         f"[radius, height]}}, got {_shown(fp)}", query_id=qid, field="footprint")
    key = next(iter(fp))
    size = _vector(qid, fp[key], f"footprint.{key}", 3 if key == "box_m" else 2)
    if np.any(size <= 0):
        raise QueryError(f"query {qid!r}: footprint.{key} must be positive lengths, got {size.tolist()}",
                         query_id=qid, field=f"footprint.{key}")
    if np.any(size > MAX_LENGTH_M):
        raise QueryError(f"query {qid!r}: footprint.{key} must be lengths <= {MAX_LENGTH_M:g} m, got "
                         f"{size.tolist()}", query_id=qid, field=f"footprint.{key}")
    return CollisionQuery(qid, "collision", path, "box" if key == "box_m" else "cylinder",
                          tuple(float(v) for v in size), _policy(qid, item))


def _grasp(qid: str, item: Mapping) -> GraspQuery:
    lo, hi = _box(qid, item, "roi_min_m", "roi_max_m")
    min_points = _integer(qid, item, "min_points", lo=3, hi=MAX_MIN_POINTS) if "min_points" in item else None
    spread = _number(qid, item, "max_normal_spread_deg", lo=0.0, hi=90.0) if "max_normal_spread_deg" in item else None
    return GraspQuery(qid, "grasp", lo, hi, min_points, spread)


def _foothold(qid: str, item: Mapping) -> FootholdQuery:
    center = _vector(qid, item["center_m"], "center_m", 3, bound=MAX_COORDINATE_M)
    radius = _number(qid, item, "radius_m", lo=0.0, hi=MAX_LENGTH_M, strict=True)
    slope = _number(qid, item, "max_slope_deg", lo=0.0, hi=90.0)
    flat = _number(qid, item, "max_flatness_m", lo=0.0, hi=MAX_LENGTH_M, strict=True) if "max_flatness_m" in item else None
    min_points = _integer(qid, item, "min_points", lo=3, hi=MAX_MIN_POINTS) if "min_points" in item else None
    return FootholdQuery(qid, "foothold", center, radius, slope, flat, min_points)


def _explore(qid: str, item: Mapping) -> ExploreQuery:
    lo, hi = _box(qid, item, "min_m", "max_m")
    frac = _number(qid, item, "max_unknown_fraction", lo=0.0, hi=1.0)
    return ExploreQuery(qid, "explore", lo, hi, frac)


_BUILDERS = {"clearance": _clearance, "collision": _collision, "grasp": _grasp, "foothold": _foothold,
             "explore": _explore}


# ------------------------------------------------------------------------------------------------ values
MAX_VALUES_PER_QUERY = 4 * MAX_POINTS_PER_QUERY + 100_000
"""a query holding more values (numbers, strings, lists and mappings, its ignored fields included) is refused: a
YAML file's aliases can name one list many times (431 bytes expand to 387M values), so the bytes do not bound it"""
MAX_VALUES_PER_FILE = 40_000_000
"""the values of all the queries of a file together (a 256 MB JSON file of coordinates holds about 25M)"""


class _Budget:
    """The values a query may still hold (:data:`MAX_VALUES_PER_QUERY`) and the file's (a one-item list, shared)."""

    def __init__(self, source: str, n: int, item: Any, file_left: list[int]):
        self.source, self.n, self.item, self.file_left = source, n, item, file_left
        self.left = MAX_VALUES_PER_QUERY

    def take(self) -> None:
        self.left -= 1
        self.file_left[0] -= 1
        if self.left >= 0 and self.file_left[0] >= 0:
            return
        qid = self.item.get("id") if isinstance(self.item, Mapping) else None
        name = f"query {qid!r}" if isinstance(qid, str) else f"query {self.n}"
        what = (f"{name} holds more than {MAX_VALUES_PER_QUERY:,} values" if self.left < 0
                else f"the queries up to {name} hold more than {MAX_VALUES_PER_FILE:,} values")
        named = "" if self.source == "<memory>" else f"{self.source}: "
        raise QueryError(f"{named}{what} (its fields, ignored ones included; YAML aliases expand to a copy each "
                         f"time they are named): split the file or remove the repeated aliases",
                         query_id=qid if isinstance(qid, str) else None)


def _from_numpy(value: Any, budget: _Budget | None = None) -> Any:
    """Queries made in code hold numpy values: an array becomes its nested list, a numpy scalar its Python value (a
    numpy bool a bool, a complex a complex: the checks below refuse them as numbers), in mappings and lists too.
    ``budget``: every value counted against it (a :class:`QueryError` past it)."""
    if budget is not None:
        budget.take()
    if isinstance(value, np.ndarray):
        if budget is not None:
            for _ in range(min(value.size, MAX_VALUES_PER_QUERY + 1)):
                budget.take()
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {k: _from_numpy(v, budget) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_from_numpy(v, budget) for v in value]
    return value


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _number(qid: str, item: Mapping, key: str, *, lo: float | None = None, hi: float | None = None,
            strict: bool = False) -> float:
    v = item[key]
    if not _is_number(v):
        hint = ""
        if isinstance(v, str):
            try:
                float(v)
                hint = (" (a number written as text: quoted, or in YAML 1.1 an exponent without a decimal point such "
                        "as 1e-1, which PyYAML reads as a string; write 0.1 or 1.0e-1)")
            except ValueError:
                pass
        raise QueryError(f"query {qid!r}: {key} must be a number, got {_shown(v)}{hint}", query_id=qid, field=key)
    v = _finite(qid, key, v)
    if lo is not None and (v < lo or (strict and v == lo)):
        what = "negative" if v < 0 <= lo else f"{'<=' if strict else 'below'} {lo:g}"
        raise QueryError(f"query {qid!r}: {key} must be {'>' if strict else '>='} {lo:g}, got {v:g} ({what})",
                         query_id=qid, field=key)
    if hi is not None and v > hi:
        raise QueryError(f"query {qid!r}: {key} must be <= {hi:g}, got {v:g}", query_id=qid, field=key)
    return v


def _finite(qid: str, key: str, v: int | float) -> float:
    """``v`` as a finite float, or a :class:`QueryError` naming the field (NaN, inf, or an integer too large for a
    float: hundreds of digits)."""
    try:
        out = float(v)
    except OverflowError:
        raise QueryError(f"query {qid!r}: {key} must be a finite number, got an integer of {len(str(abs(v)))} digits",
                         query_id=qid, field=key) from None
    if not math.isfinite(out):
        raise QueryError(f"query {qid!r}: {key} must be finite, got {out}", query_id=qid, field=key)
    return out


def _integer(qid: str, item: Mapping, key: str, *, lo: int, hi: int) -> int:
    v = item[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < lo or v > hi:
        raise QueryError(f"query {qid!r}: {key} must be a whole number from {lo} to {hi:,}, got {_shown(v)}",
                         query_id=qid, field=key)
    return int(v)


def _vector(qid: str, value: Any, key: str, n: int, *, bound: float | None = None) -> NDArray[np.float64]:
    """``n`` finite numbers; with ``bound``, each of magnitude at most ``bound`` (coordinates, m)."""
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != n or not all(_is_number(v) for v in value):
        raise QueryError(f"query {qid!r}: {key} must be {n} numbers, got {_shown(value)}", query_id=qid, field=key)
    out = np.array([_finite(qid, key, v) for v in value], dtype=np.float64)
    if bound is not None and np.any(np.abs(out) > bound):
        raise QueryError(f"query {qid!r}: {key} must be coordinates within {bound:g} m of the map's origin, got "
                         f"{out.tolist()} (a unit mistake?)", query_id=qid, field=key)
    return out


def _points(qid: str, item: Mapping, key: str, *, min_count: int) -> NDArray[np.float64]:
    value = item[key]
    if not isinstance(value, Sequence) or isinstance(value, str):
        raise QueryError(f"query {qid!r}: {key} must be a list of [x, y, z] points, got {type(value).__name__}",
                         query_id=qid, field=key)
    if len(value) < min_count:
        what = "a path needs at least two points" if min_count == 2 else "give at least one point"
        raise QueryError(f"query {qid!r}: {key} has {len(value)} point{'s' if len(value) != 1 else ''}: {what}",
                         query_id=qid, field=key)
    if len(value) > MAX_POINTS_PER_QUERY:
        raise QueryError(f"query {qid!r}: {key} has {len(value):,} points, more than {MAX_POINTS_PER_QUERY:,}",
                         query_id=qid, field=key)
    return np.stack([_vector(qid, p, f"{key}[{k}]", 3, bound=MAX_COORDINATE_M) for k, p in enumerate(value)])


def _box(qid: str, item: Mapping, lo_key: str, hi_key: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    lo = _vector(qid, item[lo_key], lo_key, 3, bound=MAX_COORDINATE_M)
    hi = _vector(qid, item[hi_key], hi_key, 3, bound=MAX_COORDINATE_M)
    if np.any(hi <= lo):
        raise QueryError(f"query {qid!r}: {hi_key} {hi.tolist()} must exceed {lo_key} {lo.tolist()} on every axis",
                         query_id=qid, field=hi_key)
    return lo, hi


def _policy(qid: str, item: Mapping) -> str | None:
    v = item.get("unknown_is")
    if v is None:
        return None
    if v not in UNKNOWN_POLICIES:
        raise QueryError(f"query {qid!r}: unknown_is must be one of {', '.join(UNKNOWN_POLICIES)}, got {_shown(v)}",
                         query_id=qid, field="unknown_is")
    return str(v)


def query_to_json(query: Query) -> dict:
    """A query as the file holds it (contract keys)."""
    out: dict[str, Any] = {"id": query.id, "kind": query.kind}
    if isinstance(query, ClearanceQuery):
        out.update(points_m=query.points_m.tolist(), radius_m=query.radius_m)
    elif isinstance(query, CollisionQuery):
        key = "box_m" if query.footprint == "box" else "cylinder_m"
        out.update(path_m=query.path_m.tolist(), footprint={key: list(query.size_m)})
    elif isinstance(query, GraspQuery):
        out.update(roi_min_m=query.roi_min_m.tolist(), roi_max_m=query.roi_max_m.tolist())
    elif isinstance(query, FootholdQuery):
        out.update(center_m=query.center_m.tolist(), radius_m=query.radius_m, max_slope_deg=query.max_slope_deg)
    elif isinstance(query, ExploreQuery):
        out.update(min_m=query.min_m.tolist(), max_m=query.max_m.tolist(), max_unknown_fraction=query.max_unknown_fraction)
    for key in ("unknown_is", "min_points", "max_normal_spread_deg", "max_flatness_m"):
        value = getattr(query, key, None)
        if value is not None:
            out[key] = value
    return out
