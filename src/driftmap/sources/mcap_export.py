"""Deprecated alias of :mod:`driftmap.export.mcap` (and its message helpers), kept so that existing imports keep
working.

Every MCAP writer now lives in :mod:`driftmap.export` (above the sources it reads from); import
:func:`~driftmap.export.mcap.export_mcap`, :func:`~driftmap.export.mcap.convert` and
:func:`~driftmap.export.depth_log.write_depth_image_mcap` from there. The names below are the same objects.
"""

from __future__ import annotations

from driftmap.errors import ExportError
from driftmap.export.depth_log import write_depth_image_mcap
from driftmap.export.mcap import EXPORT_FORMAT_VERSION as EXPORT_FORMAT_VERSION  # importable as before, not in __all__
from driftmap.export.mcap import convert, export_mcap
from driftmap.export.mcap import source_origin as source_origin
from driftmap.export.ros_messages import camera_info_msg, depth_image_msg, pointcloud2_msg, ros2_msgdef

__all__ = [
    "ExportError",
    "camera_info_msg",
    "convert",
    "depth_image_msg",
    "export_mcap",
    "pointcloud2_msg",
    "ros2_msgdef",
    "write_depth_image_mcap",
]

