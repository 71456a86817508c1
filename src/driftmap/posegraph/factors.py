"""GTSAM conversion: poses, noise models and factors built from driftmap measurements, ``Values`` to and from
pose dictionaries, and GTSAM's C++ failures turned into :class:`PoseGraphError`."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import gtsam
import numpy as np
from numpy.typing import NDArray

from driftmap.errors import PoseGraphError
from driftmap.posegraph.measurements import Edge, Prior
from driftmap.posegraph.robust import m_estimator
from driftmap.posegraph.tangent import information_to_gtsam

__all__ = [
    "between_factor",
    "gaussian",
    "gtsam_call",
    "noise_model",
    "pose3",
    "poses_from_values",
    "prior_factor",
    "values_from_poses",
]


def pose3(T: NDArray[np.float64]) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


def gaussian(information_6x6: NDArray[np.float64]) -> gtsam.noiseModel.Base:
    """GTSAM Gaussian noise model of an information matrix in driftmap order (permuted to GTSAM's)."""
    return gtsam.noiseModel.Gaussian.Information(information_to_gtsam(information_6x6))


def noise_model(edge: Edge) -> gtsam.noiseModel.Base:
    """The edge's Gaussian noise model, wrapped in ``noiseModel.Robust`` when it has a robust kernel."""
    model = gaussian(edge.information_6x6)
    estimator = m_estimator(edge.robust, edge.robust_param)
    return model if estimator is None else gtsam.noiseModel.Robust.Create(estimator, model)


def prior_factor(prior: Prior) -> gtsam.PriorFactorPose3:
    return gtsam.PriorFactorPose3(prior.key, pose3(prior.T_world_x), gaussian(prior.information_6x6))


def between_factor(edge: Edge) -> gtsam.BetweenFactorPose3:
    """The edge as a factor with its own (possibly robust) noise model."""
    return gtsam.BetweenFactorPose3(edge.key_from, edge.key_to, pose3(edge.T_from_to), noise_model(edge))


def values_from_poses(poses: Mapping[int, NDArray[np.float64]]) -> gtsam.Values:
    values = gtsam.Values()
    for key, T in poses.items():
        values.insert(key, pose3(T))
    return values


def poses_from_values(values: gtsam.Values, keys: Iterable[int]) -> dict[int, NDArray[np.float64]]:
    """Read-only float64 4x4 poses of ``keys`` from GTSAM ``Values``."""
    out = {}
    for key in keys:
        T = np.array(values.atPose3(key).matrix(), dtype=np.float64)
        T.setflags(write=False)
        out[key] = T
    return out


def gtsam_call(what: str, fn: Callable[[], object]) -> object:
    """``fn()``, with GTSAM's C++ exceptions (IndeterminantLinearSystem, ...), which arrive as
    ``RuntimeError``, raised as :class:`PoseGraphError` prefixed with ``what`` (their first line: the rest is generic
    advice)."""
    try:
        return fn()
    except RuntimeError as exc:
        # GTSAM's messages run to 20 lines of advice and a URL: the first line names the failure and the variable
        lines = [line.strip() for line in str(exc).strip().splitlines() if line.strip()]
        raise PoseGraphError(f"{what}: GTSAM failed: {lines[0] if lines else type(exc).__name__}") from exc
