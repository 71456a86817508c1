"""Double walls: where the map holds the same surface twice, how far apart the two layers are, and which
frames put them there. Also the smearing score (one number in metres) and, for comparison with the
literature, Mean Map Entropy and Mean Plane Variance.

Method (see ``docs/diagnostics.md`` for the reasoning and the measured numbers):

1. **Samples** (:class:`DiagnosticCloud`): a bounded random subset of every frame's sensor-frame points,
   each with a normal estimated *within its own frame* (smearing between frames cannot corrupt it), its
   planarity, and a sensor-noise level along the normal (Kinect-style ``sigma_z = a + b (z - z0)^2`` or a
   constant LiDAR range sigma). Placing the samples with a revision's poses is cheap, so one cloud serves
   many revisions (and the perturbation experiments).
2. **Per voxel, per scale** (:func:`detect_double_walls`): the dominant normal of the voxel's own-frame
   normals (a second one for the points that disagree with it), points within ``normal_max_angle_deg``
   of it, split by which side the sensor was on; the two halves of a surface that a voxel face cuts along its
   normal are joined (else each half holds a truncated noise band and separations read short). Offsets along the normal are referred to a *lateral cell
   reference* (the mean offset of all frames in a small cell of the surface), which removes real relief
   (a door recess, a curb) seen by every frame; what is left between frames is pose disagreement.
3. Per frame, the mean residual offset; a two-layer split of the frames (1-D 2-means, per-frame mean
   offsets as samples) is accepted as a double wall when the two-component model wins by BIC, the
   layers are far apart relative to their widths (Ashman's D), the separation exceeds both the minimum
   and its own uncertainty, the smaller layer is not tiny, the layers overlap laterally, and the
   **time/frame purity** holds: points of each frame lie on that frame's layer about as often as the
   sensor noise allows (two-layer geometry seen within single frames fails this).
4. The separation is measured where both layers were seen: per shared lateral cell, the difference of
   the two layers' mean offsets; its uncertainty combines the spread over cells and the frame-to-frame
   jitter of each layer.
5. **Smearing score**: per group, its frames are split into *visits* (runs without ``visit_gap_m`` of travel
   between two frames that saw it); the visits' mean offsets should agree. Their dispersion, less what the
   sensor noise and the group's own frame-to-frame jitter within visits explain, is the group's smearing; the
   score is its RMS over the groups (a group seen in one visit counts 0: drift without a revisit is
   invisible). Within-visit jitter (viewpoint-dependent depth distortion, pose jitter) is the same for every
   pose estimate, so leaving it out is what separates a drifting map from a good one. The frame-level
   score (between-frame instead of between-visit dispersion) is kept beside it: it also sees a jump inside
   one pass.

This module is the front door: the work is done in one module per step, all re-exported here (import from
here or from the step's module):

* :mod:`driftmap.preprocess.noise`: the sensor noise model (1, the noise along the normal);
* :mod:`driftmap.diagnostics.samples`: the samples and their placement (1);
* :mod:`driftmap.diagnostics.surfaces`: surface groups and lateral cells (2);
* :mod:`driftmap.diagnostics.layers`: the per-voxel two-layer test, separation, purity and smearing (2-5);
* :mod:`driftmap.diagnostics.detector`: every voxel size, and the flagged groups merged into regions;
* :mod:`driftmap.diagnostics.wall_results`: the configuration and result types;
* :mod:`driftmap.diagnostics.entropy`: Mean Map Entropy and Mean Plane Variance.
"""

from __future__ import annotations

from driftmap.diagnostics.detector import detect_double_walls
from driftmap.diagnostics.entropy import MapEntropy, map_entropy
from driftmap.diagnostics.samples import (
    UNIT_NORMAL_TOLERANCE,
    DiagnosticCloud,
    PlacedCloud,
    RejectReason,
    SamplingConfig,
)
from driftmap.diagnostics.surfaces import SurfaceGroups, surface_groups
from driftmap.diagnostics.wall_results import DoubleWallConfig, DoubleWallRegion, DoubleWallResult, ScaleResult
from driftmap.preprocess.noise import NoiseModel, NoiseModelKind

__all__ = [
    "UNIT_NORMAL_TOLERANCE",
    "DiagnosticCloud",
    "DoubleWallConfig",
    "DoubleWallRegion",
    "DoubleWallResult",
    "MapEntropy",
    "NoiseModel",
    "NoiseModelKind",
    "PlacedCloud",
    "RejectReason",
    "SamplingConfig",
    "ScaleResult",
    "SurfaceGroups",
    "detect_double_walls",
    "map_entropy",
    "surface_groups",
]
