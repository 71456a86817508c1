"""What the mesh extraction and the queries need of the layers (:class:`~driftmap.volume.layers.VolumeLayers` has
it): a protocol, so that they depend on it and not on the module that calls them (no import cycle)."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from driftmap.volume.config import VolumeConfig
from driftmap.volume.grid import GridSpec


class LayerArrays(Protocol):
    hits: NDArray[np.int32]
    misses: NDArray[np.int32]
    mark: NDArray[np.int32]
    tsdf_sum: NDArray[np.int64]
    tsdf_count: NDArray[np.int32]


class Layers(Protocol):
    """The grid, the settings, the per-voxel arrays, a memo per version and the state / evidence lookups."""

    config: VolumeConfig
    grid: GridSpec
    arrays: LayerArrays
    version: int
    cache: dict[Any, Any]
    revision: int

    def states(self, points_m: NDArray[np.floating]) -> NDArray[np.int8]: ...

    def state_grid(self) -> NDArray[np.int8]: ...

    def observers(self, points_m: NDArray[np.floating]) -> list[NDArray[np.int64]]: ...

    def hit_means(self) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]: ...
