"""driftmap: multi-frame fusion and drift-aware mapping.

Every frame is kept in its sensor frame with the pose estimate that produced it, so a later drift
correction re-transforms old points instead of discarding them.
"""

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
from driftmap.frame import (
    Frame,
    FrameQuality,
    PinholeIntrinsics,
    PointAttributes,
    PoseEstimate,
    PoseSource,
    Provenance,
    SensorKind,
)
from driftmap.preprocess.depth import BackprojectionResult, InvalidFractionMonitor, InvalidReason, backproject, depth_frame

__version__ = "0.1.0"

__all__ = [
    "BackprojectionResult",
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
