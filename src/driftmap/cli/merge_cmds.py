"""``driftmap merge``: sessions of one place (stores) into one merged store (docs/merge.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table
from rich.text import Text

from driftmap.cli.common import app, bold, console, err_console, progress_bar, stage_ticker


@app.command()
def merge(
    stores: Annotated[list[Path], typer.Argument(metavar="STORE_A STORE_B [STORE_C ...]", help="Stores of the same place, one per session; session 0 (the first) keeps its frame. With --append: the merged store first, then the new sessions' stores.")],
    out: Annotated[Optional[Path], typer.Option("--out", help="The merged store to create (a new folder; the sources are never modified).")] = None,
    append: Annotated[bool, typer.Option("--append", help="Append the sessions of the stores after the first to the merged store given first, in place: their frames and one new revision (the older revisions are kept; rollback undoes it). The new stores are never modified.")] = False,
    config: Annotated[Optional[Path], typer.Option("--config", help="Config file (JSON or TOML) whose [build] table sets the loop-closure and pose-graph settings (as for build; an append takes the merge's recorded loop-closure settings).")] = None,
) -> None:
    """Merge sessions of one place: loops between sessions from the place descriptors, one pose graph, a new store
    holding every connected session's frames with the merged poses as a revision. With --append, new sessions are
    added to an existing merged store (MERGED NEW [NEW ...] --append)."""
    from driftmap.pipeline.build import BuildConfig

    if append and out is not None:  # usage errors (exit 2), as a missing --out always was
        raise typer.BadParameter(f"--append and --out {out}: choose one (--append adds the stores after {stores[0]} "
                                 f"to that merged store in place; --out writes a new merged store)",
                                 param_hint="--out")
    if not append and out is None:
        raise typer.BadParameter("merge needs --out OUT (a new merged store), or --append to add sessions to the "
                                 "merged store given first", param_hint="--out")
    cfg = BuildConfig.load(config)
    if config is not None:
        from driftmap.config import refuse_unread_tables

        refuse_unread_tables(config, "merge")
    if append:
        _append(stores, cfg)
        return
    assert out is not None
    from driftmap.pipeline.merge import merge_stores

    with progress_bar() as progress:
        tick = stage_ticker(progress)

        result = merge_stores(stores, out, config=cfg, progress=tick)

    _print_sessions_and_loops(result, f"driftmap merge -> {out}", "loops between sessions")
    rows = [
        ("frames in the merged store", str(result.n_frames)),
        ("merge revision", "-" if result.revision_id is None else str(result.revision_id)),
        ("graph error before / after", "-" if result.graph_error_before is None else f"{result.graph_error_before:.4g} / {result.graph_error_after:.4g}"),
        ("loops rejected by the graph", str(result.loops_rejected_by_graph)),
        ("largest move of a session-0 frame", "-" if result.max_session0_shift_m is None else f"{result.max_session0_shift_m:.3f} m"),
    ]
    rows += [(f"time: {k}", f"{v:.2f} s") for k, v in result.seconds_per_stage.items()]
    summary = Table(title="merge")
    summary.add_column("quantity")
    summary.add_column("value", justify="right")
    for k, v in rows:
        summary.add_row(k, v)
    console.print(summary)
    for s in result.sessions:
        if not s.connected:
            err_console.print(Text.assemble(("not connected:", "yellow"), f" session {s.session} ({s.store}): {s.reason}"),
                              highlight=False)
    console.print(bold("store: ", Path(result.out).resolve(), " (merge_summary.json saved in it)"))


def _append(stores: list[Path], cfg: object) -> None:
    from driftmap.errors import ConfigError
    from driftmap.pipeline.merge_append import append_sessions

    if len(stores) < 2:
        raise ConfigError(f"--append: give the merged store and at least one new store (got {len(stores)} store)")
    with progress_bar() as progress:
        result = append_sessions(stores[0], stores[1:], config=cfg, progress=stage_ticker(progress))  # type: ignore[arg-type]
    _print_sessions_and_loops(result, f"driftmap merge --append -> {stores[0]}", "loops of the new sessions")
    rows = [
        ("frames appended / in the store", f"{result.n_frames_appended} / {result.n_frames}"),
        ("revision (previous head)", f"{result.revision_id} ({result.previous_head})"),
        ("existing frames moved / kept", f"{result.existing_moved} / {result.existing_kept}"),
        ("largest move of an existing frame", "-" if result.max_existing_shift_m is None else f"{result.max_existing_shift_m:.4f} m"),
        ("loops: new / recorded reused / verified again", f"{result.loops_new} / {result.loops_reused} / {result.loops_reverified}"),
        ("graph error before / after", "-" if result.graph_error_before is None else f"{result.graph_error_before:.4g} / {result.graph_error_after:.4g}"),
        ("loops rejected by the graph", str(result.loops_rejected_by_graph)),
    ]
    rows += [(f"time: {k}", f"{v:.2f} s") for k, v in result.seconds_per_stage.items()]
    summary = Table(title="append")
    summary.add_column("quantity")
    summary.add_column("value", justify="right")
    for k, v in rows:
        summary.add_row(k, v)
    console.print(summary)
    for s in result.sessions:
        if not s.connected:
            err_console.print(Text.assemble(("not connected:", "yellow"), f" session {s.session} ({s.store}): {s.reason}"
                                            " (nothing of it was appended)"), highlight=False)
    console.print(bold("store: ", Path(result.store), f" (revision {result.revision_id}; merge_summary.json updated)"))


def _print_sessions_and_loops(result, title: str, loops_title: str) -> None:  # noqa: ANN001 - MergeResult | AppendResult
    """The sessions table (one row per session of ``result``) and the loops between sessions."""
    sessions = Table(title=title)
    for col in ("session", "store", "frames", "keyframes", "head revision", "connected", "frame ids"):
        sessions.add_column(col, justify="left" if col in ("store", "connected") else "right")
    for s in result.sessions:
        sessions.add_row(str(s.session), s.store, str(s.n_frames), str(s.n_keyframes),
                         f"{s.head_revision} ({s.head_source})", "yes" if s.connected else "NO",
                         f"{s.frame_id_offset}+" if s.connected else "-")
    console.print(sessions)
    loops = Table(title=loops_title)
    for col in ("sessions", "tried", "verified", "accepted", "in the other's free space", "connected"):
        loops.add_column(col, justify="right")
    for p in result.pairs:
        conflict = p.get("free_space_conflict")
        loops.add_row(f"{p['session_a']}-{p['session_b']}", str(p["tried"]), str(p["verified"]), str(p["accepted"]),
                      "-" if conflict is None else f"{100 * conflict:.1f} %", "yes" if p["connected"] else "no")
    console.print(loops)
