"""Volumetric layers of a revision: occupied / free / unknown space, a TSDF mesh and a distance field, computed from
the stored frames' rays and kept true when a pose correction arrives (docs/volume.md)."""

from driftmap.volume.config import UnknownIs, VolumeConfig
from driftmap.volume.layers import FREE, OCCUPIED, STATE_NAMES, UNKNOWN, VolumeChange, VolumeLayers, VolumeStats

__all__ = ["FREE", "OCCUPIED", "STATE_NAMES", "UNKNOWN", "UnknownIs", "VolumeChange", "VolumeConfig", "VolumeLayers",
           "VolumeStats"]
