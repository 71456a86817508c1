"""Which options a source takes, and opening the source of a build with them: the command line's source options
(``--sensor``, ``--topic``, ``--pose-from-tf``, ``--pose-from-odometry``, ``--lenient``, ``--period-s``) and the
``depth.*`` settings, each checked against the format's own opener before anything is read or stored."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from driftmap.errors import ConfigError, SourceError
from driftmap.pipeline.build_config import BuildConfig
from driftmap.sources.base import FrameSource, accepted_options, auto_pixel_stride, first_depth_frame, open_source, registered_formats

logger = logging.getLogger(__name__)


#: the depth options (``DepthConfig.source_options``) and the setting that names each in messages
DEPTH_OPTION_SETTINGS = {"min_depth_m": "depth.min_depth_m", "max_depth_m": "depth.max_depth_m",
                          "depth_scale": "depth.depth_scale (--depth-scale)", "sensor_range_m": "depth.check_scale = false",
                          "intrinsics": "depth.intrinsics (--intrinsics)"}


def detect_format(path: Path, format: str | None) -> str | None:
    if format is not None:
        return format
    for spec in registered_formats().values():
        try:
            if spec.detect(path):
                return spec.name
        except Exception:  # noqa: BLE001 - detectors must not hide each other
            continue
    return None


#: source options the command line offers (``build`` / ``convert``) and the flag that sets each
SOURCE_OPTION_FLAGS = {"sensor": "--sensor", "topic": "--topic", "pose_from_tf": "--pose-from-tf",
                       "pose_from_odometry": "--pose-from-odometry", "lenient": "--lenient", "period_ns": "--period-s",
                       "point_layout": "--point-layout"}


#: why a format may not take a source option, added to the refusal
SOURCE_OPTION_REFUSALS = {"period_ns": "--period-s sets the stamps of a folder of PLY / PCD clouds (cloud_folder) that "
                                        "has none; format {fmt} stamps its frames itself (docs/sources-datasets.md)"}


def show_source_option(name: str, value: Any) -> str:
    """A source option as the command line gives it (``--period-s 0.5`` for ``period_ns=500000000``)."""
    if name == "period_ns":
        return f"--period-s {int(value) / 1e9:g}"
    return f"{SOURCE_OPTION_FLAGS.get(name, name)} {value}"


def source_params(path: Path, format: str | None) -> tuple[str | None, frozenset[str]]:
    """The format of ``path`` (given or detected) and the options its opener takes."""
    fmt = detect_format(path, format)
    opener = registered_formats()[fmt].open if fmt in registered_formats() else None
    return fmt, accepted_options(opener) if opener is not None else frozenset()


def check_source_options(path: Path, format: str | None, options: dict[str, Any]) -> None:
    """Refuse source options (``SOURCE_OPTION_FLAGS``) the format of ``path`` does not take, naming the flags."""
    fmt, params = source_params(path, format)
    if fmt is None or not options:
        return
    refused = [k for k in options if k not in params]
    if refused:
        takes = [SOURCE_OPTION_FLAGS[k] for k in SOURCE_OPTION_FLAGS if k in params]
        reasons = "".join(f"; {SOURCE_OPTION_REFUSALS[k].format(fmt=fmt)}" for k in refused if k in SOURCE_OPTION_REFUSALS)
        raise ConfigError(f"{', '.join(SOURCE_OPTION_FLAGS.get(k, k) for k in refused)}: does not apply to {path} "
                          f"(format {fmt}" + (f", which takes {', '.join(takes)})" if takes else ", which takes none of "
                          f"{', '.join(SOURCE_OPTION_FLAGS.values())})") + reasons)


def open_build_source(source: str | Path, format: str | None, frames: str | None, config: BuildConfig, poses_from_source: bool,
          depth_options: dict[str, Any] | None = None, source_options: dict[str, Any] | None = None) -> FrameSource:
    path = Path(source)
    options: dict[str, Any] = {"frames": frames}
    fmt, params = source_params(path, format)
    if depth_options and fmt in registered_formats():
        refused = [k for k in depth_options if k not in params]
        if refused:
            takes = [DEPTH_OPTION_SETTINGS[k] for k in DEPTH_OPTION_SETTINGS if k in params]
            raise ConfigError(
                f"{', '.join(DEPTH_OPTION_SETTINGS[k] for k in refused)}: does not apply to {path} (format {fmt}"
                + (f", which takes only {', '.join(takes)})" if takes else ", to which build passes no depth options)")
                + "; remove it from the config file, the DRIFTMAP_DEPTH__* environment or the command line")
        options.update(depth_options)
    if source_options:
        check_source_options(path, fmt, source_options)
        options.update(source_options)
    if poses_from_source and "poses_from_ground_truth" in params:
        options["poses_from_ground_truth"] = True  # data sets: their ground truth; logs carry their own poses
    if "pixel_stride" in params:
        options["pixel_stride"] = config.pixel_stride if config.pixel_stride is not None else 0  # 0: decide below
    src = open_source(path, fmt, **{k: v for k, v in options.items() if k != "pixel_stride" or v})
    require_frames(src, path, fmt, frames, {k: v for k, v in options.items() if k not in ("frames", "pixel_stride")})
    # a ROS log's depth-image topic takes the stride as a data set does (its opener cannot declare it: the format does
    # not tell whether the topic is one); a 640 px log converted to MCAP was read at every pixel, its folder at every
    # second (4x the points, other odometry and volume results from one recording)
    log_depth = "pixel_stride" not in params and bool(getattr(src, "reads_depth_images", False))
    if ("pixel_stride" in params or log_depth) and not config.pixel_stride:
        stride = auto_pixel_stride(first_depth_frame(src))
        if stride != 1:
            src = open_source(path, fmt, **{**options, "pixel_stride": stride})
    elif log_depth and config.pixel_stride != 1:
        src = open_source(path, fmt, **{**options, "pixel_stride": config.pixel_stride})
    return src


def require_frames(src: FrameSource, path: Path, fmt: str | None, frames: str | None, options: dict[str, Any]) -> None:
    """An empty selection is an error that names ``--frames`` and the source's length (not a failed index 0)."""
    try:
        n = len(src)
    except SourceError:  # the length is unknown for this source: the frames are counted as they come
        return
    if n:
        return
    if frames is None:
        raise SourceError(f"{path}: the source has no frames")
    total = len(open_source(path, fmt, **options))
    raise ConfigError(f"--frames {frames} selects no frame of {path} (the source has {total} frames"
                      + (f", indices 0..{total - 1})" if total else ")"))


def option_matrix() -> dict[str, dict[str, bool]]:
    """For every registered format, which command-line source flags (:data:`SOURCE_OPTION_FLAGS`, keyed by flag)
    and depth settings (:data:`DEPTH_OPTION_SETTINGS`, keyed by setting) ``build`` / ``convert`` pass to it: the
    readers' own declarations (:func:`~driftmap.sources.base.accepted_options`), exactly what
    :func:`check_source_options` and :func:`open_build_source` check. docs/cli.md shows it; tests/test_option_matrix.py
    runs every cell through the command line."""
    out: dict[str, dict[str, bool]] = {}
    for name, spec in registered_formats().items():
        params = accepted_options(spec.open)
        row = {flag: key in params for key, flag in SOURCE_OPTION_FLAGS.items()}
        row.update({setting: key in params for key, setting in DEPTH_OPTION_SETTINGS.items()})
        out[name] = row
    return out

