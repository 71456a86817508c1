"""Robust kernels: the M-estimators a loop edge can carry, their default width, and the chi2 gate."""

from __future__ import annotations

import enum
import math

import gtsam

__all__ = ["CHI2_6DOF_99", "RobustKernel", "default_robust_param", "m_estimator"]

#: 99 % quantile of the chi-square distribution with 6 degrees of freedom (``scipy.stats.chi2.ppf(0.99, 6)``).
#: A loop edge whose chi2 after optimisation exceeds it is reported as not accepted. GTSAM's GNC uses the
#: same gate by default (inlier cost threshold ``0.5 * chi2inv(0.99, dim)`` on the factor error).
CHI2_6DOF_99 = 16.811893829770927


class RobustKernel(enum.Enum):
    """M-estimator applied to an edge's whitened residual norm ``r = sqrt(chi2)`` (GTSAM ``noiseModel.Robust``)."""

    NONE = "none"
    """Plain least squares: weight 1, loss ``r^2 / 2``."""
    HUBER = "huber"
    """Quadratic up to ``k``, linear beyond: weight ``min(1, k / r)``; a wrong edge keeps a bounded pull."""
    CAUCHY = "cauchy"
    """Weight ``1 / (1 + (r / k)^2)``: a far-off edge is almost switched off (redescending influence)."""


def default_robust_param(kernel: RobustKernel) -> float | None:
    """Default kernel width ``k`` in whitened units (a threshold on ``sqrt(chi2)``).

    ``sqrt(CHI2_6DOF_99)`` (about 4.1) for Huber and Cauchy: a 6-dof residual inside the 99 % acceptance gate
    keeps (almost) full weight, one outside it is down-weighted. (The textbook Huber ``k = 1.345`` is for a
    scalar residual; applied to the norm of a 6-vector it would down-weight most correct edges.)
    """
    if kernel is RobustKernel.NONE:
        return None
    return math.sqrt(CHI2_6DOF_99)


def m_estimator(kernel: RobustKernel, param: float | None) -> gtsam.noiseModel.mEstimator.Base | None:
    """GTSAM's M-estimator for ``kernel`` with width ``param``; ``None`` for :attr:`RobustKernel.NONE`."""
    if kernel is RobustKernel.HUBER:
        return gtsam.noiseModel.mEstimator.Huber.Create(param)
    if kernel is RobustKernel.CAUCHY:
        return gtsam.noiseModel.mEstimator.Cauchy.Create(param)
    return None
