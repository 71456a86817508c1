"""What ``driftmap batch`` is asked to run: its inputs expanded to one :class:`LogSpec` per log.

An input is a log or data-set folder (or file: an MCAP, a bag), a glob (``logs/2024-*``; expanded here when the
shell did not), or a text file listing logs (``*.txt`` / ``*.list`` / ``*.lst``), one per line, each line a path or
glob and optional per-log options::

    # comments and blank lines are skipped; relative paths are relative to the list file's folder
    robot1/run-007.mcap --topic /lidar/points --pose-from-tf map,base_link
    synthetic/room-03   --sensor lidar --gt synthetic/room-03/groundtruth.txt
    tum/fr1_desk        --format tum --name desk

A mistake in a list file is a :class:`~driftmap.errors.ConfigError` naming the file and the line. Each log gets a
name (its folder or file name, ``--name`` in a list file; a repeated folder name gets ``-2``, ``-3`` ... with a
warning, a repeated ``--name`` is an error): its results go to
``DIR/<name>/``. The same log with the same options given twice is run once.
"""

from __future__ import annotations

import glob
import logging
import math
import re
import shlex
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from driftmap.errors import ConfigError
from driftmap.fleet.folders import MARKER, TMP_DIR

logger = logging.getLogger(__name__)

__all__ = ["LIST_SUFFIXES", "LogSpec", "expand_inputs", "log_name", "parse_log_options", "read_list_file"]

LIST_SUFFIXES = (".txt", ".list", ".lst")
"""A file input with one of these suffixes is a list of logs (no log format driftmap reads is a single such file)."""

RESERVED_NAMES = frozenset({"fleet.json", "fleet.html", "fleet_config.json", "fleet_ranking.png", "fleet_drift.png"})
"""Names a log folder may not take: the batch's own files in ``DIR``."""

#: per-log option of a list file -> (LogSpec field, takes a value)
LIST_OPTIONS: dict[str, tuple[str, bool]] = {
    "--name": ("name", True), "--format": ("format", True), "--sensor": ("sensor", True), "--topic": ("topic", True),
    "--pose-from-tf": ("pose_from_tf", True), "--pose-from-odometry": ("pose_from_odometry", True),
    "--lenient": ("lenient", False), "--period-s": ("period_s", True), "--point-layout": ("point_layout", True),
    "--poses": ("poses", True), "--poses-from-source": ("poses_from_source", False), "--frames": ("frames", True),
    "--gt": ("gt", True), "--gt-format": ("gt_format", True),
}
PATH_OPTIONS = ("poses", "gt")
"""Options whose value is a file (relative to the list file's folder)."""


@dataclass(frozen=True)
class LogSpec:
    """One log of a batch and how to read it (the options ``driftmap build`` / ``diagnose`` take for it)."""

    name: str
    """the log's folder under ``DIR``"""
    input: str
    """the log's path (absolute)"""
    format: str | None = None
    sensor: str | None = None
    topic: str | None = None
    pose_from_tf: str | None = None
    """``PARENT,CHILD``"""
    pose_from_odometry: str | None = None
    lenient: bool = False
    period_s: float | None = None
    point_layout: str | None = None
    poses: str | None = None
    poses_from_source: bool = False
    frames: str | None = None
    gt: str | None = None
    gt_format: str | None = None
    origin: str = field(default="", compare=False)
    """where the log was named (``list.txt:3``, or the argument), for messages"""

    def source_options(self) -> dict[str, Any]:
        """The source options of :func:`driftmap.pipeline.build.build` this log sets."""
        options: dict[str, Any] = {"sensor": self.sensor, "topic": self.topic,
                                   "pose_from_odometry": self.pose_from_odometry, "point_layout": self.point_layout,
                                   "lenient": self.lenient or None}
        if self.pose_from_tf is not None:
            options["pose_from_tf"] = tuple(p.strip() for p in self.pose_from_tf.split(","))
        if self.period_s is not None:
            options["period_ns"] = round(self.period_s * 1e9)
        return {k: v for k, v in options.items() if v is not None}

    def input_paths(self) -> list[str | None]:
        """The files this log reads: the log, its pose file and its ground truth."""
        return [self.input, self.poses, self.gt]

    def options_record(self) -> dict[str, Any]:
        """Everything that decides this log's results apart from the config (hashed for ``--resume``)."""
        return {k: v for k, v in vars(self).items() if k not in ("name", "origin")}


def log_name(path: Path) -> str:
    """The default name of a log: its folder name, or a file's name without its suffix, made safe as a folder name."""
    stem = path.name if path.is_dir() or not path.suffix else path.stem
    name = re.sub(r"[^A-Za-z0-9._+-]+", "_", stem).strip("._") or "log"
    return f"log-{name}" if name in RESERVED_NAMES else name


def _check_value(option: str, value: str, where: str) -> None:
    if option == "--period-s":
        try:
            period = float(value)
        except ValueError:
            raise ConfigError(f"{where}: --period-s: expected seconds, got {value!r}") from None
        if not (math.isfinite(period) and period > 0):
            raise ConfigError(f"{where}: --period-s: the scan period must be a positive number, got {value!r}")
    elif option == "--pose-from-tf" and (len(value.split(",")) != 2 or not all(p.strip() for p in value.split(","))):
        raise ConfigError(f"{where}: --pose-from-tf: expected 'PARENT,CHILD' (two frame names), got {value!r}")
    elif option == "--frames":
        from driftmap.errors import SourceError
        from driftmap.sources.base import parse_frame_slice

        try:
            selection = parse_frame_slice(value)
        except SourceError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        if selection is not None and selection.start is not None and selection.stop is not None \
                and selection.start >= 0 and selection.stop >= 0 and selection.stop <= selection.start:
            raise ConfigError(f"{where}: --frames {value!r} selects no frame (STOP is not after START)")
    elif option == "--gt-format":
        from driftmap.diagnostics.ground_truth import GT_FORMATS

        if value not in GT_FORMATS:
            raise ConfigError(f"{where}: --gt-format: {value!r} is not one of {', '.join(GT_FORMATS)}")
    elif option == "--name":
        if value in RESERVED_NAMES or value in (TMP_DIR, MARKER):
            reserved = ", ".join(sorted(RESERVED_NAMES | {TMP_DIR, MARKER}))
            raise ConfigError(f"{where}: --name: {value!r} is reserved: the batch's folder keeps its own files under "
                              f"that name ({reserved}); choose another name")
        if value.startswith("."):
            raise ConfigError(f"{where}: --name: {value!r} starts with '.': a log's folder name may not (those are "
                              f"the batch's own, hidden files); choose another name")
        if not re.fullmatch(r"[A-Za-z0-9_+-][A-Za-z0-9._+-]*", value):
            raise ConfigError(f"{where}: --name: {value!r} is not a usable folder name (letters, digits, . _ + -)")


def parse_log_options(words: list[str], where: str, base: Path) -> dict[str, Any]:
    """The per-log options of a list-file line (``--opt VALUE``, ``--opt=VALUE`` or a flag) as :class:`LogSpec`
    fields; a file value relative to ``base``. Unknown options and missing values are errors naming ``where``."""
    fields: dict[str, Any] = {}
    k = 0
    while k < len(words):
        word = words[k]
        option, _, inline = word.partition("=")
        if option not in LIST_OPTIONS:
            known = ", ".join(LIST_OPTIONS)
            raise ConfigError(f"{where}: unknown option {word!r} (a list-file line takes a log path, then any of {known})")
        key, takes_value = LIST_OPTIONS[option]
        if key in fields:
            raise ConfigError(f"{where}: {option} is given twice (which one is meant?)")
        if not takes_value:
            if inline:
                raise ConfigError(f"{where}: {option} takes no value")
            fields[key] = True
            k += 1
            continue
        if inline:
            value, k = inline, k + 1
        elif k + 1 < len(words) and not words[k + 1].startswith("--"):
            value, k = words[k + 1], k + 2
        else:
            raise ConfigError(f"{where}: {option} needs a value")
        _check_value(option, value, where)
        if key in PATH_OPTIONS:
            value = str((base / value).absolute())
        fields[key] = float(value) if key == "period_s" else value
    if fields.get("poses") is not None and fields.get("poses_from_source"):
        raise ConfigError(f"{where}: --poses and --poses-from-source both say where the poses come from: give one")
    if fields.get("gt_format") is not None and fields.get("gt") is None:  # as `diagnose` refuses it (trial 17 W6)
        raise ConfigError(f"{where}: --gt-format describes the --gt FILE; give one")
    return fields


def _matches(pattern: str, base: Path, where: str) -> list[Path]:
    """The paths ``pattern`` names (relative to ``base``): a glob expanded (sorted), or the path itself if it exists."""
    path = Path(pattern).expanduser()
    path = path if path.is_absolute() else base / path
    if path.exists():
        return [path]
    if glob.has_magic(pattern):
        found = sorted(Path(p) for p in glob.glob(str(path)))
        if not found:
            raise ConfigError(f"{where}: {pattern!r} matched no log")
        return found
    raise ConfigError(f"{where}: {pattern}: no such log (file or folder)")


def read_list_file(path: Path) -> list[tuple[Path, dict[str, Any], str]]:
    """The logs a list file names: ``(path, per-log options, "FILE:LINE")`` per log, globs expanded."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such list file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the list of logs ({exc})") from exc
    entries = []
    for number, line in enumerate(text.splitlines(), start=1):
        where = f"{path}:{number}"
        try:
            words = shlex.split(line, comments=True)
        except ValueError as exc:
            raise ConfigError(f"{where}: cannot split the line ({exc})") from None
        if not words:
            continue
        if words[0].startswith("--"):
            raise ConfigError(f"{where}: a line starts with the log's path, then its options; got {words[0]!r}")
        options = parse_log_options(words[1:], where, path.parent)
        found = _matches(words[0], path.parent, where)
        if "name" in options and len(found) > 1:
            raise ConfigError(f"{where}: --name names one log, but {words[0]!r} matched {len(found)}")
        entries += [(p, options, where) for p in found]
    return entries


def _expand_one(text: str) -> list[tuple[Path, dict[str, Any], str]]:
    path = Path(text).expanduser()
    if path.suffix.lower() in LIST_SUFFIXES and (path.is_file() or not glob.has_magic(text)):
        return read_list_file(path)
    return [(p, {}, text) for p in _matches(text, Path.cwd(), "input")]


def _unique_names(specs: list[LogSpec], named: set[int]) -> list[LogSpec]:
    """Repeated default names (two folders called ``log``) get ``-2``, ``-3`` ... in input order (so a rerun names
    every log as before), with a warning; a name given with ``--name`` (``named``: the specs' indices) is the
    user's: repeated, it is a :class:`ConfigError` naming both places, never renamed."""
    first: dict[str, LogSpec] = {}
    for k, spec in enumerate(specs):
        if k in named and spec.name in first:
            raise ConfigError(f"{spec.origin}: --name {spec.name!r} is used again (first by {first[spec.name].input} "
                              f"at {first[spec.name].origin}): each log's results need a folder of their own; "
                              f"choose another name")
        first.setdefault(spec.name, spec)
    taken = {s.name for s in specs}
    seen: set[str] = set()
    out = []
    for spec in specs:
        name = spec.name
        if name in seen:
            k = 2
            while f"{spec.name}-{k}" in taken or f"{spec.name}-{k}" in seen:
                k += 1
            name = f"{spec.name}-{k}"
            logger.warning("%s: a log named %r is in the batch already; %s runs as %r (give --name in a list file "
                           "to choose)", spec.origin, spec.name, spec.input, name)
        seen.add(name)
        out.append(spec if name == spec.name else replace(spec, name=name))
    return out


def _refuse_out_among_inputs(out: Path, out_resolved: Path, path: Path, resolved: Path, where: str) -> None:
    """``--out`` may not be inside an input log (its files would land among the log's own, e.g. its frames), nor
    be one, unless it is an earlier batch's folder that a glob matched (then it is skipped)."""
    inside = resolved in out_resolved.parents
    if not inside and not (resolved == out_resolved and not (out_resolved / MARKER).is_file()):
        return
    source = "" if where == str(path) else f" ({where})"
    if inside:
        raise ConfigError(f"--out {out}: is inside the input {path}{source}; a batch may not write into a log it "
                          f"reads (its files would be taken for the log's own): choose an --out outside the inputs")
    raise ConfigError(f"--out {out}: is one of the inputs ({path}{source}); a batch writes its own folder and may not "
                      f"write into a log it reads: choose an --out outside the inputs")


def expand_inputs(inputs: list[str] | tuple[str, ...], *, exclude: Path | None = None) -> list[LogSpec]:
    """One :class:`LogSpec` per log the inputs name, in order (paths, globs, list files; see the module docstring).
    ``exclude``: a folder (the batch's ``--out``) whose own path and contents are never taken as logs.

    Raises :class:`ConfigError` for an input that names nothing, a list-file mistake (naming the line) or no log
    at all."""
    if not inputs:
        raise ConfigError("no inputs: give log folders or files, globs, or a text file listing logs")
    skip = None if exclude is None else exclude.resolve()
    specs: list[LogSpec] = []
    named: set[int] = set()  # the specs whose name was given with --name
    seen: dict[tuple[Any, ...], str] = {}
    for text in inputs:
        for path, options, where in _expand_one(str(text)):
            resolved = path.resolve()
            if skip is not None:
                _refuse_out_among_inputs(exclude, skip, path, resolved, where)
                if (resolved == skip or skip in resolved.parents) and (skip / MARKER).is_file():
                    continue  # an earlier batch's folder (or its contents) that a glob like logs/* matched
                if skip in resolved.parents:  # (hostile trial 28 W6: it read "no log among the inputs")
                    raise ConfigError(f"{where}: the input {path} lies inside --out {exclude}, which is no earlier "
                                      f"batch's folder: the batch would write its results among the logs it reads; "
                                      f"choose an --out outside the inputs")
            spec = LogSpec(name=options.get("name") or log_name(resolved), input=str(resolved),
                           origin=where, **{k: v for k, v in options.items() if k != "name"})
            key = tuple(sorted(spec.options_record().items())) + (spec.name,)
            if key in seen:
                logger.warning("%s: %s is named again with the same options (first at %s): it runs once", where,
                               path, seen[key])
            else:
                seen[key] = where
                if options.get("name"):
                    named.add(len(specs))
                specs.append(spec)
    if not specs:
        raise ConfigError(f"no log among the inputs ({', '.join(map(str, inputs))})")
    return _unique_names(specs, named)
