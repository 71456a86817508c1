"""``driftmap decide``: answer a file of action queries (clearance, collision, grasp, foothold, explore) on a store's
revision, and with ``--compare A,B`` or ``--against OTHER_STORE`` list the decisions that flipped
(docs/decisions.md)."""

from __future__ import annotations

import contextlib
import json
import logging
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from driftmap.cli.common import (
    app,
    bold,
    check_output,
    general_settings,
    console,
    open_store,
    progress_bar,
    refuse_existing,
    refuse_same_output,
    refuse_store_inputs,
    stage_ticker,
    warn_unmerged,
)

FIGURE = "decisions.png"


def _pair(text: str | None) -> tuple[int, int] | None:
    """``--compare A,B`` -> two revision ids (a usage error otherwise)."""
    if text is None:
        return None
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or not all(re.fullmatch(r"-?[0-9]+", p) for p in parts):  # ASCII digits only
        raise typer.BadParameter(f"expected two revision ids A,B, got {text!r}", param_hint="--compare")
    a, b = int(parts[0]), int(parts[1])
    if a < 0 or b < 0:
        raise typer.BadParameter(f"revision ids are >= 0, got {text!r}", param_hint="--compare")
    if a == b:
        raise typer.BadParameter(f"compares revision {a} with itself ({text!r}): name two revisions",
                                 param_hint="--compare")
    return a, b


@app.command()
def decide(
    store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")],
    queries: Annotated[Path, typer.Option("--queries", help="Query file (JSON, or YAML with PyYAML): {\"queries\": [{\"id\", \"kind\": clearance | collision | grasp | foothold | explore, ...}]} (docs/decisions.md).")],
    json_path: Annotated[Path, typer.Option("--json", help="Write the decisions here (JSON).")],
    revision: Annotated[int | None, typer.Option("--revision", min=0, help="Revision (default: the latest).")] = None,
    report: Annotated[Path | None, typer.Option("--report", help="Write the top-view figure of the decisions (decisions.png) to this folder.")] = None,
    compare_revisions: Annotated[str | None, typer.Option("--compare", metavar="A,B", help="Decide on revisions A and B of STORE (the layers updated from A to B, not rebuilt) and list the decisions that flipped; the JSON's decisions are B's.")] = None,
    against: Annotated[Path | None, typer.Option("--against", metavar="OTHER_STORE", help="Also decide on another store built from the same log (its latest revision, or --against-revision) and list the decisions that flipped from STORE to it.")] = None,
    against_revision: Annotated[int | None, typer.Option("--against-revision", min=0, help="The revision of --against (default: its latest).")] = None,
    same_log: Annotated[bool, typer.Option("--same-log", help="--against: the two stores hold the same log read from two places (a copied or moved log): skip the check that their frames were read from the same files.")] = False,
    diagnose: Annotated[bool, typer.Option("--diagnose", help="Run diagnose on each decided revision first: double walls in reach of a query bound its uncertainty and label it double_wall_nearby.")] = False,
    diagnosis: Annotated[Path | None, typer.Option("--diagnosis", help="The double walls from a diagnosis JSON (diagnose --json) of the decided revision, instead of --diagnose.")] = None,
    config: Annotated[Path | None, typer.Option("--config", help="Config file (JSON or TOML) whose [volume] table sets the volumetric layers and [decide] table the decisions' thresholds (driftmap config --show).")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --json file (and the report's figure).")] = False,
    threads: Annotated[int, typer.Option("--threads", min=1, help="Queries answered at once (default 1). The decisions are the same, bit for bit, with any count; 2 threads are faster than 1 but not twice as fast (each query's Python steps hold the GIL).")] = 1,
) -> None:
    """Decide what the map lets the robot do: clearance, collision, grasp, foothold and exploration queries, each
    with its margin, uncertainty, failure label, contributing frames, freshness and latency."""
    from driftmap.config import check_threads
    from driftmap.decisions.query_file import load_queries
    from driftmap.decisions.walls import double_walls_of

    threads = check_threads(threads, "--threads")
    pair = _pair(compare_revisions)
    if pair is not None and (revision is not None or against is not None):
        raise typer.BadParameter("--compare A,B names both revisions: give it without --revision and --against",
                                 param_hint="--compare")
    if same_log and against is None:
        raise typer.BadParameter("--same-log needs --against (it relaxes the check that the two stores share a log)",
                                 param_hint="--same-log")
    if against_revision is not None and against is None:
        raise typer.BadParameter("--against-revision needs --against", param_hint="--against-revision")
    if diagnose and diagnosis is not None:
        raise typer.BadParameter("give --diagnose or --diagnosis, not both", param_hint="--diagnosis")
    if diagnosis is not None and (pair is not None or against is not None):
        raise typer.BadParameter("--diagnosis holds one revision's double walls; with a comparison use --diagnose",
                                 param_hint="--diagnosis")
    inputs = [(queries, "--queries")] + [(p, f) for p, f in ((config, "--config"), (diagnosis, "--diagnosis")) if p]
    figure = None if report is None else report / FIGURE
    _refuse_same_input(inputs)
    outputs = [(json_path, "--json")] + ([(report, "--report"), (figure, "--report")] if report is not None else [])
    for store_dir in (store_path, against):
        if store_dir is not None:
            refuse_store_inputs(store_dir, outputs)
    refuse_same_output([(json_path, "--json"), *inputs] + ([(report, "--report"), (figure, "--report")] if figure else []),
                       folders=("--report",))
    check_output(json_path, "--json")
    check_output(report, "--report", folder=True)
    refuse_existing(json_path, "--json", overwrite)
    if figure is not None:
        refuse_existing(figure, "--report", overwrite)
    query_set = load_queries(queries)  # every query checked before the store is opened
    settings = general_settings(config, "decide")  # a config file's numbers must be written as numbers (check_written_types)
    if diagnosis is not None:
        _check_diagnosis_shape(diagnosis)
    volume, decide_config = settings.volume, settings.decide
    with open_store(store_path, reads_map=True) as store:
        revisions = list(pair) if pair else [store.head if revision is None else revision]
        with _naming_query_file(queries):
            _precheck(store, query_set, volume, revisions, decide_config)
        warn_unmerged(store, revisions)
        named = True if diagnosis is None else _check_diagnosis_frames(store, diagnosis)
        walls = None if diagnosis is None else double_walls_of(diagnosis, revisions[0])  # its revision checked first
        if not named:  # warned only for a diagnosis that is one (a malformed one is a single error line)
            logging.getLogger(__name__).warning(
                "%s: the diagnosis names no store (no store_uuid: an older diagnose wrote it): only its frames and "
                "stamps are checked against %s", diagnosis, store.path)
        with progress_bar() as progress, _naming_query_file(queries):
            tick = stage_ticker(progress, {"volume": "volumetric layers", "decide": "decisions"})
            result = _run(store, query_set, volume, revision, pair, against, against_revision, diagnose, walls, tick,
                          same_log, decide_config, threads)
    decisions, comparison, layers = result
    from driftmap.files import no_clobber

    with no_clobber(not overwrite):  # an output another process wrote meanwhile is not replaced (trial 25 W9)
        _write(json_path, decisions, comparison)
        if figure is not None:
            from driftmap.decisions.figure import write_figure

            write_figure(figure, decisions, layers, comparison)
    _render(decisions, comparison)
    console.print(bold("decisions: ", json_path))
    if figure is not None:
        console.print(bold("report: ", figure))


@contextlib.contextmanager
def _naming_query_file(queries: Path) -> Iterator[None]:
    """A query that cannot be answered on this map names the query file as well as the query (trial 24 W8)."""
    from driftmap.decisions.errors import QueryError

    try:
        yield
    except QueryError as exc:
        if exc.query_id is None or str(exc).startswith(f"{queries}:"):
            raise
        raise QueryError(f"{queries}: {exc}", query_id=exc.query_id, field=exc.field) from None


def _check_diagnosis_shape(diagnosis: Path) -> None:
    """--diagnosis is what diagnose --json writes: an object with a 'revision' id and a 'double_wall' object with
    its 'regions' list. Any other object ({}, a synthetic.json, a build_summary.json) would decide as if the map had
    no double wall: refused naming the file and what is missing. An unreadable file or a non-object is left to
    :func:`~driftmap.decisions.walls.double_walls_of`, which names it."""
    from driftmap.decisions.errors import QueryError

    try:
        data = json.loads(diagnosis.read_text(encoding="utf-8-sig"))
    except (OSError, ValueError, RecursionError):
        return
    if not isinstance(data, dict):
        return
    missing = [f"'{key}'" for key in ("revision", "double_wall") if key not in data]
    problems = [f"it has no {' and no '.join(missing)}"] if missing else []
    rev, block = data.get("revision"), data.get("double_wall")
    if "revision" in data and (isinstance(rev, bool) or not isinstance(rev, int) or rev < 0):
        problems.append(f"its 'revision' is {_brief(rev)}, not a revision id (a whole number >= 0)")
    if "double_wall" in data and not isinstance(block, dict):
        problems.append(f"its 'double_wall' is {_brief(block)}, not an object with 'regions'")
    elif isinstance(block, dict) and not isinstance(block.get("regions"), list):
        problems.append("its 'double_wall' has no 'regions' list")
    if problems:
        raise QueryError(f"{diagnosis}: not a diagnosis (diagnose --json writes an object with 'revision' and "
                         f"'double_wall'; {'; '.join(problems)})", query_id=None)


def _brief(value) -> str:
    """A JSON value for an error line: short ones as written, others by their type."""
    text = json.dumps(value)
    kinds = {dict: "an object", list: "a list", str: "a text", int: "a number", float: "a number"}
    return text if len(text) <= 30 else kinds.get(type(value), f"a {type(value).__name__}")


def _check_diagnosis_frames(store, diagnosis: Path) -> bool:
    """--diagnosis must be of this store: the store id it names (``store_uuid``; older diagnoses have none) is this
    store's, and every frame it lists is in the store with the same stamp (a diagnosis of another store, or of a
    store of other frames, would put its double walls in the wrong place; two logs of the same length can share
    every frame id and stamp, hostile trial 24 B3). A diagnosis without a store id (an older one) is checked by its
    frames alone: False is returned (the caller warns). True otherwise (a malformed file too: its reader names the
    problem)."""
    from driftmap.decisions.walls import diagnosis_mismatch
    from driftmap.errors import ConfigError

    reason, named = diagnosis_mismatch(diagnosis, store.ledger.frame_ids, store.ledger.stamps_ns, store.uuid)
    if reason is not None:
        raise ConfigError(f"{diagnosis}: --diagnosis is not of {store.path} (id {store.uuid}): {reason}; diagnose "
                          f"this store")
    return named


def _precheck(store, query_set, volume, revisions: list[int], decide_config=None) -> None:
    """Before any work: the revisions exist, no query lies far off the map and no sweep needs a runaway number of
    placements (a QueryError naming it)."""
    from driftmap.decisions.decide import check_in_box, check_sweeps, reach_of

    for rev in revisions:
        store.ledger.revision(rev)
        check_in_box(query_set, *reach_of(store, rev, volume))
    check_sweeps(query_set, store, volume, decide_config)


_INPUT_WHAT = {"--queries": "the queries", "--config": "the config", "--diagnosis": "the diagnosis"}


def _refuse_same_input(inputs: list[tuple[Path, str]]) -> None:
    """Two inputs naming one file (e.g. --diagnosis the query file): a one-line error saying what each should be."""
    import os

    from driftmap.errors import ConfigError

    seen: dict[Path, str] = {}
    for path, flag in inputs:
        key = Path(os.path.abspath(path)).resolve()
        if key in seen:
            first = seen[key]
            raise ConfigError(f"{path}: {flag} and {first} name the same file, but {_INPUT_WHAT.get(flag, flag)} and "
                              f"{_INPUT_WHAT.get(first, first)} are different files ({flag} {path})")
        seen[key] = flag


def _check_same_log(store, other, other_path: Path, same_log: bool = False, rev: int | None = None,
                    other_rev: int | None = None) -> None:
    """--against: the two stores must hold the same log -- frames in common (by id), each with the same stamp in
    both ledgers and, unless ``same_log``, read from the same file (the provenance both stores record; logs whose
    stamps start alike, as every default synthetic log does, differ there). Else a one-line error naming the first
    frame that differs."""
    import numpy as np

    from driftmap.errors import ConfigError

    ids_a, st_a = np.asarray(store.ledger.frame_ids), np.asarray(store.ledger.stamps_ns)
    ids_b, st_b = np.asarray(other.ledger.frame_ids), np.asarray(other.ledger.stamps_ns)
    if len(ids_a) and len(ids_b):  # (hostile trial 28 W3: --same-log over two sensors read 35 of 60 decisions flipped)
        fa, fb = store.frame(int(ids_a[0])), other.frame(int(ids_b[0]))
        if fa.sensor_kind is not fb.sensor_kind:
            raise ConfigError(f"--against {other_path}: the stores hold different sensors ({fa.sensor_kind.value} in "
                              f"{store.path}, {fb.sensor_kind.value} in {other_path}): their decisions differ by what "
                              f"each sensor sees, not by a pose; compare stores of one sensor")
    shared, ia, ib = np.intersect1d(ids_a, ids_b, assume_unique=True, return_indices=True)
    if len(shared) == 0:
        def span(ids) -> str:
            return f"frames {int(ids.min())}..{int(ids.max())}" if len(ids) else "no frames"

        raise ConfigError(f"--against {other_path}: the stores are not of the same log (no frame id in common: "
                          f"{store.path} has {span(ids_a)}, {other_path} {span(ids_b)})")
    differ = np.flatnonzero(st_a[ia] != st_b[ib])
    if len(differ):
        k = int(differ[0])
        raise ConfigError(f"--against {other_path}: the stores are not of the same log (frame {int(shared[k])} has "
                          f"stamp {int(st_a[ia[k]])} ns in {store.path} but {int(st_b[ib[k]])} ns in {other_path}; "
                          f"{len(differ)} of {len(shared)} shared frames differ)")
    if not same_log:
        _check_same_files(store, other, other_path, shared)
    import logging

    if len(shared) < max(len(ids_a), len(ids_b)):
        logging.getLogger(__name__).warning(
            "--against %s: the stores share %d frames, but %s holds %d and %s %d: decisions may differ because frames "
            "are missing, not only because poses moved", other_path, len(shared), store.path, len(ids_a), other_path,
            len(ids_b))
        return
    # the same frames stored, but the decided revisions may place fewer of them (a revision older than a resume or an
    # append, a rollback that left frames out: hostile trial 18 W5)
    placed_a = store.members(rev)
    placed_b = other.members(other_rev)
    both = np.intersect1d(placed_a, placed_b)
    if len(both) < max(len(placed_a), len(placed_b)):
        logging.getLogger(__name__).warning(
            "--against %s: the revisions decided place different frames (%d in both; revision %d of %s places %d, "
            "revision %d of %s %d): decisions may differ because frames are missing, not only because poses moved",
            other_path, len(both), store.head if rev is None else rev, store.path, len(placed_a),
            other.head if other_rev is None else other_rev, other_path, len(placed_b))


def _check_same_files(store, other, other_path: Path, shared) -> None:
    """--against without --same-log: every shared frame was read from the same file for both stores."""
    from driftmap.errors import ConfigError

    from driftmap.pipeline.merge import frame_origin

    def uri(s, fid: int) -> str | None:  # a merged store's frame: the file its session's store read it from
        provenance = s.frame_info(fid).get("provenance") or {}
        origin = frame_origin(provenance) if provenance.get("source_uri") else None
        return origin.source_uri if origin is not None else provenance.get("source_uri")

    for fid in shared.tolist():
        ua, ub = uri(store, fid), uri(other, fid)
        if ua is not None and ub is not None and ua != ub:
            raise ConfigError(f"--against {other_path}: the stores are not of the same log (frame {fid} was read from "
                              f"{ua} for {store.path} but from {ub} for {other_path}); if it is one log read from two "
                              f"places, pass --same-log")


def _run(store, query_set, volume, revision, pair, against, against_revision, diagnose, given_walls, tick,
         same_log=False, decide_config=None, threads=1):
    """The decision sets (one, or two and their comparison) and the layers of the last."""
    from driftmap.decisions import compare, decide, decide_revisions
    from driftmap.volume.layers import VolumeLayers

    def walls(s, rev):
        if not diagnose:
            return None
        from driftmap.diagnostics.diagnosis import diagnose_store

        return diagnose_store(s, rev)

    if pair is not None:
        (a, b), layers = decide_revisions(store, query_set, list(pair), volume, decide_config=decide_config,
                                          double_walls=[walls(store, pair[0]), walls(store, pair[1])], progress=tick,
                                          threads=threads)
        return b, compare(a, b), layers
    rev = store.head if revision is None else revision
    if against is not None:
        with open_store(against, reads_map=True) as other:
            other_rev = other.head if against_revision is None else against_revision
            if against_revision is not None and not 0 <= against_revision <= other.head:
                from driftmap.errors import StoreError

                raise StoreError(f"--against-revision {against_revision}: the --against store {against} has no "
                                 f"revision {against_revision} (its revisions are 0..{other.head})")
            other.ledger.revision(other_rev)
            if other_rev == rev and Path(other.path).resolve() == Path(store.path).resolve():  # trial 24 W6: as
                from driftmap.errors import ConfigError  # --compare A,A is refused (a copy elsewhere is another store)

                raise ConfigError(f"--against {against}: compares revision {rev} of {store.path} with itself (the "
                                  "same store): name another store, or another revision with --against-revision "
                                  "(or --compare A,B)")
            warn_unmerged(other, [other_rev])
            _check_same_log(store, other, against, same_log, rev, other_rev)
            a = decide(store, query_set, rev, volume, decide_config=decide_config, double_walls=walls(store, rev),
                       progress=tick, threads=threads)
            layers = VolumeLayers.from_store(other, other_rev, volume, progress=tick)
            b = decide(other, query_set, other_rev, volume, layers=layers, decide_config=decide_config,
                       double_walls=walls(other, other_rev),
                       progress=tick, threads=threads)
        return b, compare(a, b), layers
    layers = VolumeLayers.from_store(store, rev, volume, progress=tick)
    d = decide(store, query_set, rev, volume, layers=layers, decide_config=decide_config,
               double_walls=given_walls if given_walls is not None else walls(store, rev),
               progress=tick, threads=threads)
    return d, None, layers


def _write(path: Path, decisions, comparison) -> None:
    from driftmap.decisions.compare import output_json
    from driftmap.store.guards import atomic_output

    data = output_json(decisions, comparison)
    with atomic_output(path, "--json") as tmp:
        tmp.write_text(json.dumps(data, indent=1) + "\n")


def _render(decisions, comparison) -> None:
    table = Table(title=f"decisions on revision {decisions.representation.revision}")
    for col in ("kind", "decisions", "failures"):
        table.add_column(col)
    by_kind: dict[str, dict[str, int]] = {}
    failures: dict[str, int] = {}
    for d in decisions.decisions:
        counts = by_kind.setdefault(d.kind, {})
        counts[d.decision] = counts.get(d.decision, 0) + 1
        if d.failure_label is not None:
            failures[d.kind] = failures.get(d.kind, 0) + 1
    for kind, counts in by_kind.items():
        table.add_row(kind, ", ".join(f"{k} {v}" for k, v in sorted(counts.items())), str(failures.get(kind, 0)))
    console.print(table)
    if comparison is not None:
        a, b = comparison.a.representation, comparison.b.representation
        console.print(f"{len(comparison.flipped)} of {len(comparison.margin_deltas)} decisions flipped from revision "
                      f"{a.revision} of {a.store} to revision {b.revision} of {b.store}")
        for f in comparison.flipped[:20]:
            delta = "" if f.margin_delta is None else f", margin {f.margin_delta:+.3f}"
            console.print(f"  {f.id}: {f.before} -> {f.after}{delta} (evidence moved "
                          f"{100 * f.why['max_evidence_shift_m']:.1f} cm)")
