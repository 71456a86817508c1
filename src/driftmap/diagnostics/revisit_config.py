"""The revisit check's settings (:class:`RevisitCheckConfig`) and the constants its registrations share: the
pairs' (:mod:`driftmap.diagnostics.revisits`) and the jumps' (:mod:`driftmap.diagnostics.jumps`)."""

from __future__ import annotations

from pydantic import ConfigDict, Field

from driftmap.config import SettingsModel

MIN_PROBE_POINTS = 50
"""A frame with fewer diagnostic samples is not registered (GICP needs neighbourhoods to fit planes in)."""

HYPOTHESIS_WITHIN = 0.5
"""A jump's two hypotheses (no pose error / the jump is one) are told apart by the share of the probe within this many
finest voxels of the target: at 1.5 a 30 cm step at frame 58 of the room fits 0.794 as placed and 0.788 undone, at 0.5
0.631 and 0.678 (the step runs along the walls most of the view sees; only its precise fit tells)."""
FREE_OVER_LOCAL = 0.1
"""A jump probe's free registration replaces its best local hypothesis only with this much more of the probe within
:data:`HYPOTHESIS_WITHIN` finest voxels (a larger share, 0 .. 1)."""


class RevisitCheckConfig(SettingsModel):
    """Which revisit pairs are registered onto each other and when their corrections leave the detector's range."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    enabled: bool = Field(True, description="register revisiting frames onto earlier ones (the check of pose errors beyond the double-wall detector's range)")
    revisit_min_path_m: float = Field(1.0, gt=0.0, description="a pair's two frames are at least this much travel apart (m)")
    registration_voxel_m: float = Field(0.05, gt=0.0, description="finest GICP voxel (m); the coarse levels are 2x and 4x")
    coarse_gate_m: float = Field(0.8, gt=0.0, description="correspondence gate of the coarsest level and the overlap grid (m): pose errors up to about this are measured")
    max_probes: int = Field(12, ge=1, le=1000, description="pairs registered at most (in turn the pair furthest apart in travel and the one overlapping most)")
    window_m: float = Field(0.5, gt=0.0, description="a pair's target: its frame and those up to this much travel before it (m)")
    max_window_frames: int = Field(50, ge=1, le=1000, description="... at most this many frames")
    min_overlap: float = Field(0.5, gt=0.0, le=1.0, description="a probe has at least this share of its points in coarse voxels its target frame occupies")
    min_fitness: float = Field(0.6, gt=0.0, le=1.0, description="a registration counts with at least this share of the probe's points on the target")
    min_constraint: float = Field(0.03, gt=0.0, le=1.0, description="... and sqrt(lambda_min / lambda_max) of its translational information at least this (no slide along a corridor)")
    min_probes: int = Field(3, ge=1, description="counted pairs the check needs; its disagreement is the min_probes-th largest correction")
    max_detectable_m: float = Field(0.2, gt=0.0, description="the largest separation the double-wall detector reports (m): beyond it the figures cannot judge the map")
    max_detectable_deg: float = Field(10.0, gt=0.0, description="the largest rotation the detector's normal grouping tolerates (deg)")
    max_step_checks: int = Field(4, ge=0, le=100, description="consecutive frames whose relative motion jumps against their neighbours' by jump_min_share of the detectable error or more are registered onto the frames before them: at most this many such jumps, the largest first")
    jump_min_share: float = Field(0.25, gt=0.0, le=10.0, description="... a jump is checked from this share of max_detectable_m or max_detectable_deg on (0.25: 5 cm / 2.5 deg indoors). At 0.5 a 5 deg yaw step in the room (a 6.7 deg turn between frames becoming 11.7) sat on the threshold and a 5 deg step on the street went unchecked")
    step_probes: int = Field(3, ge=1, le=10, description="... the frames from the jump on (at most this many, within half window_m of travel, up to the next jump) registered together onto the frames before it")
    implausible_factor: float = Field(5.0, gt=1.0, description="a jump whose frames fit nothing before it is no verdict ('cannot judge') when it exceeds this many times the log's 90th-percentile motion between consecutive frames")
