"""Diagnose a stored map (double walls, smearing score, MME/MPV, per-frame attribution, optional ground-truth
errors), turn the result into the JSON contract of ``driftmap diagnose`` and into PNG figures a person
looks at.

The JSON keys ``revision``, ``smearing_score_m``, ``double_wall``, ``frames``, ``change_points``,
``revisit_fraction``, ``mme``, ``mpv`` and (with ground truth) ``trajectory`` are a contract other tools
depend on; more keys may be added, none removed or renamed.

This module is the front door; the work is done in (and re-exported from):

* :mod:`driftmap.diagnostics.diagnose_config`: :class:`DiagnoseConfig` and its per-sensor / per-scene defaults;
* :mod:`driftmap.diagnostics.diagnosis`: the run (:func:`diagnose_store`, :func:`diagnose_cloud`) and its result
  :class:`Diagnosis` with the JSON contract; no file is written there;
* :mod:`driftmap.diagnostics.ground_truth`: the ATE / RPE / segment errors (reading a ground-truth file:
  :func:`driftmap.pipeline.pose_files.read_ground_truth`);
* :mod:`driftmap.diagnostics.figures`: the PNG figures (:func:`write_report`).
"""

from __future__ import annotations

from driftmap.diagnostics.attribution import Attribution, AttributionConfig
from driftmap.diagnostics.causes import RegionCause
from driftmap.diagnostics.coverage import Coverage, CoverageConfig
from driftmap.diagnostics.diagnose_config import DiagnoseConfig, EntropyConfig
from driftmap.diagnostics.diagnosis import Diagnosis, diagnose_cloud, diagnose_store
from driftmap.diagnostics.entropy import MapEntropy
from driftmap.diagnostics.figures import plot_double_walls, plot_frame_disagreement, plot_score_comparison, write_report
from driftmap.diagnostics.ground_truth import GT_FORMATS, MIN_GT_FRAMES
from driftmap.diagnostics.samples import DiagnosticCloud, PlacedCloud, SamplingConfig
from driftmap.diagnostics.verify import RegionCheck
from driftmap.diagnostics.wall_results import DoubleWallConfig, DoubleWallResult
from driftmap.preprocess.noise import NoiseModel

__all__ = [  # the run, its config, figures, ground truth, and the types of its results
    "GT_FORMATS",
    "MIN_GT_FRAMES",
    "Attribution",
    "AttributionConfig",
    "Coverage",
    "CoverageConfig",
    "DiagnoseConfig",
    "Diagnosis",
    "DiagnosticCloud",
    "DoubleWallConfig",
    "DoubleWallResult",
    "EntropyConfig",
    "MapEntropy",
    "NoiseModel",
    "PlacedCloud",
    "RegionCause",
    "RegionCheck",
    "SamplingConfig",
    "diagnose_cloud",
    "diagnose_store",
    "plot_double_walls",
    "plot_frame_disagreement",
    "plot_score_comparison",
    "write_report",
]
