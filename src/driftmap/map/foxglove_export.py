"""Deprecated alias of :mod:`driftmap.export.foxglove`, kept so that existing imports keep working.

Every MCAP writer now lives in :mod:`driftmap.export` (the layer above the diagnostics); import
:func:`~driftmap.export.foxglove.export_foxglove_mcap` from there. The names below are the same objects.
"""

from __future__ import annotations

from driftmap.errors import EmptyStoreExportError as EmptyStoreExportError  # importable as before, not in __all__
from driftmap.errors import ExportError as ExportError
from driftmap.export.foxglove import (
    METADATA_NAME,
    TOPIC_DOUBLE_WALLS,
    TOPIC_GRID2D,
    TOPIC_MAP,
    TOPIC_MESH,
    TOPIC_POINTS,
    TOPIC_TF,
    TOPIC_TRAJECTORY,
    FoxgloveExportSummary,
    double_wall_scene,
    export_foxglove_mcap,
    frame_cloud_points,
    grid2d_message,
    mesh_scene,
)
from driftmap.export.foxglove import ProgressCallback as ProgressCallback
from driftmap.export.foxglove_messages import GRID2D_RGBA as GRID2D_RGBA
from driftmap.export.foxglove_messages import MESH_COLOR as MESH_COLOR
from driftmap.export.foxglove_messages import MESH_ENTITY_ID as MESH_ENTITY_ID

__all__ = [
    "METADATA_NAME",
    "TOPIC_DOUBLE_WALLS",
    "TOPIC_GRID2D",
    "TOPIC_MAP",
    "TOPIC_MESH",
    "TOPIC_POINTS",
    "TOPIC_TF",
    "TOPIC_TRAJECTORY",
    "FoxgloveExportSummary",
    "double_wall_scene",
    "export_foxglove_mcap",
    "frame_cloud_points",
    "grid2d_message",
    "mesh_scene",
]

