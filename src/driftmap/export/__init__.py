"""Everything driftmap writes as MCAP for other tools: a revision for Foxglove, frames as ROS 2 messages.

The export layer sits above the diagnostics (it draws their double walls) and the volumetric layers (it carries
their mesh and 2-D grid), and below the pipeline and the CLI. Modules (one concept each; the package re-exports
every public name):

* :mod:`~driftmap.export.foxglove` -- :func:`export_foxglove_mcap`: one pose revision of a store as a Foxglove
  MCAP (map, trajectory, frames, double walls, mesh, 2-D grid; docs/export.md);
* :mod:`~driftmap.export.foxglove_messages` -- the ``foxglove.*`` protobuf messages it is made of;
* :mod:`~driftmap.export.mcap` -- :func:`export_mcap` / :func:`convert`: frames (any source) as an MCAP of
  standard ROS 2 messages that driftmap and ROS tools read back (docs/sources-ros.md);
* :mod:`~driftmap.export.ros_messages` -- the ROS 2 message dicts (``PointCloud2``, ``CameraInfo``, ``Image``,
  transforms) and their schemas;
* :mod:`~driftmap.export.depth_log` -- :func:`write_depth_image_mcap`: depth images as a ROS camera log.

Errors: :class:`~driftmap.errors.ExportError` (and :class:`~driftmap.errors.EmptyStoreExportError`), defined in
:mod:`driftmap.errors`. ``driftmap.map.foxglove_export`` and ``driftmap.sources.mcap_export`` are deprecated
aliases of :mod:`~driftmap.export.foxglove` and :mod:`~driftmap.export.mcap`, kept for existing imports.
"""

from __future__ import annotations

from driftmap.errors import EmptyStoreExportError, ExportError
from driftmap.export.depth_log import write_depth_image_mcap
from driftmap.export.foxglove import (
    FoxgloveExportSummary,
    double_wall_scene,
    export_foxglove_mcap,
    frame_cloud_points,
    grid2d_message,
    mesh_scene,
)
from driftmap.export.mcap import EXPORT_FORMAT_VERSION, convert, export_mcap, source_origin
from driftmap.export.ros_messages import camera_info_msg, depth_image_msg, pointcloud2_msg, ros2_msgdef

__all__ = [
    "EXPORT_FORMAT_VERSION",
    "EmptyStoreExportError",
    "ExportError",
    "FoxgloveExportSummary",
    "camera_info_msg",
    "convert",
    "depth_image_msg",
    "double_wall_scene",
    "export_foxglove_mcap",
    "export_mcap",
    "frame_cloud_points",
    "grid2d_message",
    "mesh_scene",
    "pointcloud2_msg",
    "ros2_msgdef",
    "source_origin",
    "write_depth_image_mcap",
]
