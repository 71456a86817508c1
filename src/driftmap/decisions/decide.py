"""The library entry point: :func:`decide` answers a query set on one revision of a store, for a navigation stack
as for ``driftmap decide``; :func:`decide_revisions` answers it on several revisions, updating the volumetric layers
from one to the next (only the frames that moved) instead of rebuilding them.

Every query is checked before the first is answered: its fields when the file is read
(:mod:`driftmap.decisions.query_file`), and here that its region reaches the map (the layers' grid) at all.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from driftmap import __version__
from driftmap.config import check_threads
from driftmap.decisions import space, surface
from driftmap.decisions.errors import QueryError
from driftmap.errors import ConfigError
from driftmap.decisions.evidence import DecisionContext
from driftmap.decisions.point_index import point_index
from driftmap.decisions.query_file import Query, QuerySet, load_queries, parse_queries
from driftmap.decisions.records import Decision, DecisionSet, Representation
from driftmap.decisions.settings import DecideConfig, for_sensor, settings_hash
from driftmap.decisions.voxel_normals import voxel_normals
from driftmap.decisions.walls import diagnosis_mismatch, double_walls_of
from driftmap.store.unmerged import unmerged_sessions
from driftmap.store.values import as_int
from driftmap.volume.grid import BLOCK_RESOLUTION

if TYPE_CHECKING:
    from driftmap.config import VolumeConfig
    from driftmap.store.frame_store import FrameStore
    from driftmap.volume.layers import VolumeLayers

logger = logging.getLogger(__name__)

ProgressCallback = Callable[[str, int, int | None], None]

DECIDERS: dict[str, Callable[[DecisionContext, Any], dict]] = {
    "clearance": space.clearance,
    "collision": space.collision,
    "explore": space.explore,
    "grasp": surface.grasp,
    "foothold": surface.foothold,
}
_REGION_FIELD = {"clearance": "points_m", "collision": "path_m", "grasp": "roi_min_m", "foothold": "center_m",
                 "explore": "min_m"}


def as_query_set(queries: QuerySet | Sequence[Query] | dict | str | Path) -> QuerySet:
    """A query set from a file path, a parsed file (dict), a list of queries or a query set."""
    if isinstance(queries, QuerySet):
        return queries
    if isinstance(queries, (str, Path)):
        return load_queries(queries)
    if isinstance(queries, dict):
        return parse_queries(queries)
    items = list(queries)
    if items and all(isinstance(q, Query) for q in items):
        return QuerySet(items)
    return parse_queries(items)


def check_on_map(queries: Iterable[Query], layers: VolumeLayers, decide_config: DecideConfig | None = None) -> None:
    """A query whose whole region lies outside the layers' grid (the map's bounds) is a :class:`QueryError`
    naming it: a unit or frame mistake, not a question about unknown space; so is one needing more work than
    :func:`check_work` allows at the layers' voxel size."""
    queries = list(queries)
    check_in_box(queries, layers.grid.min_m, layers.grid.max_m)
    check_work(queries, float(layers.grid.voxel_size_m), decide_config)


def reach_of(store: FrameStore, revision: int, config: VolumeConfig | None) -> tuple[np.ndarray, np.ndarray]:
    """A box holding the layers' grid, from the poses alone: every sensor origin of the revision grown by the
    max range and the grid's padding (the grid spans the frames' points cut to that range, plus the padding).
    Queries outside it are refused before the layers are built."""
    from driftmap.config import VolumeConfig
    from driftmap.volume.defaults import resolve_config

    cfg = resolve_config(store, config or VolumeConfig())
    if cfg.max_range_m is None:
        return np.full(3, -np.inf), np.full(3, np.inf)
    origins = np.asarray(store.poses(revision))[store.ledger.member_rows(revision), :3, 3]
    block = 2 * BLOCK_RESOLUTION * float(cfg.voxel_size_m)  # the grid's corners are rounded out to whole blocks
    grow = float(cfg.max_range_m) + cfg.padding_m + float(cfg.truncation_m or 0.0) + block
    return origins.min(axis=0) - grow, origins.max(axis=0) + grow


def check_sweeps(queries: Iterable[Query], store: FrameStore, config: VolumeConfig | None,
                 decide_config: DecideConfig | None = None) -> None:
    """Before the layers are built: no collision path needs more than :data:`space.MAX_PATH_SAMPLES` footprint
    placements at the sweep step (the layers' half voxel by default), and no clearance query's balls span more than
    :data:`space.MAX_BALL_COLUMNS` voxel columns: else a :class:`QueryError` naming it."""
    from driftmap.config import VolumeConfig
    from driftmap.decisions.query_file import ClearanceQuery, CollisionQuery
    from driftmap.volume.defaults import resolve_config

    queries = list(queries)
    if not any(isinstance(q, (ClearanceQuery, CollisionQuery)) for q in queries):
        return
    voxel_m = float(resolve_config(store, config or VolumeConfig()).voxel_size_m)
    check_work(queries, voxel_m, decide_config)


def check_work(queries: Iterable[Query], voxel_m: float, decide_config: DecideConfig | None = None) -> None:
    """:func:`check_sweeps` at a given voxel size (the layers' when they are built)."""
    from driftmap.decisions.query_file import ClearanceQuery, CollisionQuery

    step = (decide_config or DecideConfig()).sweep_step_m
    for q in queries:
        if isinstance(q, CollisionQuery):
            space.check_path_samples(q, space.sweep_step(q, step, voxel_m, warn=False))
        elif isinstance(q, ClearanceQuery):
            space.check_ball_columns(q, voxel_m)


def check_in_box(queries: Iterable[Query], lo_map: np.ndarray, hi_map: np.ndarray) -> None:
    """Each query's region must reach into the box ``lo_map .. hi_map``, and not reach far beyond it (more than the
    box's largest side: a unit or frame mistake, and work without bound): else a :class:`QueryError` naming it."""
    lo_map, hi_map = np.asarray(lo_map, dtype=np.float64), np.asarray(hi_map, dtype=np.float64)
    side = float(np.max(hi_map - lo_map))
    for q in queries:
        lo, hi = q.extent_m()
        field = "path_m" if q.kind == "collision" else _REGION_FIELD[q.kind]
        where = (f"its {q.kind} region {np.round(lo, 3).tolist()} .. {np.round(hi, 3).tolist()}",
                 f"the map ({np.round(lo_map, 3).tolist()} .. {np.round(hi_map, 3).tolist()}, field {field})")
        if np.any(hi < lo_map) or np.any(lo > hi_map):
            raise QueryError(f"query {q.id!r}: {where[0]} lies outside {where[1]}", query_id=q.id, field=field)
        if np.isfinite(side) and (np.any(lo < lo_map - side) or np.any(hi > hi_map + side)):
            raise QueryError(f"query {q.id!r}: {where[0]} reaches far outside {where[1]}: a unit or frame mistake?",
                             query_id=q.id, field=field)


def check_diagnosis_of(double_walls: Any, store: FrameStore) -> None:
    """Double walls given as a diagnosis (a Diagnosis, a ``diagnose --json`` file or dict) are this store's, as
    ``decide --diagnosis`` requires (:func:`~driftmap.decisions.walls.diagnosis_mismatch`): another store's put
    its walls elsewhere and dropped the ones in reach (hostile trial 25 B5). One without a store id is checked by its
    frames, with a warning. A bare list of regions names no store and is taken as given."""
    if double_walls is None or isinstance(double_walls, list | tuple):
        return
    reason, named = diagnosis_mismatch(double_walls, store.ledger.frame_ids, store.ledger.stamps_ns, store.uuid)
    what = str(double_walls) if isinstance(double_walls, (str, Path)) else "the diagnosis"
    if reason is not None:
        raise QueryError(f"{what}: double_walls is not of {store.path} (id {store.uuid}): {reason}; diagnose this "
                         f"store", query_id=None)
    if not named:
        logger.warning("%s: the diagnosis names no store (no store_uuid: an older diagnose wrote it): only its frames "
                       "and stamps are checked against %s", what, store.path)


def check_layers_of(layers: Any, store: FrameStore, revision: int) -> None:
    """Layers given to :func:`decide` are this store's, of this revision: another store's (its id, or frames it does
    not hold) gave plausible, wrong decisions (hostile trial 25 B4), as did a revision id alone."""
    from driftmap.volume.layers import VolumeLayers

    if not isinstance(layers, VolumeLayers):
        raise ConfigError(f"layers must be the VolumeLayers of the store (VolumeLayers.from_store), got "
                          f"{type(layers).__name__}")
    if layers.store_uuid is not None and layers.store_uuid != store.uuid:
        raise QueryError(f"the layers given are of another store (id {layers.store_uuid}), not of {store.path} (id "
                         f"{store.uuid})", query_id=None)
    # layers that name no store (made by hand) are judged by their frames; an id that matches says enough
    foreign = [] if layers.store_uuid is not None else sorted(set(layers.frame_hits) - {int(f) for f in store.frame_ids})
    if foreign:
        raise QueryError(f"the layers given integrate frames {store.path} does not hold ({foreign[:5]}"
                         f"{' ...' if len(foreign) > 5 else ''}): another store's layers", query_id=None)
    if layers.revision != revision:
        raise QueryError(f"the layers given are of revision {layers.revision}, not {revision}", query_id=None)


LAYER_BUDGET_SETTINGS = frozenset({"memory_budget_mb", "keep_frame_voxels"})
"""volume settings that bound how the layers are kept, not what they hold: not compared by :func:`check_config_of`"""


def check_config_of(layers: VolumeLayers, config: VolumeConfig | None) -> None:
    """``config`` given with ``layers``: every setting it sets must be the layers' (hostile trial 27 W3: a 0.1 m
    voxel in ``config`` was ignored for the layers' 0.02 m without a word); a :class:`ConfigError` naming them."""
    if config is None:
        return
    differ = [f"{k} {getattr(config, k)!r} (the layers: {getattr(layers.config, k)!r})"
              for k in sorted(config.model_fields_set - LAYER_BUDGET_SETTINGS)
              if getattr(config, k) is not None and getattr(config, k) != getattr(layers.config, k)]
    if differ:
        raise ConfigError(f"config sets {', '.join(differ)}, which the layers given were not built with: give layers "
                          f"built with this config (VolumeLayers.from_store(store, revision, config)), or no config")


def decide(store: FrameStore, queries: QuerySet | Sequence[Query] | dict | str | Path, revision: int | None = None,
           config: VolumeConfig | None = None, *, decide_config: DecideConfig | None = None,
           layers: VolumeLayers | None = None, double_walls: Any = None,
           progress: ProgressCallback | None = None, threads: int = 1) -> DecisionSet:
    """Answer every query on ``revision`` (default: the head) of ``store``.

    ``config``: the volumetric settings (defaults follow the sensor); ``layers``: layers of that revision already
    built (else they are built here, which is most of the time of a first call); ``double_walls``: a
    :class:`~driftmap.diagnostics.diagnosis.Diagnosis` of the revision, the JSON ``diagnose --json`` wrote (path
    or dict) or a list of regions -- the double walls in reach of each query then label and bound it;
    ``threads``: queries answered at once (1 up to :func:`~driftmap.config.max_threads`); the decisions are the
    same, bit for bit, with any count. The compiled query kernels release the GIL, but each query's Python steps
    hold it, so 2 threads are not twice as fast as 1 (docs/decisions.md, "Speed").
    """
    threads = check_threads(threads, "threads")
    qs = as_query_set(queries)
    rev = store.head if revision is None else as_int(revision, "revision")
    store.ledger.revision(rev)  # an unknown revision: a StoreError naming it, before any work
    check_diagnosis_of(double_walls, store)
    walls = double_walls_of(double_walls, rev)
    t0 = time.perf_counter()
    if layers is None:
        check_in_box(qs, *reach_of(store, rev, config))
        check_sweeps(qs, store, config, decide_config)
        from driftmap.volume.layers import VolumeLayers

        layers = VolumeLayers.from_store(store, rev, config, progress=progress)
    else:
        check_layers_of(layers, store, rev)
        check_config_of(layers, config)
    layers_s = time.perf_counter() - t0
    check_on_map(qs, layers, decide_config)
    return _decide_on(store, qs, layers, decide_config or DecideConfig(), walls, progress, layers_s, threads)


def decide_revisions(store: FrameStore, queries: QuerySet | Sequence[Query] | dict | str | Path,
                     revisions: Sequence[int], config: VolumeConfig | None = None, *,
                     decide_config: DecideConfig | None = None, double_walls: Sequence[Any] | None = None,
                     progress: ProgressCallback | None = None,
                     threads: int = 1) -> tuple[list[DecisionSet], VolumeLayers]:
    """:func:`decide` on each revision in turn; the layers are built once and then updated to the next revision
    (:meth:`~driftmap.volume.layers.VolumeLayers.apply`: only the frames that moved). Returns the decision sets
    and the layers (of the last revision)."""
    from driftmap.volume.layers import VolumeLayers

    threads = check_threads(threads, "threads")
    qs = as_query_set(queries)
    revisions = [as_int(r, "revisions") for r in revisions]
    if not revisions:
        raise QueryError("decide_revisions: no revision given (revisions is empty)", query_id=None)
    for r in revisions:
        store.ledger.revision(int(r))
        check_in_box(qs, *reach_of(store, int(r), config))
    check_sweeps(qs, store, config, decide_config)
    walls = list(double_walls) if double_walls is not None else [None] * len(revisions)
    if len(walls) != len(revisions):
        raise QueryError(f"double_walls: {len(walls)} entries for {len(revisions)} revisions (one per revision, None "
                         f"for none)", query_id=None)
    for w in walls:
        check_diagnosis_of(w, store)
    walls = [double_walls_of(w, int(r)) for w, r in zip(walls, revisions)]
    out: list[DecisionSet] = []
    layers = None
    for n, rev in enumerate(revisions):
        t0 = time.perf_counter()
        if layers is None:
            layers = VolumeLayers.from_store(store, int(rev), config, progress=progress)
            check_on_map(qs, layers, decide_config)
        else:
            layers.apply(int(rev), store)
        out.append(_decide_on(store, qs, layers, decide_config or DecideConfig(), walls[n], progress,
                              time.perf_counter() - t0, threads))
    assert layers is not None
    return out, layers


def _answer(ctx: DecisionContext, q: Query) -> Decision:
    t = time.perf_counter()
    fields = DECIDERS[q.kind](ctx, q)
    return Decision(q.id, q.kind, latency_s=time.perf_counter() - t, **fields)


def _answer_all(ctx: DecisionContext, qs: QuerySet, threads: int, tick: ProgressCallback) -> list[Decision]:
    """The decisions of ``qs`` in order, ``threads`` queries at a time. Each query reads only what :func:`prepare`
    and :meth:`DecisionContext.prepare_shared` built beforehand (and memos whose value does not depend on who
    computes it first), so the order in which the threads finish changes nothing."""
    queries = list(qs)
    pool = None
    if threads == 1 or len(queries) < 2:
        answers: Iterable[Decision] = (_answer(ctx, q) for q in queries)
    else:
        ctx.prepare_shared()
        pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="driftmap-decide")
        answers = (f.result() for f in [pool.submit(_answer, ctx, q) for q in queries])  # an error raised here
    try:
        decisions = []
        for n, decision in enumerate(answers):
            decisions.append(decision)
            tick("decide", n + 1, len(queries))
        return decisions
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


def _decide_on(store: FrameStore, qs: QuerySet, layers: VolumeLayers, cfg: DecideConfig, walls: list,
               progress: ProgressCallback | None, layers_s: float, threads: int = 1) -> DecisionSet:
    tick = progress or (lambda stage, done, total: None)
    cfg = for_sensor(cfg, layers.sensor_kind, float(layers.grid.voxel_size_m))  # LiDAR: lengths at its scale
    ctx = DecisionContext(store, layers.revision, layers, cfg, walls)
    t_all = time.perf_counter()
    prepare(layers, cfg, kinds=[q.kind for q in qs])
    prepare_s = time.perf_counter() - t_all
    decisions = _answer_all(ctx, qs, threads, tick)
    rev = layers.revision
    unmerged = unmerged_sessions(store, rev)
    if unmerged is not None:  # the map lays those sessions over session 0's misaligned: a decision on them is not one
        logger.warning("%s: %s", store.path, unmerged)
        for d in decisions:
            if d.failure_label is None and unmerged.frame_mask(np.asarray(d.frames, dtype=np.int64)).any():
                d.failure_label = "sessions_not_merged"
    representation = Representation(
        store=str(store.path), revision=int(rev), settings_hash=settings_hash(layers.config, cfg),
        driftmap_version=__version__, store_uuid=_store_uuid(store), n_frames=len(store),
        settings={"volume": layers.config.model_dump(mode="json"), "decide": cfg.model_dump(mode="json")},
        query_file=None if qs.source == "<memory>" else qs.source,
        sessions_not_merged=[] if unmerged is None else list(unmerged.sessions),
        warnings=[] if unmerged is None else [str(unmerged)])
    placed = store.ledger.member_rows(rev)  # the frames the revision places
    return DecisionSet(representation, decisions, qs, np.asarray(store.frame_ids, dtype=np.int64)[placed],
                       np.asarray(store.poses(rev))[placed], walls,
                       {"layers": layers_s, "prepare": prepare_s, "decide": time.perf_counter() - t_all - prepare_s})


SHARED_NORMALS_MIN_QUERIES = 50
"""A run with at least this many grasp and foothold queries fits the map's voxel normals once (3-9 s for the benchmark
map) and lets each region take them; fewer fit their own (milliseconds each): a run of one grasp stays fast."""


def prepare(layers: VolumeLayers, decide_config: DecideConfig | None = None,
            kinds: Iterable[str] | None = None) -> None:
    """Build what every query reads once (the surface KD-tree, the per-column unknown counts, the map points sorted
    by cell, and the map's voxel normals when ``kinds`` -- the run's queries' kinds, one per query; default: many of
    every kind -- hold at least :data:`SHARED_NORMALS_MIN_QUERIES` grasps and footholds; cached on the layers until
    they change), so that a query's latency is its own."""
    from driftmap.volume.queries import surface_tree

    cfg = decide_config or DecideConfig()
    kinds = list(DECIDERS) * SHARED_NORMALS_MIN_QUERIES if kinds is None else list(kinds)
    surface_tree(layers)
    space.unknown_sat(layers)
    space.surface_reach(layers)
    layers.observers(np.zeros((1, 3)))  # the sorted (voxel, frame) index the provenance lookups search
    point_index(layers, cfg.range_limited_points)
    if sum(k in ("grasp", "foothold") for k in kinds) >= SHARED_NORMALS_MIN_QUERIES:
        voxel_normals(layers, cfg)


def _store_uuid(store: FrameStore) -> str | None:
    from driftmap.store.manifest import read_manifest

    try:
        return str(read_manifest(Path(store.path))["store_uuid"])
    except Exception:  # noqa: BLE001 - the id is a label; a store that opened has one, a damaged manifest gives none
        return None
