"""What every command of the ``driftmap`` command line shares: the typer app, the consoles, the option checks
(every integer plain ASCII digits, every number finite, outputs writable and not inside a store, existing files kept
unless ``--overwrite``), the source-option help texts, the progress bar, and opening a store with its recovery events
printed.

Only the ``driftmap.cli`` package prints and exits; the library raises and logs.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import re
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.text import Text
from typer.core import TyperGroup

from driftmap import __version__
from driftmap.errors import DriftmapError, OutputWriteError

_ASCII_INT = re.compile(r"-?[0-9]+")


def strict_int_text(value: Any, param: Any = None) -> Any:
    """``value`` as the command line gave it, refused (a usage error, exit 2) unless it is an optional '-' and ASCII
    digits 0-9. Python's ``int()`` and pydantic's lax integers (which typer parses with) read "1_0" as 10, "+3",
    " 3 " and "3.0" as 3, and ``int()`` reads "٣" or "３" as 3: ``--revision 1_0`` was revision 10. Values that are
    not text (defaults) pass unchanged; a list or tuple (``multiple``, ``nargs``) is checked item by item."""
    if isinstance(value, (list, tuple)):
        for item in value:
            strict_int_text(item, param)
    elif isinstance(value, str) and not _ASCII_INT.fullmatch(value):
        raise typer.BadParameter(f"{value!r} is not an integer (ASCII digits only)", param=param)
    return value


def _is_int(param: Any) -> bool:
    """A command-line parameter parsed as integers: ``int``, ``Optional[int]``, ``list[int]`` or a tuple of ints."""
    descriptor = getattr(param, "type_descriptor", None)  # typer >= 0.2x parses by the annotation (pydantic)
    if descriptor is None:  # older typer on click: INT / IntRange
        return getattr(getattr(param, "type", None), "name", None) in ("integer", "integer range")
    annotation = descriptor.annotation
    if getattr(annotation, "__origin__", None) in (list, tuple):
        args = [a for a in getattr(annotation, "__args__", ()) if a is not Ellipsis]
        return bool(args) and all(a is int for a in args)
    return annotation is int


def _strict_ints(command: Any) -> None:
    """Make every integer parameter of ``command`` (and of its subcommands) take only '-'? and ASCII digits: the
    text is checked before typer converts it, so the option's own range check and its message stay as they are."""
    for param in getattr(command, "params", ()):
        if not _is_int(param) or getattr(param, "_strict_int", False):
            continue

        def checked(ctx: Any, value: Any, _process: Any = param.process_value, _param: Any = param) -> Any:
            return _process(ctx, strict_int_text(value, _param))

        param.process_value = checked
        param._strict_int = True
    for sub in getattr(command, "commands", {}).values():
        _strict_ints(sub)


class StrictIntGroup(TyperGroup):
    """The app's group: on building the command tree, every integer option and argument of every command is made
    strict (:func:`strict_int_text`), so a command or option added later is covered without a flag of its own."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _strict_ints(self)


app = typer.Typer(
    cls=StrictIntGroup,
    name="driftmap",
    help="Multi-frame fusion and drift-aware mapping: frames kept with the poses that produced them.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode=None,  # help texts are plain: "[build] table" stays as written
)
# piped output (logs, other tools) gets wide tables instead of rich's 80-column default
PIPE_WIDTH = None if sys.stdout.isatty() else int(os.environ.get("COLUMNS", "160"))
# no rich markup in printed text: paths and messages may contain brackets ("run[1].tum")
console = Console(width=PIPE_WIDTH, markup=False)
err_console = Console(stderr=True, markup=False)


def bold(label: str, value: object, rest: str = "") -> Text:
    return Text.assemble(label, (str(value), "bold"), rest)


def choice(value: str, allowed: tuple[str, ...], flag: str) -> str:
    """A usage error (exit 2) for an option value outside ``allowed`` (case-insensitive)."""
    v = value.lower()
    if v not in allowed:
        raise typer.BadParameter(f"{value!r} is not one of {', '.join(allowed)}", param_hint=flag)
    return v

def check_output(path: Optional[Path], flag: str, *, folder: bool = False) -> None:
    """Refuse, before any work, an output that cannot be written or must not be: one inside a frame-store folder
    (any store: exports, reports and traces never land among a store's own files), a folder in its way (or, for
    ``folder``, a file), a file where a parent folder must go, or a parent that is not writable (one error line,
    exit 1)."""
    from driftmap.errors import ConfigError

    if path is None:
        return
    from driftmap.store import refuse_inside_store

    refuse_inside_store(path, flag)  # no command writes into a store folder except through the store
    from driftmap.files import refuse_special_file

    refuse_special_file(path, flag)  # before the work, not after it (hostile trial 25 B6)
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


SENSOR_HELP = "Which sensor of a log with several (the synthetic log: depth | lidar)."
TOPIC_HELP = "ROS logs: the PointCloud2 or depth Image topic to read (default: the only one)."
POSE_TF_HELP = "ROS logs: frame poses from TF, 'PARENT,CHILD' (e.g. map,base_link) looked up at each frame's stamp."
POSE_ODOM_HELP = "ROS logs: frame poses from this nav_msgs/Odometry topic (interpolated at each frame's stamp)."
POINT_LAYOUTS = ("auto", "xyzi", "xyz")
POINT_LAYOUT_HELP = ("KITTI-layout .bin scans: auto (decided once for the folder from the file sizes, then the data) | "
                     "xyzi (float32 x, y, z, intensity) | xyz (float32 x, y, z); give it when auto cannot tell.")
LENIENT_HELP = "Skip unreadable frames (each logged with its reason) instead of stopping at the first."
PERIOD_HELP = ("Folders of PLY / PCD clouds without stamps of their own: the scan period in seconds, frame n is "
                "stamped n * S (e.g. 0.5 for a 2 Hz scanner; without it such a folder is assumed 10 Hz, with a warning). "
                "Refused for formats with stamps of their own and for folders that carry stamps (file names, "
                "times.txt, a 4x4 pose file with stamps).")


def source_options(sensor: Optional[str], topic: Optional[str], pose_from_tf: Optional[str],
                    pose_from_odometry: Optional[str], lenient: bool, period_s: Optional[float] = None,
                    point_layout: Optional[str] = None) -> dict:
    """The source options of ``build`` / ``convert`` that were given (checked against the format later)."""
    from driftmap.errors import ConfigError

    period_ns = None
    if period_s is not None:
        if not (math.isfinite(period_s) and period_s > 0):
            raise ConfigError(f"--period-s: the scan period must be a positive number of seconds, got {period_s:g}")
        if round(period_s * 1e9) < 1:
            raise ConfigError(f"--period-s: {period_s:g} s rounds to 0 ns (stamps are whole nanoseconds); the period "
                              f"must be at least 1 ns (1e-09 s)")
        period_ns = round(period_s * 1e9)

    tf = None
    if pose_from_tf is not None:
        parts = [p.strip() for p in pose_from_tf.split(",")]
        if len(parts) != 2 or not all(parts):
            raise ConfigError(f"--pose-from-tf: expected 'PARENT,CHILD' (two frame names), got {pose_from_tf!r}")
        tf = (parts[0], parts[1])
    layout = None if point_layout is None else choice(point_layout, POINT_LAYOUTS, "--point-layout")
    options = {"sensor": sensor, "topic": topic, "pose_from_tf": tf, "pose_from_odometry": pose_from_odometry,
               "lenient": lenient or None, "period_ns": period_ns, "point_layout": layout}
    return {k: v for k, v in options.items() if v is not None}


def finite(value: Any) -> Any:
    """Every number option is finite (click reads 'nan' and 'inf' as floats): the one check at the command line."""
    for v in value if isinstance(value, (list, tuple)) else [value]:
        if v is not None and not math.isfinite(v):
            raise typer.BadParameter(f"must be a finite number, got {v}")
    return value


def finite_within(lo: float, hi: float, unit: str) -> Callable[[Any], Any]:
    """A callback: :func:`finite`, then within ``lo .. hi`` (a usage error naming the bounds and ``unit``; ``hi``
    inf: at least ``lo``). Use it, not click's ``min=``, which runs first and says "greater than or equal to 0" of
    ``nan`` (trial 17)."""
    def check(value: Any) -> Any:
        finite(value)
        if value is not None and not lo <= value <= hi:
            bounds = f">= {lo:g}" if math.isinf(hi) else f"within {lo:g} .. {hi:g}"
            raise typer.BadParameter(f"must be {bounds} {unit}, got {value!r}")
        return value
    return check


def refuse_same_output(outputs: list[tuple[Path, str]], folders: tuple[str, ...] = ()) -> None:
    """Two output options naming one file (one would replace the other), or an output inside another that is a file
    (the flags in ``folders`` name folders, which may hold the others): a one-line error naming both, before any
    work."""
    from driftmap.errors import ConfigError

    seen: dict[Path, str] = {}
    for path, flag in outputs:
        key = Path(os.path.abspath(path)).resolve()
        if key in seen:
            raise ConfigError(f"{path}: {seen[key]} and {flag} name the same file; give each output its own path")
        seen[key] = flag
    for key, flag in seen.items():
        for other, other_flag in seen.items():
            if other_flag not in folders and other != key and key.is_relative_to(other):
                raise ConfigError(f"{key}: {flag} would lie inside {other}, the file {other_flag} writes; give each "
                                  f"output its own path")


def refuse_output_on_input(path: Path, flag: str, inputs: list[tuple[Path, str]]) -> None:
    """An output that is one of the command's own inputs (the same path, a link to it, or a folder holding it)
    would destroy what it is computed from: a one-line error, before any work."""
    from driftmap.errors import ConfigError

    out = Path(os.path.abspath(path)).resolve()
    for source, what in inputs:
        src = Path(os.path.abspath(source)).resolve()
        same = out == src or (out.exists() and src.exists() and os.path.samefile(out, src))
        if same or src.is_relative_to(out):
            raise ConfigError(f"{path}: {flag} is {what} itself; write the output to another path")


def refuse_store_inputs(store_path: Path, outputs: list[tuple[Path, str]]) -> None:
    """No output replaces what the store was built from (its source folder or log, a file in that folder, its
    --poses or --calib file), --overwrite or not: ``--resume`` and ``--poses-from-source`` read them again
    (``export``, ``decide``, ``diagnose``: hostile trial 28 B1 replaced a log's ground truth by a diagnosis)."""
    from driftmap.errors import ConfigError
    from driftmap.pipeline.resume import recorded_inputs

    for source, what in recorded_inputs(store_path):
        src = source.resolve()
        for path, flag in outputs:
            dst = path.resolve()
            if dst == src or (src.is_dir() and src in dst.parents):
                raise ConfigError(f"{flag} {path}: would replace {what} ({source}); write it elsewhere")


def refuse_existing(path: Path, flag: str, overwrite: bool) -> None:
    """An existing output file is kept unless ``--overwrite`` (as ``export`` does)."""
    from driftmap.errors import ConfigError

    if path.is_file() and not overwrite:
        raise ConfigError(f"{path}: already exists ({flag}); pass --overwrite to replace it")


state = {"debug": False}


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
    state["debug"] = debug
    level = logging.DEBUG if debug else logging.INFO if verbose else logging.WARNING
    logging.basicConfig(level=level, format="%(name)s: %(message)s", handlers=[RichHandler(console=err_console, show_path=False)])


def progress_bar() -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        console=err_console, transient=False,
    )


def stage_ticker(progress: Progress, names: dict[str, str] | None = None) -> Callable[[str, int, int | None], None]:
    """The ``progress(stage, done, total)`` callback the library takes: one bar per stage (``names`` renames stages
    for the screen)."""
    tasks: dict[str, int] = {}

    def tick(stage: str, done: int, total: int | None) -> None:
        name = (names or {}).get(stage, stage)
        if name not in tasks:
            tasks[name] = progress.add_task(name, total=total)
        progress.update(tasks[name], completed=done, total=total)
    return tick


KITTI_FRAME_HELP = ("Frame of a KITTI pose file on a store of KITTI Velodyne scans: auto (the data set's own cam0 "
                     "poses.txt is converted to the Velodyne frame, any other file is taken as Velodyne poses) | "
                     "velodyne (rows as they are) | cam0 (converted with calib.txt Tr).")
CALIB_HELP = "KITTI calib.txt (line Tr) for --kitti-frame cam0 (default: the data set's calib.txt)."


def open_store(path: Path, mode: str = "r", *, reads_map: bool = False):
    """Open a store for a command, printing what opening recovered. ``reads_map``: the command reads a revision's map
    (export, diagnose, decide, view): a store whose merge append was interrupted is refused, since its frames stored
    so far sit in every revision's map at their unmerged poses (hostile trial 16 B2); `info` shows it, running the
    append again finishes it. A revision that shows sessions unmerged because damage took the merge revision is
    warned about by :func:`warn_unmerged`, once the command knows which revision it reads."""
    from driftmap.errors import ConfigError
    from driftmap.store.frame_store import FrameStore

    store = FrameStore.open(path, mode)
    if reads_map:
        from driftmap.pipeline.merge_append import interrupted_append

        if (unfinished := interrupted_append(store.path, store.head)) is not None:
            store.close()
            raise ConfigError(f"{path}: {unfinished}; until then its frames would be read at their unmerged poses")
        from driftmap.pipeline.resume import build_running, interrupted_build

        if (unfinished := build_running(store) or interrupted_build(store)) is not None:  # readable as it is
            err_console.print(Text.assemble(("warning:", "yellow"), f" {path}: {unfinished}"), highlight=False)
    for event in store.recovery_events:
        err_console.print(Text.assemble(("recovered:", "yellow"), f" {event}"), highlight=False)
    if store.loss:
        err_console.print(Text.assemble(("recovered earlier:", "yellow"), f" {store.loss}"), highlight=False)
    return store


def warn_unmerged(store, revisions, *, session: int | None = None) -> None:
    """Warn when a revision the command reads shows sessions at their own, unmerged poses because damage took the
    merge revision or the revision restored revision 0's poses (hostile trials 19 W6, 21 W6, 26 W1); not when it
    reads one session (``--session``) or revision 0, which shows the sessions unmerged by design."""
    if session is not None:
        return
    from driftmap.store.unmerged import unmerged_sessions

    for rev in dict.fromkeys(revisions):
        if (found := unmerged_sessions(store, rev)) is not None:
            err_console.print(Text.assemble(("warning:", "yellow"), f" {store.path}: {found}"), highlight=False)


_OS_HINTS = {
    errno.ENOSPC: "the disk is full: free space or write elsewhere",
    errno.EDQUOT: "the disk quota is used up: free space or write elsewhere",
    errno.EROFS: "the file system is mounted read-only: write elsewhere",
    errno.EACCES: "no permission to write there: write elsewhere",
}


def os_error_hint(exc: OSError) -> str | None:
    """What to do about a full, read-only or forbidden disk (None for other OS errors)."""
    return _OS_HINTS.get(exc.errno or -1)


@contextmanager
def writing_output(path: Path, flag: str) -> Iterator[None]:
    """An ``OSError`` while writing ``path`` (``flag``) that names no file (a full disk raises from ``write()``
    without one) becomes an :class:`OutputWriteError` naming the output, with what to do for a full or read-only
    disk; driftmap's own errors pass through."""
    try:
        yield
    except DriftmapError:
        raise
    except OSError as exc:
        hint = os_error_hint(exc)
        where = exc.filename or path
        reason = exc.strerror or str(exc)
        raise OutputWriteError(f"{where}: writing {flag} failed: {reason}" + (f"; {hint}" if hint else ""),
                               path=where, errno=exc.errno) from exc


def general_settings(config: Path | None, command: str, **overrides: Any) -> Any:
    """:meth:`DriftmapConfig.load` of ``--config`` for a command that reads only its general tables (``depth``,
    ``map``, ``volume``, ``decide``), with the rest of the file checked as ``build`` checks it, so that a misspelled
    table (``[volum]``) or a stray key is refused, naming the file and the key, instead of silently changing nothing
    (hostile trial 26 B2); a file holding build settings only (no general table) is refused as well: nothing in it
    applies to ``command``."""
    from driftmap.config import GENERAL_TABLES, DriftmapConfig, refuse_unread_tables, split_config_file
    from driftmap.errors import ConfigError
    from driftmap.pipeline.build_config import BuildConfig

    settings = DriftmapConfig.load(config, **overrides)
    if config is None:
        return settings
    general, build, prefix = split_config_file(config)
    BuildConfig.load(config)  # the build settings (a bare file's every key) as build takes them: typos named
    if not prefix and build:
        raise ConfigError(f"{config}: holds no [{'] / ['.join(GENERAL_TABLES)}] table, only build settings "
                          f"({', '.join(sorted(build))}), none of which applies to {command}: put its settings in "
                          f"those tables (driftmap config --show lists them)")
    refuse_unread_tables(config, command)
    return settings
