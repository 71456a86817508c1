"""driftmap: multi-frame fusion and drift-aware mapping.

Every frame is kept in its sensor frame with the pose estimate that produced it, so a later drift
correction re-transforms old points instead of discarding them.
"""

from driftmap._version import __version__
from driftmap.errors import (
    ConfigError,
    DepthError,
    DepthScaleError,
    DriftmapError,
    GeometryError,
    IntrinsicsError,
    SourceError,
    StoreError,
    TransformError,
)
#: Everything but the errors is imported on first use (``driftmap.Frame``, ``driftmap.FrameStore``,
#: ``driftmap.backproject`` etc.) so that ``import driftmap`` stays light (not even numpy: the command line takes
#: Ctrl-C cleanly from its first moment, driftmap.cli) and ``import driftmap.store`` loads no numba, Open3D, GTSAM
#: or KISS-ICP.
_LAZY = {
    **{name: "driftmap.frame" for name in ("Frame", "FrameQuality", "PinholeIntrinsics", "PointAttributes",
                                           "PoseEstimate", "PoseSource", "Provenance", "SensorKind")},
    "BackprojectionResult": "driftmap.preprocess.depth",
    "InvalidFractionMonitor": "driftmap.preprocess.depth",
    "InvalidReason": "driftmap.preprocess.depth",
    "backproject": "driftmap.preprocess.depth",
    "depth_frame": "driftmap.preprocess.depth",
    "FrameStore": "driftmap.store.frame_store",
    "MapView": "driftmap.map.view",
    "ChangeSet": "driftmap.map.view",
    "open_source": "driftmap.sources.base",
    "build": "driftmap.pipeline.build",
    "BuildConfig": "driftmap.pipeline.build",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'driftmap' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "BackprojectionResult",
    "BuildConfig",
    "ChangeSet",
    "FrameStore",
    "MapView",
    "build",
    "open_source",
    "ConfigError",
    "DepthError",
    "DepthScaleError",
    "DriftmapError",
    "Frame",
    "FrameQuality",
    "GeometryError",
    "IntrinsicsError",
    "InvalidFractionMonitor",
    "InvalidReason",
    "PinholeIntrinsics",
    "PointAttributes",
    "PoseEstimate",
    "PoseSource",
    "Provenance",
    "SensorKind",
    "SourceError",
    "StoreError",
    "TransformError",
    "__version__",
    "backproject",
    "depth_frame",
]
