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
from typing import TYPE_CHECKING, Annotated, Optional

import numpy as np
import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from driftmap import __version__
from driftmap.errors import DriftmapError

if TYPE_CHECKING:
    from driftmap.diagnostics.verify import RegionCheck

app = typer.Typer(
    name="driftmap",
    help="Multi-frame fusion and drift-aware mapping: frames kept with the poses that produced them.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode=None,  # help texts are plain: "[build] table" stays as written
)
# piped output (logs, other tools) gets wide tables instead of rich's 80-column default
_PIPE_WIDTH = None if sys.stdout.isatty() else int(os.environ.get("COLUMNS", "160"))
# no rich markup in printed text: paths and messages may contain brackets ("run[1].tum")
console = Console(width=_PIPE_WIDTH, markup=False)
err_console = Console(stderr=True, markup=False)


def _bold(label: str, value: object, rest: str = "") -> Text:
    return Text.assemble(label, (str(value), "bold"), rest)


def _choice(value: str, allowed: tuple[str, ...], flag: str) -> str:
    """A usage error (exit 2) for an option value outside ``allowed`` (case-insensitive)."""
    v = value.lower()
    if v not in allowed:
        raise typer.BadParameter(f"{value!r} is not one of {', '.join(allowed)}", param_hint=flag)
    return v

def _check_output(path: Optional[Path], flag: str, *, folder: bool = False) -> None:
    """Refuse, before any work, an output that cannot be written: a folder in its way (or, for ``folder``, a file),
    a file where a parent folder must go, or a parent that is not writable (one error line, exit 1)."""
    from driftmap.errors import ConfigError

    if path is None:
        return
    if path.exists() and (path.is_dir() != folder):
        what = "a folder" if path.is_dir() else "a file"
        raise ConfigError(f"{path}: is {what}, but {flag} needs a {'folder' if folder else 'file'} path")
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"{path}: {parent} is a file, so {flag} cannot make a folder there")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{path}: {parent} is not writable ({flag})")


_SENSOR_HELP = "Which sensor of a log with several (the synthetic log: depth | lidar)."
_TOPIC_HELP = "ROS logs: the PointCloud2 or depth Image topic to read (default: the only one)."
_POSE_TF_HELP = "ROS logs: frame poses from TF, 'PARENT,CHILD' (e.g. map,base_link) looked up at each frame's stamp."
_POSE_ODOM_HELP = "ROS logs: frame poses from this nav_msgs/Odometry topic (interpolated at each frame's stamp)."
_LENIENT_HELP = "Skip unreadable frames (each logged with its reason) instead of stopping at the first."
_PERIOD_HELP = ("Folders of PLY / PCD clouds without stamps of their own: the scan period in seconds, frame n is "
                "stamped n * S (e.g. 0.5 for a 2 Hz scanner; without it such a folder is assumed 10 Hz, with a warning). "
                "Refused for formats with stamps of their own and for folders that carry stamps (file names, "
                "times.txt, a 4x4 pose file with stamps).")


def _source_options(sensor: Optional[str], topic: Optional[str], pose_from_tf: Optional[str],
                    pose_from_odometry: Optional[str], lenient: bool, period_s: Optional[float] = None) -> dict:
    """The source options of ``build`` / ``convert`` that were given (checked against the format later)."""
    from driftmap.errors import ConfigError

    period_ns = None
    if period_s is not None:
        if not (np.isfinite(period_s) and period_s > 0 and round(period_s * 1e9) > 0):
            raise ConfigError(f"--period-s: the scan period must be a positive number of seconds, got {period_s:g}")
        period_ns = round(period_s * 1e9)

    tf = None
    if pose_from_tf is not None:
        parts = [p.strip() for p in pose_from_tf.split(",")]
        if len(parts) != 2 or not all(parts):
            raise ConfigError(f"--pose-from-tf: expected 'PARENT,CHILD' (two frame names), got {pose_from_tf!r}")
        tf = (parts[0], parts[1])
    options = {"sensor": sensor, "topic": topic, "pose_from_tf": tf, "pose_from_odometry": pose_from_odometry,
               "lenient": lenient or None, "period_ns": period_ns}
    return {k: v for k, v in options.items() if v is not None}


def _refuse_existing(path: Path, flag: str, overwrite: bool) -> None:
    """An existing output file is kept unless ``--overwrite`` (as ``export`` does)."""
    from driftmap.errors import ConfigError

    if path.is_file() and not overwrite:
        raise ConfigError(f"{path}: already exists ({flag}); pass --overwrite to replace it")


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
    """Run the whole story on the embedded synthetic drifting-robot log: build -> diagnose -> loop closure
    -> diagnose again -> exports -> report."""
    from driftmap.demo import region_lines, run_demo, summary_rows

    with _progress() as progress:
        tasks: dict[str, int] = {}

        def tick(stage: str, done: int, total: int | None) -> None:
            if stage not in tasks:
                tasks[stage] = progress.add_task(stage, total=total)
            progress.update(tasks[stage], completed=done, total=total)

        result = run_demo(out, log_path=log, max_frames=frames, progress=tick)
    before = result.diagnosis_before
    if before is not None:
        console.print(f"revision 0 (drifting odometry): {before.n_regions} double-wall regions, "
                      f"{100 * before.fraction_flagged:.2f} % of surface voxels doubled", highlight=False)
        for line in region_lines(before):
            console.print(f"  {line}", highlight=False)
    table = Table(title="driftmap demo: synthetic loop, drifting odometry -> loop closure")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for k, v in summary_rows(result):
        table.add_row(k, v)
    console.print(table)
    for name, path in result.files.items():
        console.print(f"  {name:28s} {path}", highlight=False)
    console.print(_bold("report: ", result.files.get("report_html", "-")))
    console.print(_bold("results: ", result.out_dir))


@app.command("config")
def config_cmd(
    show: Annotated[bool, typer.Option("--show", help="Print every setting with its default and meaning.")] = True,
    file: Annotated[Optional[Path], typer.Option("--file", help="Show the values a config file (JSON/TOML) yields; 'build --config' reads its [build] and [depth] tables, 'export --config' its [map] table.")] = None,
) -> None:
    """Print the configuration (defaults < file < DRIFTMAP_* environment) with units in every name; every
    setting shown takes effect (depth.* in build, map.* in export, build.* in build)."""
    from pydantic import BaseModel

    from driftmap.config import DriftmapConfig
    from driftmap.pipeline.build import BuildConfig

    table = Table(title="driftmap configuration" + (f" ({file})" if file else " (defaults + environment)"))
    for col in ("setting", "value", "meaning"):
        table.add_column(col, overflow="fold")

    from driftmap.registration.loops import LIDAR_LOOP_DEFAULTS

    def walk(model: BaseModel, prefix: str) -> None:
        for name, field in type(model).model_fields.items():
            value = getattr(model, name)
            if isinstance(value, BaseModel):
                walk(value, f"{prefix}{name}.")
            else:
                shown = str(value.value if hasattr(value, "value") else value)
                if prefix == "build.loop_closure." and name in LIDAR_LOOP_DEFAULTS and name not in model.model_fields_set:
                    shown = f"depth: {shown}, lidar: {LIDAR_LOOP_DEFAULTS[name]}"
                table.add_row(prefix + name, shown, field.description or "")

    walk(DriftmapConfig.load(file), "")
    build_cfg = BuildConfig() if file is None else BuildConfig.load(file)
    walk(build_cfg, "build.")
    if build_cfg.odometry is None:  # per sensor kind: show both defaults instead of "None"
        from driftmap.frame import SensorKind
        from driftmap.registration.odometry import KISS_LENGTHS, OdometryConfig

        depth, lidar = (OdometryConfig.for_sensor(k) for k in (SensorKind.DEPTH_CAMERA, SensorKind.LIDAR))
        for name, field in OdometryConfig.model_fields.items():
            a, b = (getattr(c, name) for c in (depth, lidar))
            a, b = (v.value if hasattr(v, "value") else v for v in (a, b))
            if name in KISS_LENGTHS:
                b = f"{b} (scaled down indoors)"
            table.add_row(f"build.odometry.{name}", f"depth: {a}, lidar: {b}" if a != b else str(a), field.description or "")
    console.print(table)


@app.command("synth")
def synth(
    out: Annotated[Path, typer.Argument(help="Folder to write the synthetic log to.")],
    frames: Annotated[Optional[int], typer.Option("--frames", min=2, help="Number of frames (default: 60 in the room, 245 on the street; with --period-s, --stationary-start, --stops or turns: what the scene's speed needs).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 7,
    lidar: Annotated[bool, typer.Option("--lidar/--no-lidar", help="Also simulate a 16-beam spinning LiDAR (implied by --lidar-pattern rosette and --point-times).")] = False,
    yaw_drift_deg_per_m: Annotated[Optional[float], typer.Option("--yaw-drift-deg-per-m", help="Odometry yaw drift (default: 0.6 in the room, 0.02 on the street).")] = None,
    scale_drift_percent: Annotated[Optional[float], typer.Option("--scale-drift-percent", help="Odometry scale drift (default: 1.0).")] = None,
    scene: Annotated[str, typer.Option("--scene", help="room (a furnished room, a depth camera and with --lidar a 16-beam LiDAR) | street (a city block loop, a 32-beam car LiDAR; defaults: 245 frames, 0.02 deg/m yaw drift, 1 % scale drift).")] = "room",
    period_s: Annotated[Optional[float], typer.Option("--period-s", min=0.001, help="Time between frames/scans in seconds (default: 0.2 in the room, 0.1 on the street; 0.5-0.05 for 2-20 Hz). The speed stays the scene's unless --frames or --speed-m-per-s is given: at 2 Hz a scan moves 5 times as far as at 10 Hz.")] = None,
    speed_m_per_s: Annotated[Optional[float], typer.Option("--speed-m-per-s", min=0.001, help="Speed along the path while moving (default: the scene's, 0.59 m/s in the room, 10 m/s on the street); the frame count follows from it (not with --frames).")] = None,
    stationary_start: Annotated[int, typer.Option("--stationary-start", min=0, metavar="N", help="The first N scans stand at the start pose (each a new noise draw); motion starts at frame N.")] = 0,
    stops: Annotated[int, typer.Option("--stops", min=0, metavar="K", help="K stops at evenly spaced places of the path (fractions j / (K + 1)); give --stop-frames.")] = 0,
    stop_frames: Annotated[int, typer.Option("--stop-frames", min=0, metavar="M", help="Scans each stop lasts.")] = 0,
    turn_deg_per_frame: Annotated[float, typer.Option("--turn-deg-per-frame", metavar="DEG", help="Yaw per scan of the in-place turns (e.g. 45 or 50; + counter-clockwise; |DEG| < 180).")] = 0.0,
    turn_frames: Annotated[int, typer.Option("--turn-frames", min=0, metavar="F", help="Scans each in-place turn lasts at --turn-deg-per-frame (8 x 45 = one full turn); if they make no whole turn, the robot turns back as many scans.")] = 0,
    turns: Annotated[int, typer.Option("--turns", min=0, metavar="K", help="K in-place turns at evenly spaced places of the path (fractions j / (K + 1)).")] = 0,
    turn_at: Annotated[Optional[list[float]], typer.Option("--turn-at", metavar="FRACTION", help="An in-place turn at this fraction (0-1) of the path, instead of --turns; repeat for more.")] = None,
    lidar_pattern: Annotated[str, typer.Option("--lidar-pattern", help="spinning (beams x azimuths) | rosette (a Livox-like non-repetitive scanner: 70 deg circular field of view along x, the pattern rotating from scan to scan).")] = "spinning",
    points_per_scan: Annotated[Optional[int], typer.Option("--points-per-scan", min=1, help="Points per rosette scan (default: 24000).")] = None,
    point_times: Annotated[bool, typer.Option("--point-times/--no-point-times", help="Per-point capture times: each LiDAR point is rendered from the moving sensor's pose at its time, stored in lidar/NNNNNN.time.bin (int64 ns after the scan's start stamp).")] = False,
) -> None:
    """Generate a synthetic drifting-robot log (deterministic for a given seed)."""
    from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log

    scene = _choice(scene, ("room", "street"), "--scene")
    pattern = _choice(lidar_pattern, ("spinning", "rosette"), "--lidar-pattern")
    if frames is not None and speed_m_per_s is not None:
        raise typer.BadParameter("give the frame count or the speed, not both (the speed sets the frame count)",
                                 param_hint="--speed-m-per-s")
    given = {"seed": seed, "n_frames": frames, "yaw_drift_deg_per_m": yaw_drift_deg_per_m,
             "scale_drift_percent": scale_drift_percent}
    motion = {"stationary_start_frames": stationary_start, "stops": stops, "stop_frames": stop_frames,
              "turn_in_place_deg_per_frame": turn_deg_per_frame, "turn_in_place_frames": turn_frames,
              "turns_in_place": turns, "turn_in_place_at": tuple(turn_at or ()),
              "lidar_pattern": pattern, "lidar_point_times": point_times}
    if period_s is not None:
        motion["frame_period_ns"] = int(round(period_s * 1e9))
    if points_per_scan is not None:
        motion["lidar_points_per_scan"] = points_per_scan
    if scene == "street":
        cfg = SyntheticLogConfig.street(**{k: v for k, v in given.items() if v is not None}, **motion)
    else:
        defaults = SyntheticLogConfig()
        cfg = SyntheticLogConfig(lidar=lidar or pattern == "rosette" or point_times,
                                 **{k: getattr(defaults, k) if v is None else v for k, v in given.items()}, **motion)
    # without --frames the log keeps the scene's speed: stationary, stop and turn scans are added, a period changes
    # the frame count (not the speed)
    changes_frames = period_s is not None or stationary_start or stops or turns or turn_at
    if speed_m_per_s is not None or (frames is None and changes_frames):
        from dataclasses import replace

        cfg = replace(cfg, speed_m_per_s=speed_m_per_s or cfg.default_speed_m_per_s())
    with console.status(f"ray-casting the synthetic {scene}"):
        path = generate_synthetic_log(out, cfg)
    console.print(_bold("synthetic log: ", path.resolve()))
    console.print(f"{cfg.n_frames} frames, {cfg.frame_period_ns / 1e9:g} s apart")


# ------------------------------------------------------------------------------------------ sources / build


@app.command()
def convert(
    source: Annotated[Path, typer.Argument(help="Data-set folder or log to convert.")],
    out: Annotated[Path, typer.Argument(metavar="OUT.mcap", help="MCAP file to write (ROS 2 messages).")],
    format: Annotated[Optional[str], typer.Option("--format", help="Source format (default: detected).")] = None,
    frames: Annotated[Optional[str], typer.Option("--frames", help="START:STOP[:STEP] of the source's frames.")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing OUT.mcap; without it an existing file is refused before anything is read.")] = False,
    sensor: Annotated[Optional[str], typer.Option("--sensor", help=_SENSOR_HELP)] = None,
    topic: Annotated[Optional[str], typer.Option("--topic", help=_TOPIC_HELP)] = None,
    pose_from_tf: Annotated[Optional[str], typer.Option("--pose-from-tf", help=_POSE_TF_HELP)] = None,
    pose_from_odometry: Annotated[Optional[str], typer.Option("--pose-from-odometry", help=_POSE_ODOM_HELP)] = None,
    lenient: Annotated[bool, typer.Option("--lenient", help=_LENIENT_HELP)] = False,
    period_s: Annotated[Optional[float], typer.Option("--period-s", help=_PERIOD_HELP)] = None,
) -> None:
    """Convert any source to an MCAP log (ROS 2 PointCloud2 / CameraInfo / TF) that Foxglove opens."""
    from driftmap.pipeline.build import check_source_options
    from driftmap.sources.mcap_export import convert as convert_source

    format = _source_format(source, format)
    _check_output(out, "OUT.mcap")
    _refuse_existing(out, "OUT.mcap", overwrite)
    options = _source_options(sensor, topic, pose_from_tf, pose_from_odometry, lenient, period_s)
    check_source_options(source, format, options)
    with console.status(f"converting {source}"):
        summary = convert_source(source, out, format=format, frames=frames, **options)
    extra = {k: v for k, v in summary.items()
             if k not in ("out", "source", "frames", "points", "bytes", "skipped") and not isinstance(v, (dict, list))}
    console.print(f"wrote {out} ({summary.get('bytes', 0) / 1e6:.1f} MB): {summary.get('frames')} frames, "
                  f"{summary.get('points', 0):,} points from {summary.get('source')}"
                  + (f"; {summary['skipped']} frames skipped (see the log)" if summary.get("skipped") else "")
                  + ("; " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in extra.items()) if extra else ""),
                  highlight=False)


_KITTI_FRAME_HELP = ("Frame of a KITTI pose file on a store of KITTI Velodyne scans: auto (the data set's own cam0 "
                     "poses.txt is converted to the Velodyne frame, any other file is taken as Velodyne poses) | "
                     "velodyne (rows as they are) | cam0 (converted with calib.txt Tr).")
_CALIB_HELP = "KITTI calib.txt (line Tr) for --kitti-frame cam0 (default: the data set's calib.txt)."


def _load_build_config(path: Optional[Path]):
    from driftmap.pipeline.build import BuildConfig

    return BuildConfig() if path is None else BuildConfig.load(path)


def _source_format(source: Path, format: Optional[str]) -> Optional[str]:
    """``--format``: a registered source format (a usage error otherwise)."""
    from driftmap.sources.base import registered_formats

    return _choice(format, tuple(sorted(registered_formats())), "--format") if format is not None else None


def _with_depth_scale_hint(exc: Exception, source: Path, format: Optional[str]) -> DriftmapError:
    """A :class:`DepthScaleError` from ``build``, with the command line's way to fix it."""
    from driftmap.errors import DepthScaleError
    from driftmap.pipeline.build import _detect_format
    from driftmap.sources.base import accepted_options, registered_formats

    assert isinstance(exc, DepthScaleError)
    fmt = _detect_format(source, format)
    takes = accepted_options(registered_formats()[fmt].open) if fmt in registered_formats() else frozenset()
    message = str(exc).replace("(sensor_range_m=None disables this check)", "").rstrip()
    fixes = []
    if "depth_scale" in takes:
        fixes.append(f"set it with --depth-scale {exc.depth_scale_suggested:g}" if exc.depth_scale_suggested
                     else "set it with --depth-scale UNITS_PER_M")
    if "sensor_range_m" in takes:
        fixes.append("skip this check with depth.check_scale = false (config file [depth] table, or "
                     "DRIFTMAP_DEPTH__CHECK_SCALE=false)")
    return DepthScaleError(message + ("; " + "; or ".join(fixes) if fixes else ""),
                           depth_scale_used=exc.depth_scale_used, depth_scale_suggested=exc.depth_scale_suggested)


def _loops_by_cue(loops: list[dict]) -> str:
    """``proximity 5, scan_context 2``: accepted loops per candidate kind (``-`` for none)."""
    counts: dict[str, int] = {}
    for loop in loops:
        if loop["accepted"]:
            counts[loop["kind"]] = counts.get(loop["kind"], 0) + 1
    return ", ".join(f"{kind} {n}" for kind, n in sorted(counts.items())) or "-"


def _tracking_counts(tracking: dict) -> str:
    """``78 / 1 / 0`` frames whose odometry registration was ok / recovered / flagged (``-`` without records)."""
    if not tracking.get("frames"):
        return "-"
    by = tracking["by_status"]
    return f"{by.get('ok', 0) + by.get('first', 0)} / {by.get('recovered', 0)} / {len(tracking['flagged'])}"


@app.command()
def build(
    source: Annotated[Path, typer.Argument(help="Data-set folder or log.")],
    out: Annotated[Path, typer.Option("--out", help="Store directory to create (or continue with --resume).")],
    format: Annotated[Optional[str], typer.Option("--format", help="Source format (default: detected).")] = None,
    config: Annotated[Optional[Path], typer.Option("--config", help="Config file (JSON or TOML): its [build] table (the build.* keys 'driftmap config' lists) and [depth] table, or a bare build config (the whole file); DRIFTMAP_DEPTH__* environment variables and --depth-scale override the [depth] table.")] = None,
    depth_scale: Annotated[Optional[float], typer.Option("--depth-scale", help="Depth-image units per metre (1000: millimetres, TUM 5000) for depth sources that take one (7-Scenes, TUM, Redwood / ICL-NUIM); default: the format's own (depth.depth_scale).")] = None,
    intrinsics: Annotated[Optional[str], typer.Option("--intrinsics", help="Depth camera intrinsics 'fx,fy,cx,cy[,width,height]', a TUM setup fr1|fr2|fr3, or an Open3D intrinsics JSON, for sources that take them (7-Scenes, TUM, Redwood / ICL-NUIM); default: the source's own (depth.intrinsics).")] = None,
    sensor: Annotated[Optional[str], typer.Option("--sensor", help=_SENSOR_HELP)] = None,
    topic: Annotated[Optional[str], typer.Option("--topic", help=_TOPIC_HELP)] = None,
    pose_from_tf: Annotated[Optional[str], typer.Option("--pose-from-tf", help=_POSE_TF_HELP + " With --poses-from-source they become revision 0.")] = None,
    pose_from_odometry: Annotated[Optional[str], typer.Option("--pose-from-odometry", help=_POSE_ODOM_HELP + " With --poses-from-source they become revision 0.")] = None,
    lenient: Annotated[bool, typer.Option("--lenient", help=_LENIENT_HELP)] = False,
    period_s: Annotated[Optional[float], typer.Option("--period-s", help=_PERIOD_HELP)] = None,
    poses: Annotated[Optional[Path], typer.Option("--poses", help="Use these poses (format detected: TUM, EuRoC and 4x4 blocks with stamps by stamp; KITTI and 4x4 blocks without stamps row = frame_id; Redwood .log by its frame ids).")] = None,
    poses_from_source: Annotated[bool, typer.Option("--poses-from-source", help="Use the source's own poses (log odometry or ground truth).")] = False,
    no_loop_closure: Annotated[bool, typer.Option("--no-loop-closure", help="Skip loop closure and the pose graph.")] = False,
    frames: Annotated[Optional[str], typer.Option("--frames", help="START:STOP[:STEP] of the source's frames.")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue a build that was interrupted.")] = False,
    kitti_frame: Annotated[str, typer.Option("--kitti-frame", help=_KITTI_FRAME_HELP)] = "auto",
    calib: Annotated[Optional[Path], typer.Option("--calib", help=_CALIB_HELP)] = None,
    max_dt_ms: Annotated[float, typer.Option("--max-dt-ms", min=0.0, help="--poses TUM file: a row is a frame's pose when it is the nearest within this (ms; 20, as TUM's associate.py; 'correct' defaults to 10).")] = 20.0,
    threads: Annotated[Optional[int], typer.Option("--threads", min=1, help="Registration threads of the odometry and the loop closure (build.num_threads; default: the config's, 2). With 1 the same input gives the same poses, every revision, to the bit; with more, the threads' partial sums arrive in varying order and builds differ by millimetres.")] = None,
) -> None:
    """Build a drift-corrected map: odometry, verified loop closures, GTSAM pose graph, re-transform."""
    from driftmap.config import DriftmapConfig
    from driftmap.errors import ConfigError, DepthScaleError
    from driftmap.pipeline.build import build as run_build

    format = _source_format(source, format)
    options = _source_options(sensor, topic, pose_from_tf, pose_from_odometry, lenient, period_s)
    problems = []  # every problem of the config file and the environment at once
    try:
        cfg = _load_build_config(config)
    except ConfigError as exc:
        problems.append(str(exc))
    try:
        flags = {k: v for k, v in (("depth_scale", depth_scale), ("intrinsics", intrinsics)) if v is not None}
        settings = DriftmapConfig.load(config, **({"depth": flags} if flags else {}))
    except ConfigError as exc:
        problems.append(str(exc))
    if problems:
        raise ConfigError("\n".join(dict.fromkeys(problems)))
    if threads is not None:
        cfg = cfg.model_copy(update={"num_threads": threads})
    with _progress() as progress:
        tasks: dict[str, int] = {}

        def tick(stage: str, done: int, total: int | None) -> None:
            if stage not in tasks:
                tasks[stage] = progress.add_task(stage, total=total)
            progress.update(tasks[stage], completed=done, total=total)

        try:
            result = run_build(source, out, format=format, config=cfg, poses_file=poses, poses_from_source=poses_from_source,
                               loop_closure=not no_loop_closure, frames=frames, resume=resume, progress=tick,
                               kitti_frame=kitti_frame, calib_file=calib, poses_max_dt_ns=round(max_dt_ms * 1e6),
                               depth=settings.depth, source_options=options)
        except DepthScaleError as exc:
            raise _with_depth_scale_hint(exc, source, format) from exc
    table = Table(title=f"driftmap build: {source} -> {out}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    rows = [
        ("frames (new / in store)", f"{result.n_frames_new} / {result.n_frames}"),
        ("mean invalid-pixel fraction", "-" if result.mean_invalid_fraction is None else f"{result.mean_invalid_fraction:.3f}"),
        ("poses", result.pose_source),
        ("odometry fps", "-" if result.odometry_fps is None else f"{result.odometry_fps:.1f}"),
        ("tracking ok / recovered / flagged", _tracking_counts(result.tracking)),
        ("keyframes", str(result.n_keyframes)),
        ("loops tried / accepted / rejected by graph", f"{result.loops_tried} / {result.loops_accepted} / {result.loops_rejected_by_graph}"),
        ("loops accepted by cue", _loops_by_cue(result.loops)),
        ("graph error before / after", "-" if result.graph_error_before is None else f"{result.graph_error_before:.4g} / {result.graph_error_after:.4g}"),
        ("loop-closure revision", "-" if result.loop_revision is None else str(result.loop_revision)),
        ("max correction", "-" if result.max_correction_m is None else f"{result.max_correction_m:.3f} m / {result.max_correction_deg:.2f} deg"),
        ("throughput", f"{result.frames_per_second:.1f} frames/s"),
    ]
    rows += [(f"time: {k}", f"{v:.2f} s") for k, v in result.seconds_per_stage.items()]
    for k, v in rows:
        table.add_row(k, v)
    console.print(table)
    for f in result.tracking.get("flagged", [])[:10]:
        err_console.print(Text.assemble(("flagged:", "yellow"), f" frame {f['frame_id']} ({f['status']}): {f['reason']}"),
                          highlight=False)
    console.print(_bold("store: ", Path(result.store).resolve(), " (build_config.json and build_summary.json saved in it)"))


# ------------------------------------------------------------------------------------------ store / ledger


def _open_store(path: Path, mode: str = "r"):
    from driftmap.store.frame_store import FrameStore

    store = FrameStore.open(path, mode)
    for event in store.recovery_events:
        err_console.print(Text.assemble(("recovered:", "yellow"), f" {event}"), highlight=False)
    if store.loss:
        err_console.print(Text.assemble(("recovered earlier:", "yellow"), f" {store.loss}"), highlight=False)
    return store


@app.command()
def correct(
    store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")],
    poses: Annotated[Path, typer.Option("--poses", help="Pose file (T_world_sensor per frame).")],
    format: Annotated[str, typer.Option("--format", help="tum | kitti | redwood (.log) | 4x4 (one 4x4 matrix per frame, the last row 0 0 0 stamp_s or 0 0 0 1)")] = "tum",
    match: Annotated[Optional[str], typer.Option("--match", help="stamp | index (default: stamp for TUM and 4x4 files with stamps, index for KITTI and 4x4 files without: row i = frame_id i; a Redwood .log matches by the frame ids it names)")] = None,
    source: Annotated[str, typer.Option("--source", help="Revision source: external_file, loop_closure, ground_truth, ...")] = "external_file",
    max_dt_ms: Annotated[float, typer.Option("--max-dt-ms", min=0.0, help="Stamp matching tolerance (ms).")] = 10.0,
    no_propagate: Annotated[bool, typer.Option("--no-propagate", help="Do not propagate to frames without a pose row.")] = False,
    kitti_frame: Annotated[str, typer.Option("--kitti-frame", help=_KITTI_FRAME_HELP)] = "auto",
    calib: Annotated[Optional[Path], typer.Option("--calib", help=_CALIB_HELP)] = None,
) -> None:
    """Import a pose file as a new revision (a correction); nothing is overwritten."""
    from driftmap.frame import PoseSource
    from driftmap.store.frame_store import TrajectoryFormat

    format = _choice(format, tuple(f.value for f in TrajectoryFormat), "--format")
    match = None if match is None else _choice(match, ("stamp", "index"), "--match")
    source = _choice(source, tuple(s.value for s in PoseSource if s is not PoseSource.NONE), "--source")
    with _open_store(store_path, "a") as store:
        revision, matched = store.import_poses(poses, format=format, match=match, max_dt_ns=round(max_dt_ms * 1e6),
                                               source=source, propagate=not no_propagate, kitti_frame=kitti_frame,
                                               calib_file=calib)
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
            changed = d.n_changed
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
    voxel_size_m: Annotated[Optional[float], typer.Option("--voxel-size-m", help="Voxel-deduplicate the map (default: map.export_voxel_size_m if set, else every point; --mcap: 0.02 m).")] = None,
    trajectory: Annotated[Optional[Path], typer.Option("--trajectory", help="Write the trajectory to this file.")] = None,
    format: Annotated[str, typer.Option("--format", help="Trajectory format: tum | kitti")] = "tum",
    mcap_path: Annotated[Optional[Path], typer.Option("--mcap", help="Write OUT.mcap for Foxglove: fused map, trajectory and every frame with the revision's poses.")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace existing output files (--map, --trajectory, --mcap); without it an existing file is refused before anything is written.")] = False,
    config: Annotated[Optional[Path], typer.Option("--config", help="Config file (JSON or TOML) whose [map] table sets map.export_voxel_size_m (DRIFTMAP_MAP__EXPORT_VOXEL_SIZE_M overrides it, --voxel-size-m both).")] = None,
) -> None:
    """Export the map (world frame of a revision), the trajectory and/or a Foxglove MCAP."""
    from driftmap.config import DriftmapConfig

    if map_path is None and trajectory is None and mcap_path is None:
        raise typer.BadParameter("nothing to export: give --map, --trajectory and/or --mcap")
    format = _choice(format, ("tum", "kitti"), "--format")
    if voxel_size_m is not None and not voxel_size_m > 0:
        raise typer.BadParameter(f"must be positive, got {voxel_size_m}", param_hint="--voxel-size-m")
    settings = DriftmapConfig.load(config)  # validated also when --voxel-size-m is given
    if voxel_size_m is None:
        voxel_size_m = settings.map.export_voxel_size_m
    if map_path is not None and map_path.suffix.lower() not in (".ply", ".pcd"):  # before anything is written
        raise typer.BadParameter(f"{map_path}: the map is written as .ply or .pcd", param_hint="--map")
    for path, flag in ((trajectory, "--trajectory"), (map_path, "--map"), (mcap_path, "--mcap")):
        _check_output(path, flag)
    outputs = [(trajectory, "--trajectory"), (map_path, "--map"), (mcap_path, "--mcap")]
    if map_path is not None and voxel_size_m is not None:
        outputs.append((Path(f"{map_path}.provenance.npz"), "--map (its provenance file)"))
    for path, flag in outputs:  # every output checked before anything is written
        if path is not None:
            _refuse_existing(path, flag, overwrite)
    with _open_store(store_path) as store:
        rev = store.head if revision is None else revision
        store.ledger.revision(rev)
        if trajectory is not None:
            store.export_trajectory(trajectory, revision=rev, format=format)
            console.print(f"trajectory (revision {rev}, {format}): {trajectory}")
        if map_path is not None:
            view = store.map(rev)
            _, n_written = view.write(map_path, voxel_size_m=voxel_size_m, provenance=voxel_size_m is not None)
            detail = f", voxel {voxel_size_m} m, per-voxel provenance in {map_path}.provenance.npz" if voxel_size_m else ""
            console.print(f"map (revision {rev}, {n_written:,} points{detail}): {map_path}", highlight=False)
        if mcap_path is not None:
            from driftmap.map.foxglove_export import export_foxglove_mcap

            with _progress() as progress:
                task = progress.add_task("foxglove mcap", total=None)
                summary = export_foxglove_mcap(
                    store, mcap_path, revision=rev,
                    map_voxel_size_m=voxel_size_m if voxel_size_m is not None else 0.02,
                    overwrite=overwrite,
                    progress=lambda stage, done, total: progress.update(task, description=f"foxglove mcap: {stage}", completed=done, total=total),
                )
            console.print(f"foxglove mcap (revision {rev}, {summary.n_frames} frames, {summary.n_map_points:,} map points, "
                          f"{summary.bytes / 1e6:.1f} MB): {mcap_path}  (open in Foxglove, 3D panel, display frame 'world')")


@app.command()
def info(store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")]) -> None:
    """Frames, sensors, time span, revisions, size on disk and invalid-pixel statistics of a store."""
    from collections import Counter

    with _open_store(store_path) as store:
        infos = [store.frame_info(int(f)) for f in store.frame_ids]
        table = Table(title=f"driftmap store {store_path}")
        table.add_column("quantity")
        table.add_column("value", justify="right")
        stamps = [i["stamp_ns"] for i in infos]
        sensors = Counter(f"{i['sensor_name']} ({i['sensor_kind']})" for i in infos)
        invalid = [1 - i["quality"]["n_valid"] / i["quality"]["n_measurements"] for i in infos
                   if i.get("quality") and i["quality"]["n_measurements"]]
        flagged = sum(1 for i in infos if i.get("quality") and i["quality"]["flags"])
        n_points = sum(int(i["points"]["n_points"]) for i in infos)
        table.add_row("frames", str(len(infos)))
        table.add_row("frame ids", f"{int(store.frame_ids[0])} .. {int(store.frame_ids[-1])}" if infos else "-")
        table.add_row("sensors", ", ".join(f"{k}: {v}" for k, v in sensors.items()) or "-")
        if stamps:
            table.add_row("time span", f"{(max(stamps) - min(stamps)) / 1e9:.2f} s ({min(stamps)} .. {max(stamps)} ns)")
        table.add_row("points (sensor frames)", f"{n_points:,}")
        table.add_row("revisions", f"{len(store.revisions)} (head {store.head}: {store.revisions[store.head].source.value})")
        if store.loss:
            table.add_row("lost to damage (driftmap recover)", str(store.loss))
        table.add_row("size on disk", f"{store.size_bytes() / 2**20:.1f} MiB")
        if invalid:
            table.add_row("invalid-pixel fraction (mean / max)", f"{np.mean(invalid):.3f} / {np.max(invalid):.3f}")
            table.add_row("frames flagged", str(flagged))
        console.print(table)


@app.command()
def recover(store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")]) -> None:
    """Salvage every intact frame and revision of a damaged store (damaged files are kept beside)."""
    from driftmap.store.frame_store import FrameStore

    events = FrameStore.recover(store_path)
    if not events:
        console.print(f"{store_path}: intact (or already recovered); nothing to do")
    for event in events:
        console.print(f"recovered {event}")


def _verification_note(check: RegionCheck) -> str:
    if check.offset_b_minus_a_m is None:
        return f"; unverifiable ({check.note})"
    cause = {True: ", a pose error", False: ", local (its surroundings agree: not a pose error)", None: ""}[check.pose_explained]
    return f"; measured {100 * check.offset_b_minus_a_m:+.1f} cm: {'confirmed' + cause if check.confirmed else 'NOT confirmed'}"


@app.command()
def diagnose(
    store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")],
    json_path: Annotated[Path, typer.Option("--json", help="Write the diagnosis here (JSON).")],
    revision: Annotated[Optional[int], typer.Option("--revision", help="Revision (default: the latest).")] = None,
    gt: Annotated[Optional[Path], typer.Option("--gt", help="Ground-truth poses (T_world_sensor) for ATE/RPE.")] = None,
    gt_format: Annotated[Optional[str], typer.Option("--gt-format", help="tum (matched by stamp; the default) | kitti (row i = frame_id i) | redwood (.log: by the frame ids it names) | 4x4 (one 4x4 matrix per frame: by stamp when the last rows hold stamps, else block i = frame_id i)")] = None,
    report: Annotated[Optional[Path], typer.Option("--report", help="Write PNG figures to this folder.")] = None,
    compare_revision: Annotated[Optional[int], typer.Option("--compare-revision", help="Also diagnose this revision; the report shows the score before/after.")] = None,
    points_per_frame: Annotated[Optional[int], typer.Option("--points-per-frame", min=50, help="Points sampled per frame (default: a budget of 600k RGB-D / 1M LiDAR points shared by the frames).")] = None,
    kitti_frame: Annotated[str, typer.Option("--kitti-frame", help=_KITTI_FRAME_HELP)] = "auto",
    calib: Annotated[Optional[Path], typer.Option("--calib", help=_CALIB_HELP)] = None,
    verify: Annotated[bool, typer.Option("--verify", help="Re-measure every double-wall region from the stored full-resolution frames with Open3D (adds \"verification\" per region and double_wall.verified).")] = False,
    config: Annotated[Optional[Path], typer.Option("--config", help="Config file (JSON or TOML): its [diagnose] table (or the whole file without one) sets diagnose's own lengths over the scene's defaults: [diagnose.double_wall] voxel_sizes_m, visit_gap_m, ..., [diagnose.attribution], [diagnose.sampling], [diagnose.entropy] (the JSON's \"config\" lists every field); a build config's other tables are ignored.")] = None,
) -> None:
    """Find double walls (where, how far apart, which frames), the smearing score, MME/MPV, per-frame
    disagreement and change points; with --gt also ATE/RPE."""
    import dataclasses
    import time

    from driftmap.diagnostics.double_wall import DiagnosticCloud
    from driftmap.diagnostics.report import GT_FORMATS, DiagnoseConfig, diagnose_store, read_ground_truth, write_report

    gt_format = None if gt_format is None else _choice(gt_format, GT_FORMATS, "--gt-format")
    _check_output(json_path, "--json")  # before the diagnosis, not after it
    _check_output(report, "--report", folder=True)
    with _open_store(store_path) as store:
        if len(store) == 0:
            raise DriftmapError(f"{store_path}: the store has no frames")
        cfg = DiagnoseConfig.for_store(store)
        if config is not None:
            cfg = DiagnoseConfig.load(config, cfg)
        if points_per_frame is not None:
            cfg = cfg.model_copy(update={"sampling": cfg.sampling.model_copy(update={"points_per_frame": points_per_frame})})
        if gt is None and (kitti_frame != "auto" or calib is not None or gt_format is not None):
            from driftmap.errors import ConfigError

            raise ConfigError("--gt-format / --kitti-frame / --calib describe the --gt FILE; give one")
        ground_truth = (read_ground_truth(store, gt, gt_format or "tum", kitti_frame=kitti_frame, calib_file=calib)
                        if gt is not None else None)
        with _progress() as progress:
            task = progress.add_task("sampling frames", total=len(store))
            t0 = time.perf_counter()
            cloud = DiagnosticCloud.from_store(store, cfg.sampling,
                                               progress=lambda stage, done, total: progress.update(task, completed=done))
            sampling_s = time.perf_counter() - t0
        with console.status("diagnosing"):
            result = diagnose_store(store, revision, config=cfg, cloud=cloud, ground_truth=ground_truth)
            result.seconds["sampling"] = sampling_s
            other = (diagnose_store(store, compare_revision, config=cfg, cloud=cloud, ground_truth=ground_truth)
                     if compare_revision is not None else None)
        if verify:
            from driftmap.diagnostics.verify import verify_regions

            with console.status(f"verifying {len(result.double_walls.regions)} double-wall regions"):
                t0 = time.perf_counter()
                checks = verify_regions(store, result.revision, result.double_walls.regions)
                result.seconds["verify"] = time.perf_counter() - t0
            result = dataclasses.replace(result, verification=checks)
    data = result.to_json()
    if other is not None:
        data["comparison"] = {"revision": other.revision, "smearing_score_m": other.to_json()["smearing_score_m"],
                              "fraction_flagged": other.double_walls.fraction_flagged}
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(data, indent=1) + "\n")
    dw = result.double_walls
    table = Table(title=f"driftmap diagnose: {store_path} revision {result.revision}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    rows = [
        ("smearing score", f"{1000 * dw.smearing_score_m:.2f} mm ("
                           + ", ".join(f"{k:.3g} m: {1000 * v:.2f}" for k, v in dw.score_per_scale_m.items()) + "; between visits)"
         if dw.voxels_revisited else
         f"{1000 * dw.smearing_score_m:.2f} mm: no surface was seen on two visits "
         f"({dw.config.visit_gap_m:g} m of travel apart), so drift cannot show"),
        ("smearing score, frame to frame", f"{1000 * dw.frame_smearing_score_m:.2f} mm"),
        ("surface voxels doubled", f"{dw.voxels_flagged} / {dw.voxels_evaluated} ({100 * dw.fraction_flagged:.2f} %)"),
        ("median separation", "-" if dw.median_separation_m is None else f"{100 * dw.median_separation_m:.1f} cm"),
        ("double-wall regions", str(len(dw.regions))),
        ("change points (frame: jump)", ", ".join(
            f"{c.frame_id}: {100 * c.jump_m:.1f} cm" + (f" / {np.linalg.norm(c.step_deg):.1f} deg" if c.step_deg and np.any(c.step_deg) else "")
            for c in result.attribution.change_points) or "-"),
        ("revisited", f"{100 * result.attribution.revisit_fraction:.0f} %"),
        ("drift rate", "-" if result.attribution.drift.percent_per_m is None else
         f"{result.attribution.drift.percent_per_m:.2f} %/m, {result.attribution.drift.deg_per_m:.3f} deg/m"
         + ("" if result.attribution.drift.noise_floor_m is None else
            f" (above a per-frame floor of {100 * result.attribution.drift.noise_floor_m:.1f} cm, "
            f"{result.attribution.drift.noise_floor_deg:.2f} deg)")),
        ("MME / MPV", f"{result.entropy.mme:.3f} / {result.entropy.mpv_m2:.2e} m^2 (r = {result.entropy.radius_m:g} m)"),
    ]
    if result.trajectory is not None:
        tr = result.trajectory
        rows.append(("ATE / RPE", f"{100 * tr['ate_rmse_m']:.2f} cm / {100 * tr['rpe_trans_rmse_m']:.2f} cm, {tr['rpe_rot_rmse_deg']:.3f} deg"))
    if other is not None:
        rows.append((f"smearing score, revision {other.revision}", f"{1000 * other.smearing_score_m:.2f} mm"))
    if result.verification is not None:
        ver = data["double_wall"]["verified"]
        rows.append(("regions confirmed (Open3D)", f"{ver['regions_confirmed']} / {ver['regions_checked']}; "
                                                   f"{ver['voxels_unconfirmed']} flagged voxels unconfirmed, "
                                                   f"{ver['regions_local']} regions local"))
        rows.append(("flagged, confirmed pose errors", f"{100 * ver['fraction_pose']:.2f} % of evaluated voxels"))
    cov = result.coverage
    if cov is not None:
        why = ", ".join(f"{k.replace('_', ' ')} {100 * v:.0f} %" for k, v in cov.not_evaluated_fractions().items() if v >= 0.005)
        rows.insert(3, ("surface voxels inconsistent", f"{100 * cov.fraction_inconsistent:.2f} % (doubled or smeared)"))
        rows.insert(0, ("coverage", f"{100 * cov.fraction_evaluated:.0f} % of the samples in evaluated voxels"
                                    + (f" (not: {why})" if why else "")))
        labels = {"smearing score": "smearing_score", "surface voxels doubled": "fraction_flagged",
                  "surface voxels inconsistent": "fraction_inconsistent", "drift rate": "drift_rate"}
        rows = [(k, v if k not in labels or cov.measures[labels[k]]["valid"] else f"cannot judge ({v})") for k, v in rows]
    for k, v in rows:
        table.add_row(k, v)
    console.print(table)
    if cov is not None and not cov.valid:
        for reason in cov.reasons:
            console.print(Text(f"cannot judge: {reason}", style="yellow"))
    for k, region in enumerate(dw.regions[:5]):
        console.print(f"  region {k + 1}: {100 * region.separation_m:.1f} +- {100 * region.separation_sigma_m:.1f} cm at "
                      f"{np.round(region.center_m, 2).tolist()}, frames {region.frames_a.min()}-{region.frames_a.max()} vs "
                      f"{region.frames_b.min()}-{region.frames_b.max()}"
                      + ("" if result.verification is None else _verification_note(result.verification[k]))
                      + ("" if result.causes is None else f"; cause: {result.causes[k].cause} ({result.causes[k].explanation})"),
                      highlight=False)
    if result.attribution.revisit_note:
        console.print(Text(result.attribution.revisit_note, style="yellow"))
    if report is not None:
        compare = {f"revision {other.revision}": other, f"revision {result.revision}": result} if other is not None else None
        files = write_report(report, result, compare=compare)
        for name, file in files.items():
            console.print(f"  {name:20s} {file}")
    console.print(_bold("diagnosis: ", json_path))


@app.command()
def view(
    store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")],
    revision: Annotated[Optional[int], typer.Option("--revision", help="Revision (default: the latest).")] = None,
    color: Annotated[str, typer.Option("--color", help="frame (frame id) | revision (how far the correction moved each point) | double-wall (flagged surfaces by separation)")] = "frame",
    out: Annotated[Path, typer.Option("--out", help="Folder for the PNG views when there is no display (created).")] = Path("results/view"),
    voxel_size_m: Annotated[Optional[float], typer.Option("--voxel-size-m", help="Display voxel size (default: 0.02 m RGB-D, 0.2 m LiDAR).")] = None,
    backend: Annotated[str, typer.Option("--backend", help="auto | window | open3d | software | rerun (auto: a window with a display, else Open3D offscreen PNGs, else software PNGs)")] = "auto",
    headless: Annotated[Optional[bool], typer.Option("--headless/--no-headless", help="Force PNG output / a window (default: detected from DISPLAY / WAYLAND_DISPLAY).")] = None,
    reference: Annotated[Optional[int], typer.Option("--reference", help="--color revision: displacement from this revision (default: the viewed revision's parent).")] = None,
) -> None:
    """Show the map of a revision coloured by frame, by correction displacement or by double-wall separation:
    an Open3D window with a display, PNG views (top + two oblique) without one."""
    from driftmap.viewer import BACKENDS, COLOR_MODES, view_store

    color = _choice(color, tuple(COLOR_MODES), "--color")
    backend = _choice(backend, tuple(BACKENDS), "--backend")

    with _open_store(store_path) as store:
        with console.status(f"preparing the {color} view of {store_path}"):
            result = view_store(store, revision=revision, color=color, out_dir=out, voxel_size_m=voxel_size_m,
                                headless=headless, backend=backend, reference_revision=reference)
    if result.fallback_reason:
        err_console.print(Text(f"{result.fallback_reason}; used the software renderer", style="yellow"), highlight=False)
    lo, hi = result.value_range
    console.print(f"revision {result.revision}, colour {result.color} ({result.value_label}: {lo:.4g} .. {hi:.4g}), "
                  f"{result.n_points_shown:,} of {result.n_points_map:,} points (voxel {result.voxel_size_m:g} m), "
                  f"backend {result.backend}")
    if result.n_double_wall_voxels is not None:
        console.print(f"  double-wall voxels flagged: {result.n_double_wall_voxels}")
    for name, path in result.files.items():
        console.print(f"  {name:10s} {path}", highlight=False)


@app.command()
def perturb(
    poses_in: Annotated[Path, typer.Argument(metavar="POSES_IN", help="Pose file to perturb.")],
    poses_out: Annotated[Path, typer.Argument(metavar="POSES_OUT", help="Perturbed pose file (same format).")],
    format: Annotated[str, typer.Option("--format", help="tum | kitti")] = "tum",
    step_frame: Annotated[Optional[int], typer.Option("--step-frame", min=0, help="Row index of the first frame after the step (KITTI: = frame_id).")] = None,
    step_m: Annotated[Optional[str], typer.Option("--step-m", help="Translation step 'x,y,z' (m, world frame).")] = None,
    step_deg: Annotated[Optional[str], typer.Option("--step-deg", help="Rotation step 'rx,ry,rz' (deg, world-frame rotation vector about the step frame's sensor origin).")] = None,
    drift_percent_per_m: Annotated[float, typer.Option("--drift-percent-per-m", help="Translation drift (% of the path travelled).")] = 0.0,
    drift_direction: Annotated[str, typer.Option("--drift-direction", help="World direction of the translation drift 'x,y,z'.")] = "1,0,0",
    drift_deg_per_m: Annotated[float, typer.Option("--drift-deg-per-m", help="Rotation drift (deg per m travelled).")] = 0.0,
    drift_axis: Annotated[str, typer.Option("--drift-axis", help="World axis of the rotation drift 'x,y,z' (through the first position).")] = "0,0,1",
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing POSES_OUT; without it an existing file is refused.")] = False,
) -> None:
    """Write a perturbed copy of a trajectory: a translation/rotation step at a frame and/or a linear drift."""
    from driftmap.diagnostics.perturb import PosePerturbation, parse_vector, perturb_pose_file
    from driftmap.errors import ConfigError

    _check_output(poses_out, "POSES_OUT")
    _refuse_existing(poses_out, "POSES_OUT", overwrite)
    if (step_m is not None or step_deg is not None) and step_frame is None:
        raise ConfigError("--step-m / --step-deg need --step-frame")
    if step_frame is not None and step_m is None and step_deg is None:
        raise ConfigError("--step-frame needs --step-m and/or --step-deg")
    if step_m is None and step_deg is None and not drift_percent_per_m and not drift_deg_per_m:
        raise ConfigError("nothing to perturb: give a step (--step-frame with --step-m/--step-deg) or a drift")
    perturbation = PosePerturbation(
        step_index=step_frame,
        step_m=None if step_m is None else parse_vector(step_m, "--step-m"),
        step_deg=None if step_deg is None else parse_vector(step_deg, "--step-deg"),
        drift_percent_per_m=drift_percent_per_m, drift_direction=parse_vector(drift_direction, "--drift-direction"),
        drift_deg_per_m=drift_deg_per_m, drift_axis=parse_vector(drift_axis, "--drift-axis"),
    )
    result = perturb_pose_file(poses_in, poses_out, perturbation, format=_choice(format, ("tum", "kitti"), "--format"))
    console.print(f"wrote {len(result)} perturbed poses to {poses_out}")


def main() -> None:
    """Console-script entry point: maps driftmap errors to one line and a non-zero exit."""
    try:
        app()
    except DriftmapError as exc:
        if _state["debug"]:
            raise
        _error(str(exc))
    except UnicodeDecodeError as exc:
        if _state["debug"]:
            raise
        _error(f"a file is not UTF-8 text ({exc.reason} at byte {exc.start}); run with --debug to see which")
    except OSError as exc:  # unwritable output, a directory where a file was expected, a full disk ...
        if _state["debug"]:
            raise
        _error(f"{exc.filename}: {exc.strerror}" if exc.filename and exc.strerror else str(exc))
    except KeyboardInterrupt:
        err_console.print(Text("interrupted", style="red"))
        sys.exit(130)


def _error(message: str) -> None:
    err_console.print(Text.assemble(("error:", "red"), f" {message}"), highlight=False, soft_wrap=True)
    sys.exit(1)


if __name__ == "__main__":
    main()
