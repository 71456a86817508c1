"""``driftmap batch``: many logs at once, one Ray task per log (:mod:`driftmap.fleet`, docs/fleet.md)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text

from driftmap.cli.common import app, bold, check_output, console, err_console, progress_bar, writing_output
from driftmap.store import refuse_inside_store


def _fleet_progress() -> Progress:
    return Progress(
        TextColumn("[bold]logs"), BarColumn(), MofNCompleteColumn(),
        TextColumn("{task.fields[done]} done, {task.fields[running]} running, {task.fields[failed]} failed"),
        TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), console=err_console, transient=False,
    )


def _number(value: Any, scale: float = 1.0, digits: int = 2) -> str:
    return "-" if value is None else f"{scale * value:.{digits}f}"


def _interrupted_line(out: Path) -> str:
    """What an interrupted batch left: ``fleet.json`` is named only where it was written (a Ctrl-C while Ray starts
    comes before any log)."""
    if (out / "fleet.json").is_file():
        return (f"interrupted: the logs that finished are in {out}, the others left nothing behind (see "
                f"{out / 'fleet.json'}); continue with --resume")
    if out.is_dir():
        return f"interrupted before any log ran: no log was written to {out}; continue with --resume"
    return "interrupted before any log ran: nothing was written"


def _summary_table(rows: list[dict], out: Path) -> Table:
    """Every log's row, in fleet.html's order (trial 17 W7): the logs with results worst first
    (:func:`~driftmap.fleet.report.rank_worst_first`: a log whose diagnosis cannot judge its map first), then the
    failed ones in input order."""
    from driftmap.fleet.report import cannot_judge, rank_worst_first

    rows = rank_worst_first(rows) + [r for r in rows if r["status"] == "failed"]
    table = Table(title=f"driftmap batch -> {out} (worst first)")
    for col in ("log", "status", "diagnosis", "frames", "time (s)", "drift (%/m)", "doubled (%)", "smearing (mm)",
                "ATE (cm)"):
        table.add_column(col, justify="left" if col in ("log", "status", "diagnosis") else "right")
    for r in rows:
        style = {"failed": "red", "skipped": "dim"}.get(r["status"], "")
        unjudged = cannot_judge(r)  # its figures are no measure of the map (trial 16 W2)
        judged = ["cannot judge"] * 3 if unjudged else [
            _number(r["drift_percent_per_m"], digits=3), _number(r["fraction_flagged"], 100),
            _number(r["smearing_score_m"], 1000)]
        verdict = Text("cannot judge", style="yellow") if unjudged else Text("valid" if r.get("valid") else "-")
        table.add_row(r["name"], Text(r["status"], style=style), verdict, str(r["frames"]), _number(r["time_s"], digits=1),
                      *judged, _number(r["ate_rmse_m"], 100))
    return table


@app.command()
def batch(
    inputs: Annotated[list[str], typer.Argument(metavar="INPUTS...", help="Logs or data-set folders, globs, or text files (.txt / .list / .lst) listing logs one per line with optional per-log options (--format, --sensor, --topic, --pose-from-tf, --pose-from-odometry, --lenient, --period-s, --point-layout, --poses, --poses-from-source, --frames, --gt, --gt-format, --name).")],
    out: Annotated[Path, typer.Option("--out", help="Batch folder: fleet.json, fleet.html and one folder per log (store/, diagnosis.json, the exports).")],
    config: Annotated[Optional[Path], typer.Option("--config", help="Config file (JSON or TOML): the [build], [diagnose], [depth], [map], [volume] tables every log's build, diagnose and exports read, and a [fleet] table (exports, trajectory_format, ground_truth, compare_before_loop_closure, loop_closure, threads_per_log).")] = None,
    workers: Annotated[Optional[int], typer.Option("--workers", min=1, help="Logs run at once (default: one per CPU here; on a cluster, its CPUs / threads_per_log). Each log's threads are the CPUs shared by the workers, so the machine is not oversubscribed.")] = None,
    ray_address: Annotated[Optional[str], typer.Option("--ray-address", help="Join this running Ray cluster (e.g. auto, or ray://HEAD:10001; start one with 'ray start --head') instead of the Ray embedded in this process.")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue an earlier batch in --out: logs whose folder is complete and made with the same config are kept (status skipped), the others (failed, interrupted, changed config) are run.")] = False,
) -> None:
    """Build, diagnose and export many logs, one Ray task per log: DIR/<log>/ for each, DIR/fleet.json and
    DIR/fleet.html for the fleet (logs ranked worst first, failures with their reasons)."""
    from driftmap.errors import DriftmapError
    from driftmap.fleet import FleetProgress, expand_inputs, load_batch_config, require_ray, run_batch

    require_ray(ray_address)  # the one-line install hint before anything else
    check_output(out, "--out", folder=True)
    specs = expand_inputs(inputs, exclude=out)
    batch_config = load_batch_config(config)
    with _fleet_progress() as progress:
        task = progress.add_task("logs", total=len(specs), done=0, running=0, failed=0)

        def tick(state: FleetProgress) -> None:
            progress.update(task, completed=state.done + state.failed, done=state.done, running=state.running,
                            failed=state.failed)
            if state.last is not None and state.last["status"] == "failed":
                error = state.last["error"]
                error = error if len(error) <= 300 else error[:297] + "..."  # fleet.json has all of it
                progress.console.print(Text.assemble(("failed:", "red"), f" {state.last['name']}: {error}"),
                                       highlight=False)
                state.last = None

        try:
            result = run_batch(specs, out, batch_config, workers=workers, ray_address=ray_address, resume=resume,
                               progress=tick)
        except DriftmapError:
            progress.update(task, visible=False)  # e.g. Ray could not start: the error line alone, no empty bar
            raise
        except KeyboardInterrupt:
            progress.stop()
            err_console.print(Text(_interrupted_line(out), style="yellow"), highlight=False)
            raise
    console.print(_summary_table(result.rows, out))
    console.print(f"{result.workers} workers, {result.threads} thread{'s' if result.threads > 1 else ''} each"
                  + (f" on the Ray cluster at {ray_address}" if ray_address else " (embedded Ray)")
                  + f", {result.seconds:.1f} s", highlight=False)
    console.print(bold("fleet: ", result.files["fleet_json"]))
    console.print(bold("report: ", result.files["html"]))
    if result.failed:
        raise DriftmapError(f"{len(result.failed)} of {len(result.rows)} logs failed; their errors are in "
                            f"{result.files['fleet_json']}")


def synth_fleet_command(out: Path, n: Optional[int], broken: int, frames: Optional[int], seed: int, lidar: bool,
                        overwrite: bool, not_taken: list[str]) -> None:
    """``synth --fleet N``: N small room logs (and ``broken`` broken ones) in OUT (:func:`driftmap.fleet.synth_fleet`)."""
    from driftmap.fleet.synth import DEFAULT_FRAMES, synth_fleet

    if n is None:
        raise typer.BadParameter("--broken adds broken logs to a fleet: give --fleet N", param_hint="--broken")
    if not_taken:
        raise typer.BadParameter(f"--fleet makes small room logs; it does not take {', '.join(not_taken)}",
                                 param_hint="--fleet")
    refuse_inside_store(out, "OUT")
    with progress_bar() as progress, writing_output(out, "the synthetic fleet"):
        task = progress.add_task("ray-casting the synthetic fleet", total=n + broken)
        logs = synth_fleet(out, n, broken=broken, frames=frames or DEFAULT_FRAMES, seed=seed, lidar=lidar,
                           overwrite=overwrite, progress=lambda done, total: progress.update(task, completed=done))
    table = Table(title=f"synthetic fleet: {out}")
    for col in ("log", "seed", "frames", "yaw drift (deg/m)", "scale drift (%)", "step (cm)", "broken"):
        table.add_column(col, justify="left" if col in ("log", "broken") else "right")
    for log in logs:
        c = log.config
        table.add_row(log.path.name, str(c.seed), str(c.n_frames), f"{c.yaw_drift_deg_per_m:g}",
                      f"{c.scale_drift_percent:g}", f"{100 * math.hypot(*c.step_m[:2]):.1f} at {c.step_frame}",
                      log.broken or "-")
    console.print(table)
    console.print(bold("synthetic fleet: ", out.resolve(), f" ({n} logs + {broken} broken; run 'driftmap batch {out}/*')"))
