"""Commands that make data and stores: ``demo``, ``config``, ``synth``, ``convert``, ``build``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer
from rich.table import Table
from rich.text import Text

from driftmap.cli.common import (
    CALIB_HELP,
    KITTI_FRAME_HELP,
    LENIENT_HELP,
    PERIOD_HELP,
    POINT_LAYOUT_HELP,
    POSE_ODOM_HELP,
    POSE_TF_HELP,
    SENSOR_HELP,
    TOPIC_HELP,
    app,
    bold,
    check_output,
    choice,
    console,
    err_console,
    finite,
    finite_within,
    progress_bar,
    refuse_existing,
    source_options,
    stage_ticker,
    writing_output,
)
from driftmap.errors import DriftmapError
from driftmap.store import refuse_inside_store
from driftmap.store.layout import MANIFEST

if TYPE_CHECKING:
    from driftmap.sources.synthetic import SyntheticLogConfig


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", help="Results folder (created).")] = Path("results/demo"),
    frames: Annotated[Optional[int], typer.Option("--frames", min=3, help="Use only the first N frames (at least 3: the ATE against the ground truth needs them).")] = None,
    log: Annotated[Optional[Path], typer.Option("--log", help="Another synthetic log folder instead of the embedded one.")] = None,
) -> None:
    """Run the whole story on the embedded synthetic drifting-robot log: build -> diagnose -> loop closure
    -> diagnose again -> exports -> report."""
    from driftmap.demo import region_lines, run_demo, summary_rows

    check_output(out, "--out", folder=True)

    with progress_bar() as progress:
        tick = stage_ticker(progress)

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
    console.print(bold("report: ", result.files.get("report_html", "-")))
    console.print(bold("results: ", result.out_dir))


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
    build_cfg = BuildConfig.load(file)
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


MAX_DERIVED_SYNTH_FRAMES = 20_000
"""``synth``: a frame count derived from the speed and period (not given with --frames) above this is a typo."""
MIN_DERIVED_SYNTH_MOVING_SCANS = 20
"""``synth``: a frame count derived from the speed and period must leave at least this many moving scans, else the
odometry has too few frames to follow the path (the robot would jump metres or turn by tens of degrees from frame to
frame: a ``--speed-m-per-s 1e9`` or ``--period-s 100`` wrote a 2-frame log). The smallest logs known to track are
the 2 Hz ones (docs/synthetic-log.md: 24 moving scans in the room, the LiDAR); at this floor the room's robot turns
20 deg between frames. Below about 40 frames the room's depth camera already loses track (docs/fleet.md): a warning."""
MIN_DEPTH_ROOM_MOVING_SCANS = 39
"""``synth``: a room log whose derived count leaves fewer moving scans than the fleet's 40-frame logs warns that the
depth-camera odometry may lose track (the LiDAR, ``--lidar`` and ``build --sensor lidar``, tracks them)."""


def _standing_scans(cfg: SyntheticLogConfig) -> list[str]:
    """The options that add stationary, stop and turn scans to a derived frame count (as given)."""
    from driftmap.sources.synthetic_motion import scans_per_turn, turn_fractions

    parts = []
    if cfg.stationary_start_frames:
        parts.append(f"--stationary-start {cfg.stationary_start_frames}")
    if cfg.stops:
        parts.append(f"--stops {cfg.stops} x --stop-frames {cfg.stop_frames}")
    turns = len(turn_fractions(cfg))
    if turns:
        which = f"--turns {cfg.turns_in_place}" if cfg.turns_in_place else f"{turns} x --turn-at"
        back = "" if scans_per_turn(cfg) == cfg.turn_in_place_frames else " x 2 (each turns back)"
        parts.append(f"{which} x --turn-frames {cfg.turn_in_place_frames}{back}")
    return parts


def _check_derived_frames(cfg: SyntheticLogConfig, speed_given: bool, period_given: bool) -> None:
    """A frame count ``synth`` derived (no ``--frames``) is refused above :data:`MAX_DERIVED_SYNTH_FRAMES` or with fewer
    moving scans than :data:`MIN_DERIVED_SYNTH_MOVING_SCANS`, naming the count, what it is made of and the options
    that set it; a room log under :data:`MIN_DEPTH_ROOM_MOVING_SCANS` moving scans is written with a warning."""
    from driftmap.errors import ConfigError
    from driftmap.sources.synthetic import moving_scans, non_moving_scans, path_length_m

    n, moving, standing = cfg.n_frames, moving_scans(cfg), non_moving_scans(cfg)
    path = path_length_m(cfg)
    period = cfg.frame_period_ns / 1e9
    speed = f"--speed-m-per-s {cfg.speed_m_per_s:g}" if speed_given else f"the {cfg.scene}'s {cfg.speed_m_per_s:.3g} m/s"
    apart = f"--period-s {period:g}" if period_given else f"the {cfg.scene}'s {period:g} s period"
    made_of = (f"1 + {moving:,} moving scan{'s' * (moving != 1)}: the {path:.3g} m path at {speed} with {apart}, "
               f"{path / moving:.3g} m a scan")
    parts = _standing_scans(cfg)
    if parts:
        made_of += f"; + {standing:,} standing and turning scans: {', '.join(parts)}"
    if n > MAX_DERIVED_SYNTH_FRAMES:
        advice = []
        if 1 + moving > MAX_DERIVED_SYNTH_FRAMES // 2 or not parts:
            advice.append("a faster --speed-m-per-s or a longer --period-s")
        if parts:
            advice.append("fewer stationary, stop or turn scans")
        raise ConfigError(f"the options given need {n:,} frames ({made_of}), more than the "
                          f"{MAX_DERIVED_SYNTH_FRAMES:,} a derived frame count may reach: give "
                          f"{' or '.join(advice)}, or --frames N for a log that long on purpose")
    if moving < MIN_DERIVED_SYNTH_MOVING_SCANS:
        raise ConfigError(f"the options given derive only {n:,} frames ({made_of}): too few for the odometry to follow "
                          f"the path, which needs at least {MIN_DERIVED_SYNTH_MOVING_SCANS} moving scans: give a slower "
                          f"--speed-m-per-s or a shorter --period-s" + ("" if speed_given else
                          ", or --frames N to spread the path over N frames"))
    if cfg.scene == "room" and moving < MIN_DEPTH_ROOM_MOVING_SCANS:
        err_console.print(Text.assemble(("warning:", "yellow"), f" {n:,} frames ({made_of}): the room's robot turns "
                                        f"{360.0 * cfg.loop_turns / moving:.0f} deg from frame to frame, further than "
                                        f"the depth-camera odometry follows (below about 40 frames it loses track); "
                                        f"the LiDAR (--lidar, then build --sensor lidar) tracks them"), highlight=False)


@app.command("synth")
def synth(
    out: Annotated[Path, typer.Argument(help="Folder to write the synthetic log to (with --fleet: a folder of N log folders).")],
    frames: Annotated[Optional[int], typer.Option("--frames", min=2, max=1_000_000, help="Number of frames (default: 60 in the room, 245 on the street; with --period-s, --stationary-start, --stops or turns: what the scene's speed needs).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 7,
    lidar: Annotated[bool, typer.Option("--lidar/--no-lidar", help="Also simulate a 16-beam spinning LiDAR (implied by --lidar-pattern rosette and --point-times).")] = False,
    yaw_drift_deg_per_m: Annotated[Optional[float], typer.Option("--yaw-drift-deg-per-m", callback=finite_within(-360.0, 360.0, "deg per m"), help="Odometry yaw drift (default: 0.6 in the room, 0.02 on the street; within +-360).")] = None,
    scale_drift_percent: Annotated[Optional[float], typer.Option("--scale-drift-percent", callback=finite, help="Odometry scale drift (default: 1.0).")] = None,
    scene: Annotated[str, typer.Option("--scene", help="room (a furnished room, a depth camera and with --lidar a 16-beam LiDAR) | street (a city block loop, a 32-beam car LiDAR; defaults: 245 frames, 0.02 deg/m yaw drift, 1 % scale drift).")] = "room",
    period_s: Annotated[Optional[float], typer.Option("--period-s", callback=finite_within(0.001, math.inf, "s"), help="Time between frames/scans in seconds (default: 0.2 in the room, 0.1 on the street; 0.5-0.05 for 2-20 Hz). The speed stays the scene's unless --frames or --speed-m-per-s is given: at 2 Hz a scan moves 5 times as far as at 10 Hz.")] = None,
    speed_m_per_s: Annotated[Optional[float], typer.Option("--speed-m-per-s", callback=finite_within(0.001, math.inf, "m/s"), help="Speed along the path while moving (default: the scene's, 0.59 m/s in the room, 10 m/s on the street); the frame count follows from it (not with --frames): at least 20 moving scans, at most 20,000 frames.")] = None,
    stationary_start: Annotated[int, typer.Option("--stationary-start", min=0, metavar="N", help="The first N scans stand at the start pose (each a new noise draw); motion starts at frame N.")] = 0,
    stops: Annotated[int, typer.Option("--stops", min=0, metavar="K", help="K stops at evenly spaced places of the path (fractions j / (K + 1)); give --stop-frames.")] = 0,
    stop_frames: Annotated[int, typer.Option("--stop-frames", min=0, metavar="M", help="Scans each stop lasts.")] = 0,
    turn_deg_per_frame: Annotated[float, typer.Option("--turn-deg-per-frame", callback=finite, metavar="DEG", help="Yaw per scan of the in-place turns (e.g. 45 or 50; + counter-clockwise; |DEG| < 180).")] = 0.0,
    turn_frames: Annotated[int, typer.Option("--turn-frames", min=0, metavar="F", help="Scans each in-place turn lasts at --turn-deg-per-frame (8 x 45 = one full turn); if they make no whole turn, the robot turns back as many scans.")] = 0,
    turns: Annotated[int, typer.Option("--turns", min=0, metavar="K", help="K in-place turns at evenly spaced places of the path (fractions j / (K + 1)).")] = 0,
    turn_at: Annotated[Optional[list[float]], typer.Option("--turn-at", callback=finite, metavar="FRACTION", help="An in-place turn at this fraction (0-1) of the path, instead of --turns; repeat for more.")] = None,
    lidar_pattern: Annotated[str, typer.Option("--lidar-pattern", help="spinning (beams x azimuths) | rosette (a Livox-like non-repetitive scanner: 70 deg circular field of view along x, the pattern rotating from scan to scan).")] = "spinning",
    points_per_scan: Annotated[Optional[int], typer.Option("--points-per-scan", min=1, help="Points per rosette scan (default: 24000).")] = None,
    point_times: Annotated[bool, typer.Option("--point-times/--no-point-times", help="Per-point capture times: each LiDAR point is rendered from the moving sensor's pose at its time, stored in lidar/NNNNNN.time.bin (int64 ns after the scan's start stamp).")] = False,
    door_open: Annotated[bool, typer.Option("--door-open", help="The room's door (+x wall) stands open onto a corridor (the default room has it closed): a first session for 'changed' in diagnose of a merged store.")] = False,
    move_chair: Annotated[bool, typer.Option("--move-chair", help="The room's chair stands before the -x wall instead of near the -y wall: with the default closed door, the second session of a world that changed.")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an earlier synthetic log in OUT (its stale frame files are removed); without it an existing log is refused. A folder holding anything else is always refused.")] = False,
    fleet: Annotated[Optional[int], typer.Option("--fleet", min=1, max=1000, metavar="N", help="Write N small room logs OUT/room-00/ ... (40 frames at 200 x 150 unless --frames; seeds from --seed on; drift rates, odometry step and loop length differ from log to log) for 'driftmap batch OUT/*'. Takes --frames, --seed, --lidar, --broken and --overwrite.")] = None,
    broken: Annotated[int, typer.Option("--broken", min=0, max=1000, metavar="K", help="With --fleet: also K logs broken on purpose (OUT/broken-00-truncated-depth/, a missing or a cut synthetic.json, in turn).")] = 0,
) -> None:
    """Generate a synthetic drifting-robot log (deterministic for a given seed); with --fleet, N of them."""
    from driftmap.sources.synthetic import SyntheticLogConfig, generate_synthetic_log

    scene = choice(scene, ("room", "street"), "--scene")
    pattern = choice(lidar_pattern, ("spinning", "rosette"), "--lidar-pattern")
    if fleet is not None or broken:
        not_taken = {"--scene": scene != "room", "--yaw-drift-deg-per-m": yaw_drift_deg_per_m is not None,
                     "--scale-drift-percent": scale_drift_percent is not None, "--period-s": period_s is not None,
                     "--speed-m-per-s": speed_m_per_s is not None, "--stationary-start": stationary_start,
                     "--stops": stops or stop_frames, "--turns": turns or turn_at or turn_frames or turn_deg_per_frame,
                     "--lidar-pattern": pattern != "spinning", "--points-per-scan": points_per_scan is not None,
                     "--point-times": point_times, "--door-open": door_open, "--move-chair": move_chair}

        from driftmap.cli.batch_cmds import synth_fleet_command

        synth_fleet_command(out, fleet, broken, frames, seed, lidar, overwrite, [k for k, v in not_taken.items() if v])
        return
    if scene != "room" and (door_open or move_chair):
        raise typer.BadParameter("the door and the chair are the room's (--scene room)",
                                 param_hint="--door-open" if door_open else "--move-chair")
    if stop_frames and not stops:  # (hostile trial 28 W8: taken, and a log without a stop written)
        raise typer.BadParameter("sets how long each stop lasts: give --stops K with it", param_hint="--stop-frames")
    if (turn_deg_per_frame or turn_frames) and not (turns or turn_at):
        raise typer.BadParameter("sets the in-place turns: give --turns K or --turn-at FRACTION with it",
                                 param_hint="--turn-deg-per-frame" if turn_deg_per_frame else "--turn-frames")
    if frames is not None and speed_m_per_s is not None:
        raise typer.BadParameter("give the frame count or the speed, not both (the speed sets the frame count)",
                                 param_hint="--speed-m-per-s")
    # without --frames the log keeps the scene's speed: stationary, stop and turn scans are added, a period changes
    # the frame count (not the speed); the speed is given to the config at once, so that its 60 default frames are
    # never checked against scans they were never meant to hold
    changes_frames = period_s is not None or stationary_start or stops or turns or turn_at
    derived = speed_m_per_s is not None or (frames is None and bool(changes_frames))
    if derived and speed_m_per_s is None:
        speed_m_per_s = (SyntheticLogConfig.street() if scene == "street" else SyntheticLogConfig()).default_speed_m_per_s()
        speed_given = False
    else:
        speed_given = speed_m_per_s is not None
    given = {"seed": seed, "n_frames": frames, "yaw_drift_deg_per_m": yaw_drift_deg_per_m,
             "scale_drift_percent": scale_drift_percent, "speed_m_per_s": speed_m_per_s}
    motion = {"stationary_start_frames": stationary_start, "stops": stops, "stop_frames": stop_frames,
              "turn_in_place_deg_per_frame": turn_deg_per_frame, "turn_in_place_frames": turn_frames,
              "turns_in_place": turns, "turn_in_place_at": tuple(turn_at or ()),
              "lidar_pattern": pattern, "lidar_point_times": point_times}
    if door_open or move_chair:
        motion.update(door_open=door_open, chair_moved=move_chair)
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
    if derived:
        _check_derived_frames(cfg, speed_given, period_s is not None)
    refuse_inside_store(out, "OUT")
    with console.status(f"ray-casting the synthetic {scene}: {cfg.n_frames:,} frames"), \
            writing_output(out, "the synthetic log"):
        path = generate_synthetic_log(out, cfg, overwrite=overwrite)
    console.print(bold("synthetic log: ", path.resolve()))
    console.print(f"{cfg.n_frames} frames, {cfg.frame_period_ns / 1e9:g} s apart")


# ------------------------------------------------------------------------------------------ sources / build


@app.command()
def convert(
    source: Annotated[Path, typer.Argument(help="Data-set folder or log to convert.")],
    out: Annotated[Path, typer.Argument(metavar="OUT.mcap", help="MCAP file to write (ROS 2 messages).")],
    format: Annotated[Optional[str], typer.Option("--format", help="Source format (default: detected).")] = None,
    frames: Annotated[Optional[str], typer.Option("--frames", help="START:STOP[:STEP] of the source's frames (Python slicing: a negative index counts from the end, -3: is the last three).")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing OUT.mcap; without it an existing file is refused before anything is read.")] = False,
    sensor: Annotated[Optional[str], typer.Option("--sensor", help=SENSOR_HELP)] = None,
    topic: Annotated[Optional[str], typer.Option("--topic", help=TOPIC_HELP)] = None,
    pose_from_tf: Annotated[Optional[str], typer.Option("--pose-from-tf", help=POSE_TF_HELP)] = None,
    pose_from_odometry: Annotated[Optional[str], typer.Option("--pose-from-odometry", help=POSE_ODOM_HELP)] = None,
    lenient: Annotated[bool, typer.Option("--lenient", help=LENIENT_HELP)] = False,
    period_s: Annotated[Optional[float], typer.Option("--period-s", callback=finite, help=PERIOD_HELP)] = None,
    point_layout: Annotated[Optional[str], typer.Option("--point-layout", help=POINT_LAYOUT_HELP)] = None,
    pixel_stride: Annotated[Optional[int], typer.Option("--pixel-stride", min=1, max=64, metavar="N", help="Depth images: back-project every N-th pixel in both directions (default: as build reads them, 2 for images 640 px wide or more, else 1; 1 keeps every pixel). A build of the MCAP keeps every point it holds.")] = None,
) -> None:
    """Convert any source to an MCAP log (ROS 2 PointCloud2 / CameraInfo / TF) that Foxglove opens."""
    from driftmap.export.mcap import convert as convert_source
    from driftmap.pipeline.build import check_source_options

    format = _source_format(source, format)
    check_output(out, "OUT.mcap")
    _refuse_inside_source(out, source)
    if out.suffix.lower() != ".mcap":
        raise typer.BadParameter(f"{out}: convert writes an MCAP log; name it OUT.mcap", param_hint="OUT.mcap")
    refuse_existing(out, "OUT.mcap", overwrite)
    options = source_options(sensor, topic, pose_from_tf, pose_from_odometry, lenient, period_s, point_layout)
    check_source_options(source, format, options)
    with console.status(f"converting {source}"), writing_output(out, "OUT.mcap"):
        summary = convert_source(source, out, format=format, frames=frames, pixel_stride=pixel_stride, **options)
    extra = {k: v for k, v in summary.items()
             if k not in ("out", "source", "frames", "points", "bytes", "skipped") and not isinstance(v, (dict, list))}
    console.print(f"wrote {out} ({summary.get('bytes', 0) / 1e6:.1f} MB): {summary.get('frames')} frames, "
                  f"{summary.get('points', 0):,} points from {summary.get('source')}"
                  + (f"; {summary['skipped']} frames skipped (see the log)" if summary.get("skipped") else "")
                  + ("; " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in extra.items()) if extra else ""),
                  highlight=False)


def _refuse_inside_source(out: Path, source: Path) -> None:
    """An output inside the source folder would become one of its frames (or replace one): refused, --overwrite or
    not (the source is never written)."""
    from driftmap.errors import ConfigError

    src, dst = source.resolve(), out.resolve()
    if src.is_dir() and src in dst.parents:
        raise ConfigError(f"{out}: is inside the source folder {source}; the next read of the folder would take it for "
                          f"a frame (or it would replace one): write it elsewhere")


def _load_build_config(path: Optional[Path]):
    from driftmap.pipeline.build import BuildConfig

    return BuildConfig.load(path)


def _source_format(source: Path, format: Optional[str]) -> Optional[str]:
    """``--format``: a registered source format (a usage error otherwise)."""
    from driftmap.sources.base import registered_formats

    return choice(format, tuple(sorted(registered_formats())), "--format") if format is not None else None


def _with_depth_scale_hint(exc: Exception, source: Path, format: Optional[str]) -> DriftmapError:
    """A :class:`DepthScaleError` from ``build``, with the command line's way to fix it."""
    from driftmap.errors import DepthScaleError
    from driftmap.pipeline.build import detect_format
    from driftmap.sources.base import accepted_options, registered_formats

    assert isinstance(exc, DepthScaleError)
    fmt = detect_format(source, format)
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


def _given_poses_row(check: dict | None) -> str:
    """``yes (8 frame pairs)`` / ``NO: 8 of 8 frame pairs disagree`` / ``cannot judge (2 of 8 pairs decide)`` (too few
    frame pairs overlap enough to decide) / ``-`` (odometry's poses, or no frame pair to check)."""
    if check is not None and check.get("error"):
        return "not checked (see the warning)"
    spikes = (check or {}).get("spike_frames") or []
    but = (f"; but frame{'s' if len(spikes) > 1 else ''} {', '.join(str(f) for f in spikes[:5])}"
           f"{' ...' if len(spikes) > 5 else ''} jump{'' if len(spikes) > 1 else 's'} away and back (a corrupt pose row?)"
           if spikes else "")
    if check is None:
        return "-" + but
    if check.get("consistent") is None:
        pairs = check.get("pairs") or []
        slid = sum(1 for p in pairs if p.get("slid"))
        why = f", {slid} slid along repeated structure" if slid else ""
        return f"cannot judge ({check.get('n_decisive', 0)} of {len(pairs)} pairs decide{why}){but}" if pairs else "-" + but
    if check["consistent"]:
        return f"yes ({check['n_decisive']} frame pairs){but}"
    mounting = check.get("mounting_rotation") or {}
    if mounting.get("explains") and 2 * check["n_disagreeing"] < max(check["n_decisive"], 6):
        return (f"NO: the {check['n_decisive']} frame pairs fit a sensor mounted turned by "
                f"{mounting['angle_deg']:.1f} deg{but}")
    scale = check.get("step_scale") or {}
    if (scale.get("explains") and 0.2 < scale["factor"] < 5.0  # (beyond: a unit mistake, named in the warning)
            and (2 * check["n_disagreeing"] < max(check["n_decisive"], 6) or scale.get("named"))):
        why = "a depth scale?" if check.get("sensor_kind", "depth_camera") == "depth_camera" else "a unit or scale?"
        return f"NO: the {scale['n_pairs']} frame pairs' steps are {scale['factor']:.2f} times the file's ({why}){but}"
    return f"NO: {check['n_disagreeing']} of {check['n_decisive']} frame pairs disagree{but}"


def _tracking_counts(tracking: dict) -> str:
    """``78 / 1 / 0`` frames whose odometry registration was ok / recovered / flagged (``-`` without records)."""
    if not tracking.get("frames"):
        return "-"
    by = tracking["by_status"]
    return f"{by.get('ok', 0) + by.get('first', 0)} / {by.get('recovered', 0)} / {len(tracking['flagged'])}"


# longer than 80 lines: 30 of them are the typer options, one per flag, with their help text (the CLI contract)
@app.command()
def build(
    source: Annotated[Path, typer.Argument(help="Data-set folder or log.")],
    out: Annotated[Path, typer.Option("--out", help="Store directory to create (or continue with --resume).")],
    format: Annotated[Optional[str], typer.Option("--format", help="Source format (default: detected).")] = None,
    config: Annotated[Optional[Path], typer.Option("--config", help="Config file (JSON or TOML): its [build] table (the build.* keys 'driftmap config' lists) and [depth] table, or a bare build config (the whole file); DRIFTMAP_DEPTH__* environment variables and --depth-scale override the [depth] table.")] = None,
    depth_scale: Annotated[Optional[float], typer.Option("--depth-scale", callback=finite, help="Depth-image units per metre (1000: millimetres, TUM 5000) for depth sources that take one (7-Scenes, TUM, Redwood / ICL-NUIM); default: the format's own (depth.depth_scale).")] = None,
    intrinsics: Annotated[Optional[str], typer.Option("--intrinsics", help="Depth camera intrinsics 'fx,fy,cx,cy[,width,height]', a TUM setup fr1|fr2|fr3, or an Open3D intrinsics JSON, for sources that take them (7-Scenes, TUM, Redwood / ICL-NUIM); default: the source's own (depth.intrinsics).")] = None,
    sensor: Annotated[Optional[str], typer.Option("--sensor", help=SENSOR_HELP)] = None,
    topic: Annotated[Optional[str], typer.Option("--topic", help=TOPIC_HELP)] = None,
    pose_from_tf: Annotated[Optional[str], typer.Option("--pose-from-tf", help=POSE_TF_HELP + " With --poses-from-source they become revision 0.")] = None,
    pose_from_odometry: Annotated[Optional[str], typer.Option("--pose-from-odometry", help=POSE_ODOM_HELP + " With --poses-from-source they become revision 0.")] = None,
    lenient: Annotated[bool, typer.Option("--lenient", help=LENIENT_HELP)] = False,
    period_s: Annotated[Optional[float], typer.Option("--period-s", callback=finite, help=PERIOD_HELP)] = None,
    point_layout: Annotated[Optional[str], typer.Option("--point-layout", help=POINT_LAYOUT_HELP)] = None,
    poses: Annotated[Optional[Path], typer.Option("--poses", help="Use these poses (format detected: TUM, EuRoC and 4x4 blocks with stamps by stamp; KITTI and 4x4 blocks without stamps row = frame_id; Redwood .log by its frame ids).")] = None,
    poses_from_source: Annotated[bool, typer.Option("--poses-from-source", help="Use the source's own poses (log odometry or ground truth).")] = False,
    no_loop_closure: Annotated[bool, typer.Option("--no-loop-closure", help="Skip loop closure and the pose graph.")] = False,
    frames: Annotated[Optional[str], typer.Option("--frames", help="START:STOP[:STEP] of the source's frames (Python slicing: a negative index counts from the end, -3: is the last three).")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue a build that was interrupted.")] = False,
    kitti_frame: Annotated[str, typer.Option("--kitti-frame", help=KITTI_FRAME_HELP)] = "auto",
    calib: Annotated[Optional[Path], typer.Option("--calib", help=CALIB_HELP)] = None,
    max_dt_ms: Annotated[float, typer.Option("--max-dt-ms", callback=finite_within(0.0, math.inf, "ms"), help="--poses TUM file: a row is a frame's pose when it is the nearest within this (ms; 20, as TUM's associate.py; 'correct' defaults to 10).")] = 20.0,
    threads: Annotated[Optional[int], typer.Option("--threads", min=1, help="Registration threads of the odometry and the loop closure (build.num_threads; default: the config's, 2). With 1 the same input gives the same poses, every revision, to the bit; with more, the threads' partial sums arrive in varying order and builds differ by millimetres.")] = None,
) -> None:
    """Build a drift-corrected map: odometry, verified loop closures, GTSAM pose graph, re-transform."""
    from driftmap.config import DriftmapConfig
    from driftmap.errors import ConfigError, DepthScaleError
    from driftmap.pipeline.build import build as run_build

    format = _source_format(source, format)
    refuse_inside_store(out, "--out", output_is_store=True)  # --resume continues a store; none is made inside one
    _refuse_inside_source(out, source)  # as convert, export and batch do
    from driftmap.store.frame_store import creation_leftovers

    if out.is_dir() and not (out / MANIFEST).exists() and any(out.iterdir()) and not creation_leftovers(out):
        raise ConfigError(f"--out {out}: exists and is not a driftmap store (it is not empty: no {MANIFEST}); "
                          f"choose another --out, or empty the folder")
    options = source_options(sensor, topic, pose_from_tf, pose_from_odometry, lenient, period_s, point_layout)
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
    if config is not None:
        from driftmap.config import refuse_unread_tables

        refuse_unread_tables(config, "build")
    if threads is not None:
        from driftmap.config import check_threads

        cfg = cfg.model_copy(update={"num_threads": check_threads(threads, "--threads")})
    with progress_bar() as progress:
        tick = stage_ticker(progress)

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
        ("given poses fit the frames", _given_poses_row(result.given_poses_check)),
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
    console.print(bold("store: ", Path(result.store).resolve(), " (build_config.json and build_summary.json saved in it)"))
