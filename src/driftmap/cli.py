"""The ``driftmap`` command line (typer + rich).

Only this module prints and exits: library errors (:class:`DriftmapError`) become one red line and exit
code 1; ``--debug`` shows the traceback and debug logs.
"""

from __future__ import annotations

import json
import logging
import os
import sys
from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from driftmap import __version__
from driftmap.errors import DriftmapError

app = typer.Typer(
    name="driftmap",
    help="Multi-frame fusion and drift-aware mapping: frames kept with the poses that produced them.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
# piped output (logs, other tools) gets wide tables instead of rich's 80-column default
_PIPE_WIDTH = None if sys.stdout.isatty() else int(os.environ.get("COLUMNS", "160"))
console = Console(width=_PIPE_WIDTH)
err_console = Console(stderr=True)

_state = {"debug": False}


def _version_callback(value: bool) -> None:
    if value:
        console.print(f"driftmap {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        Optional[bool], typer.Option("--version", callback=_version_callback, is_eager=True, help="Print the version and exit.")
    ] = None,
    debug: Annotated[bool, typer.Option("--debug", help="Debug logging and full tracebacks on errors.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Info-level logging.")] = False,
) -> None:
    _state["debug"] = debug
    level = logging.DEBUG if debug else logging.INFO if verbose else logging.WARNING
    logging.basicConfig(level=level, format="%(name)s: %(message)s", handlers=[RichHandler(console=err_console, show_path=False)])


def _progress() -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        console=err_console, transient=False,
    )


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", help="Results folder (created).")] = Path("results/demo"),
    frames: Annotated[Optional[int], typer.Option("--frames", min=2, help="Use only the first N frames.")] = None,
    log: Annotated[Optional[Path], typer.Option("--log", help="Another synthetic log folder instead of the embedded one.")] = None,
) -> None:
    """Run the whole story on the embedded synthetic drifting-robot log."""
    from driftmap.demo import run_demo

    with _progress() as progress:
        task = progress.add_task("back-project + validate", total=None)

        def tick(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        result = run_demo(out, log_path=log, max_frames=frames, progress=tick)
    table = Table(title="driftmap demo: synthetic loop, drifting odometry vs ground truth")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    table.add_row("frames", str(result.n_frames))
    table.add_row("points (sensor frames)", f"{result.n_points:,}")
    table.add_row("mean invalid-pixel fraction", f"{result.mean_invalid_fraction:.3f}")
    table.add_row("frames flagged (invalid-pixel jump)", str(len(result.flagged_frames)))
    table.add_row("loop wall spread, odometry (median / max)",
                  f"{result.wall_spread_odometry_m * 100:.1f} / {result.wall_spread_odometry_max_m * 100:.1f} cm")
    if result.wall_spread_corrected_m is not None:
        table.add_row("loop wall spread, after loop closure (median / max)",
                      f"{result.wall_spread_corrected_m * 100:.1f} / {result.wall_spread_corrected_max_m * 100:.1f} cm")
    table.add_row("loop wall spread, ground truth (median / max)",
                  f"{result.wall_spread_ground_truth_m * 100:.1f} / {result.wall_spread_ground_truth_max_m * 100:.1f} cm")
    table.add_row("loops accepted", str(result.loops_accepted))
    if result.ate_odometry_m is not None:
        after = "-" if result.ate_corrected_m is None else f"{result.ate_corrected_m * 100:.1f}"
        table.add_row("ATE odometry -> after loop closure", f"{result.ate_odometry_m * 100:.1f} -> {after} cm")
    table.add_row("time", f"{result.seconds:.1f} s")
    console.print(table)
    for name, path in result.files.items():
        console.print(f"  {name:22s} {path}")
    console.print(f"results: [bold]{result.out_dir}[/bold]")


@app.command("synth")
def synth(
    out: Annotated[Path, typer.Argument(help="Folder to write the synthetic log to.")],
    frames: Annotated[int, typer.Option("--frames", min=2, help="Number of frames.")] = 60,
    seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 7,
    lidar: Annotated[bool, typer.Option("--lidar/--no-lidar", help="Also simulate a 16-beam spinning LiDAR.")] = False,
    yaw_drift_deg_per_m: Annotated[float, typer.Option("--yaw-drift-deg-per-m", help="Odometry yaw drift.")] = 0.6,
    scale_drift_percent: Annotated[float, typer.Option("--scale-drift-percent", help="Odometry scale drift.")] = 1.0,
) -> None:
    """Generate a synthetic drifting-robot log (deterministic for a given seed)."""
    from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log

    cfg = SyntheticLogConfig(seed=seed, n_frames=frames, lidar=lidar, yaw_drift_deg_per_m=yaw_drift_deg_per_m,
                             scale_drift_percent=scale_drift_percent)
    with console.status("ray-casting the synthetic room"):
        path = generate_synthetic_log(out, cfg)
    console.print(f"synthetic log: [bold]{path.resolve()}[/bold]")


# ------------------------------------------------------------------------------------------ sources / build


@app.command()
def convert(
    source: Annotated[Path, typer.Argument(help="Data-set folder or log to convert.")],
    out: Annotated[Path, typer.Argument(metavar="OUT.mcap", help="MCAP file to write (ROS 2 messages).")],
    format: Annotated[Optional[str], typer.Option("--format", help="Source format (default: detected).")] = None,
    frames: Annotated[Optional[str], typer.Option("--frames", help="START:STOP[:STEP] of the source's frames.")] = None,
) -> None:
    """Convert any source to an MCAP log (ROS 2 PointCloud2 / CameraInfo / TF) that Foxglove opens."""
    from driftmap.sources.mcap_export import convert as convert_source

    with console.status(f"converting {source}"):
        summary = convert_source(source, out, format=format, frames=frames)
    console.print(f"wrote {out}: " + ", ".join(f"{k} {v}" for k, v in summary.items() if not isinstance(v, (dict, list))))


def _load_build_config(path: Optional[Path]):
    import tomllib

    from driftmap.pipeline.build import BuildConfig

    if path is None:
        return BuildConfig()
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
        return BuildConfig(**data)
    except (OSError, ValueError) as exc:
        from driftmap.errors import ConfigError

        raise ConfigError(f"{path}: invalid build config ({exc})") from exc


@app.command()
def build(
    source: Annotated[Path, typer.Argument(help="Data-set folder or log.")],
    out: Annotated[Path, typer.Option("--out", help="Store directory to create (or continue with --resume).")],
    format: Annotated[Optional[str], typer.Option("--format", help="Source format (default: detected).")] = None,
    config: Annotated[Optional[Path], typer.Option("--config", help="Build config (JSON or TOML).")] = None,
    poses: Annotated[Optional[Path], typer.Option("--poses", help="Use these poses (TUM by stamp; KITTI row = frame_id).")] = None,
    poses_from_source: Annotated[bool, typer.Option("--poses-from-source", help="Use the source's own poses (log odometry or ground truth).")] = False,
    no_loop_closure: Annotated[bool, typer.Option("--no-loop-closure", help="Skip loop closure and the pose graph.")] = False,
    frames: Annotated[Optional[str], typer.Option("--frames", help="START:STOP[:STEP] of the source's frames.")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue a build that was interrupted.")] = False,
) -> None:
    """Build a drift-corrected map: odometry, verified loop closures, GTSAM pose graph, re-transform."""
    from driftmap.pipeline.build import build as run_build

    cfg = _load_build_config(config)
    with _progress() as progress:
        tasks: dict[str, int] = {}

        def tick(stage: str, done: int, total: int | None) -> None:
            if stage not in tasks:
                tasks[stage] = progress.add_task(stage, total=total)
            progress.update(tasks[stage], completed=done, total=total)

        result = run_build(source, out, format=format, config=cfg, poses_file=poses, poses_from_source=poses_from_source,
                           loop_closure=not no_loop_closure, frames=frames, resume=resume, progress=tick)
    table = Table(title=f"driftmap build: {source} -> {out}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    rows = [
        ("frames (new / in store)", f"{result.n_frames_new} / {result.n_frames}"),
        ("mean invalid-pixel fraction", "-" if result.mean_invalid_fraction is None else f"{result.mean_invalid_fraction:.3f}"),
        ("poses", result.pose_source),
        ("odometry fps", "-" if result.odometry_fps is None else f"{result.odometry_fps:.1f}"),
        ("keyframes", str(result.n_keyframes)),
        ("loops tried / accepted / rejected by graph", f"{result.loops_tried} / {result.loops_accepted} / {result.loops_rejected_by_graph}"),
        ("graph error before / after", "-" if result.graph_error_before is None else f"{result.graph_error_before:.4g} / {result.graph_error_after:.4g}"),
        ("loop-closure revision", "-" if result.loop_revision is None else str(result.loop_revision)),
        ("max correction", "-" if result.max_correction_m is None else f"{result.max_correction_m:.3f} m / {result.max_correction_deg:.2f} deg"),
        ("throughput", f"{result.frames_per_second:.1f} frames/s"),
    ]
    rows += [(f"time: {k}", f"{v:.2f} s") for k, v in result.seconds_per_stage.items()]
    for k, v in rows:
        table.add_row(k, v)
    console.print(table)
    console.print(f"store: [bold]{Path(result.store).resolve()}[/bold] (config and summary saved beside it)")


# ------------------------------------------------------------------------------------------ store / ledger


def _open_store(path: Path, mode: str = "r"):
    from driftmap.store.frame_store import FrameStore

    store = FrameStore.open(path, mode)
    for event in store.recovery_events:
        err_console.print(f"[yellow]recovered:[/yellow] {event}", highlight=False)
    return store


@app.command()
def correct(
    store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")],
    poses: Annotated[Path, typer.Option("--poses", help="Pose file (T_world_sensor per frame).")],
    format: Annotated[str, typer.Option("--format", help="tum | kitti")] = "tum",
    match: Annotated[Optional[str], typer.Option("--match", help="stamp | index (default: stamp for TUM, index for KITTI: row i = frame_id i)")] = None,
    source: Annotated[str, typer.Option("--source", help="Revision source: external_file, loop_closure, ground_truth, ...")] = "external_file",
    max_dt_ms: Annotated[float, typer.Option("--max-dt-ms", help="Stamp matching tolerance (ms).")] = 10.0,
    no_propagate: Annotated[bool, typer.Option("--no-propagate", help="Do not propagate to frames without a pose row.")] = False,
) -> None:
    """Import a pose file as a new revision (a correction); nothing is overwritten."""
    with _open_store(store_path, "a") as store:
        revision, matched = store.import_poses(poses, format=format, match=match, max_dt_ns=round(max_dt_ms * 1e6),
                                               source=source, propagate=not no_propagate)
        d = store.diff(revision.parent_id, revision.revision_id)
    console.print(f"revision {revision.revision_id} (parent {revision.parent_id}, source {revision.source.value}): "
                  f"{len(revision.set_directly)} frames set from {poses.name}, {len(revision.propagated)} propagated; "
                  f"max change {d.max_translation_m:.4f} m / {d.max_rotation_deg:.3f} deg")
    if matched.unmatched_rows:
        console.print(f"  {len(matched.unmatched_rows)} rows of {poses.name} matched no stored frame (ignored)")


@app.command()
def revisions(store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")]) -> None:
    """List the pose revisions: id, parent, source, frames changed, max displacement."""
    import datetime

    with _open_store(store_path) as store:
        table = Table(title=f"pose revisions of {store_path}")
        for col in ("id", "parent", "source", "created", "frames changed", "max displacement (m)", "max rotation (deg)", "note"):
            table.add_column(col, justify="right" if col not in ("source", "note", "created") else "left",
                             no_wrap=col != "note")
        for rev in store.revisions:
            if rev.parent_id is None:
                table.add_row(str(rev.revision_id), "-", rev.source.value, "-", str(len(store)), "-", "-", "poses that produced the frames")
                continue
            d = store.diff(rev.parent_id, rev.revision_id)
            changed = int(np.count_nonzero((d.translation_m > 0) | (d.rotation_deg > 0)))
            created = datetime.datetime.fromtimestamp(rev.created_ns / 1e9).isoformat(timespec="seconds")
            table.add_row(str(rev.revision_id), str(rev.parent_id), rev.source.value, created, str(changed),
                          f"{d.max_translation_m:.4f}", f"{d.max_rotation_deg:.3f}", rev.note)
        console.print(table)


@app.command()
def rollback(
    store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")],
    to: Annotated[int, typer.Option("--to", help="Revision to restore.")],
) -> None:
    """Create a new revision equal to revision N (history is kept)."""
    with _open_store(store_path, "a") as store:
        rev = store.rollback(to)
    console.print(f"revision {rev.revision_id}: poses of revision {to} restored ({len(rev.set_directly)} frames changed)")


@app.command()
def export(
    store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")],
    revision: Annotated[Optional[int], typer.Option("--revision", help="Revision (default: the latest).")] = None,
    map_path: Annotated[Optional[Path], typer.Option("--map", help="Write the map: OUT.ply or OUT.pcd.")] = None,
    voxel_size_m: Annotated[Optional[float], typer.Option("--voxel-size-m", help="Voxel-deduplicate the map (default: every point).")] = None,
    trajectory: Annotated[Optional[Path], typer.Option("--trajectory", help="Write the trajectory to this file.")] = None,
    format: Annotated[str, typer.Option("--format", help="Trajectory format: tum | kitti")] = "tum",
) -> None:
    """Export the map (world frame of a revision) and/or the trajectory."""
    if map_path is None and trajectory is None:
        raise typer.BadParameter("nothing to export: give --map and/or --trajectory")
    with _open_store(store_path) as store:
        rev = store.head if revision is None else revision
        store.ledger.revision(rev)
        if trajectory is not None:
            store.export_trajectory(trajectory, revision=rev, format=format)
            console.print(f"trajectory (revision {rev}, {format}): {trajectory}")
        if map_path is not None:
            view = store.map(rev)
            view.export(map_path, voxel_size_m=voxel_size_m, provenance=voxel_size_m is not None)
            console.print(f"map (revision {rev}, {view.n_points:,} points{f', voxel {voxel_size_m} m' if voxel_size_m else ''}): {map_path}")


@app.command()
def recover(store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")]) -> None:
    """Salvage every intact frame and revision of a damaged store (damaged files are kept beside)."""
    from driftmap.store.frame_store import FrameStore

    events = FrameStore.recover(store_path)
    if not events:
        console.print(f"{store_path}: every segment is intact; nothing to do")
    for event in events:
        console.print(f"recovered {event}")


def main() -> None:
    """Console-script entry point: maps driftmap errors to one line and a non-zero exit."""
    try:
        app()
    except DriftmapError as exc:
        if _state["debug"]:
            raise
        err_console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        sys.exit(1)
    except KeyboardInterrupt:
        err_console.print("[red]interrupted[/red]")
        sys.exit(130)


if __name__ == "__main__":
    main()
