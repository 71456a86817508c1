"""The ``driftmap`` command line (typer + rich).

Only this module prints and exits: library errors (:class:`DriftmapError`) become one red line and exit
code 1; ``--debug`` shows the traceback and debug logs.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Annotated, Optional

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
console = Console()
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
    table.add_row("loop wall spread, ground truth (median / max)",
                  f"{result.wall_spread_ground_truth_m * 100:.1f} / {result.wall_spread_ground_truth_max_m * 100:.1f} cm")
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
