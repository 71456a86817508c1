"""The ROS log formats in the source registry (``mcap``, ``rosbag1``, ``rosbag2``): their detectors and openers,
registered when :mod:`driftmap.sources.ros` is imported."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

from driftmap.errors import SourceError
from driftmap.sources.base import register_source
from driftmap.sources.ros.containers import detect_mcap, detect_rosbag1, detect_rosbag2
from driftmap.sources.ros.msgtypes import FORMAT_MCAP, FORMAT_ROSBAG1, FORMAT_ROSBAG2
from driftmap.sources.ros.provenance import read_export_origin
from driftmap.sources.ros.source import RosLogSource

#: :class:`RosLogSource` options that apply to depth-image topics only (not declared as the format's options)
DEPTH_IMAGE_ONLY_OPTIONS = frozenset({"pixel_stride", "min_depth_m", "max_depth_m"})


def opener(format_name: str) -> Any:
    """An opener for :func:`register_source`; unknown options raise :class:`SourceError` listing the accepted."""
    params = inspect.signature(RosLogSource.__init__).parameters
    accepted = sorted(n for n, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY and n != "format")

    def open_log(path: Path, **options: Any) -> RosLogSource:
        unknown = sorted(set(options) - set(accepted))
        if unknown:
            raise SourceError(
                f"{path}: unknown option(s) {', '.join(unknown)} for format {format_name!r}; "
                f"accepted: {', '.join(accepted)}"
            )
        return RosLogSource(path, format=format_name, **options)

    open_log.__doc__ = RosLogSource.__doc__
    # the wrapper's signature is ``**options``: declare what it takes, so that what reads an opener's options
    # (sources.base.accepted_options: build / convert checking --topic, --pose-from-tf, ... and depth.* against
    # the format) sees them. Options that apply to depth-image topics only are left out: the format alone cannot
    # tell whether a log's topic is one (build would pass its automatic pixel_stride to PointCloud2 topics, which
    # refuse it); the API takes them.
    open_log.accepted_options = frozenset(accepted) - DEPTH_IMAGE_ONLY_OPTIONS  # type: ignore[attr-defined]
    return open_log


register_source(
    FORMAT_MCAP,
    detect_mcap,
    opener(FORMAT_MCAP),
    "MCAP with ROS 2 messages (PointCloud2 or depth Image + CameraInfo, TF, Odometry)",
    origin_of=read_export_origin,
)
register_source(FORMAT_ROSBAG1, detect_rosbag1, opener(FORMAT_ROSBAG1), "ROS 1 .bag (via rosbags)")
register_source(
    FORMAT_ROSBAG2, detect_rosbag2, opener(FORMAT_ROSBAG2), "rosbag2 folder, sqlite3 or mcap storage (via rosbags)"
)
