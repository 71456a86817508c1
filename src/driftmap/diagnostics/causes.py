"""What caused each double wall, with its evidence.

The two layers of a doubled surface come from different frames. *Which* frames, and what separates them, tells
the cause apart:

* ``pose``: a pose error splits the frames by **time** -- those before the error on one layer, those after on the
  other (a drift that a loop closure did not take out, a jump). The layers' time spans barely overlap.
* ``depth_range`` / ``viewing_angle``: a depth-calibration error (a range scale, a range- or angle-dependent bias)
  splits them by **how they saw the surface** -- near against far, head-on against grazing -- while frames of both
  layers come from the same times.
* ``geometry``: real structure with two layers (a door panel behind a frame, a mesh) shows **both layers within
  single frames**.
* ``undetermined``: none of these explains the split.

The evidence per region (:func:`explain_region`): how much of the variance of the frames' mean offsets at the region
a step in time, a linear dependence on the viewing range and one on the incidence angle explain (R^2), the layers'
frame counts, time spans, mean range and incidence (with the AUC of each: the probability that a frame of layer B
saw it from further / more obliquely than one of layer A), and the share of frames on both layers.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from driftmap.diagnostics.samples import PlacedCloud
from driftmap.diagnostics.wall_results import DoubleWallRegion, DoubleWallResult

logger = logging.getLogger(__name__)

MIN_R2 = 0.5
"""A cause must explain at least this share of the variance of the frames' offsets at the region."""
GEOMETRY_MIN_SHARED = 0.5
"""Real geometry: at least this share of the region's frames put points on both layers."""


@dataclass(frozen=True)
class RegionCause:
    """The cause of one double-wall region and the numbers it rests on."""

    cause: str
    explanation: str
    evidence: dict[str, object]

    def to_json(self) -> dict:
        return {"cause": self.cause, "explanation": self.explanation, "evidence": dict(self.evidence)}


def _auc(a: NDArray[np.float64], b: NDArray[np.float64]) -> float | None:
    """P(b > a) + P(b == a) / 2 over all pairs (Mann-Whitney); None without both."""
    if len(a) == 0 or len(b) == 0:
        return None
    diff = b[None, :] - a[:, None]
    return float((np.count_nonzero(diff > 0) + 0.5 * np.count_nonzero(diff == 0)) / diff.size)


def _frame_offsets(walls: DoubleWallResult, region: DoubleWallRegion) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Per frame row seen in the region: its points' mean offset along the region's normal (from the lateral cell
    references of the member groups, point-weighted over them)."""
    sums: dict[int, float] = {}
    weights: dict[int, float] = {}
    for si, gi in region.members:
        scale = walls.scales[si]
        sel = (scale.gf_group == gi) & (scale.gf_layer >= 0)
        sign = 1.0 if float(np.dot(scale.normals[gi], region.normal)) >= 0 else -1.0
        for f, m, n in zip(scale.gf_frame[sel], scale.gf_mean_m[sel], scale.gf_points[sel]):
            sums[int(f)] = sums.get(int(f), 0.0) + sign * float(m) * float(n)
            weights[int(f)] = weights.get(int(f), 0.0) + float(n)
    rows = np.array(sorted(sums), dtype=np.int64)
    return rows, np.array([sums[int(r)] / weights[int(r)] for r in rows])


def _r2_step(t: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[float, float]:
    """R^2 of the best single step of ``y`` over ``t`` (a pose error at one instant) and the instant."""
    order = np.argsort(t, kind="stable")
    ys, ts = y[order], t[order]
    sst = float(np.sum((ys - ys.mean()) ** 2))
    n = len(ys)
    if n < 4 or sst <= 0:
        return 0.0, float("nan")
    c1, c2 = np.cumsum(ys), np.cumsum(ys * ys)
    k = np.arange(1, n)
    left = c2[k - 1] - c1[k - 1] ** 2 / k
    right = (c2[-1] - c2[k - 1]) - (c1[-1] - c1[k - 1]) ** 2 / (n - k)
    best = int(np.argmin(left + right))
    return float(1.0 - (left[best] + right[best]) / sst), float(0.5 * (ts[best] + ts[best + 1]))


def _r2_linear(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[float, float]:
    """R^2 and slope of ``y`` linear in ``x`` (a depth error growing with range, or with the viewing angle)."""
    sst = float(np.sum((y - y.mean()) ** 2))
    if len(y) < 4 or sst <= 0 or np.ptp(x) == 0:
        return 0.0, 0.0
    A = np.c_[np.ones_like(x), x]
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return float(1.0 - np.sum((y - A @ coef) ** 2) / sst), float(coef[1])


def explain_region(placed: PlacedCloud, walls: DoubleWallResult, region: DoubleWallRegion) -> RegionCause:
    """:class:`RegionCause` of one region of ``walls`` (a detection on ``placed``).

    Each frame's mean offset at the region (along its normal) is explained three ways: a single step in time (a
    pose error at one instant), linear in the viewing range, linear in the incidence angle. The model that explains
    most of the offsets' variance (R^2 at least :data:`MIN_R2`) names the cause; frames that put points on both
    layers (at least :data:`GEOMETRY_MIN_SHARED` of them) mean real two-layer structure."""
    rows_a, rows_b = np.asarray(region.rows_a, np.int64), np.asarray(region.rows_b, np.int64)
    both = np.intersect1d(rows_a, rows_b)
    all_rows = np.union1d(rows_a, rows_b)
    shared = len(both) / max(len(all_rows), 1)
    rows, y = _frame_offsets(walls, region)
    stamps = placed.stamps_ns.astype(np.float64) * 1e-9
    view = region.center_m[None, :] - placed.origins_world[rows]
    rng = np.linalg.norm(view, axis=1)
    inc = np.degrees(np.arccos(np.clip(np.abs((view / np.maximum(rng[:, None], 1e-9)) @ region.normal), 0.0, 1.0)))
    # offsets along the viewing direction (positive: the surface placed further from the sensors), so that a range
    # error's slope has its sign: a range scale above 1 puts far views' surfaces further away
    y = y * (1.0 if float(np.mean(view @ region.normal)) >= 0 else -1.0)
    r2_time, at_s = _r2_step(stamps[rows], y)
    r2_range, slope_range = _r2_linear(rng, y)
    r2_angle, slope_angle = _r2_linear(inc, y)
    in_a = np.isin(rows, rows_a) & ~np.isin(rows, both)
    in_b = np.isin(rows, rows_b) & ~np.isin(rows, both)
    ev: dict[str, object] = {
        "frames_a": int(len(rows_a)), "frames_b": int(len(rows_b)), "frames_on_both_layers": int(len(both)),
        "share_on_both_layers": float(shared), "frames_with_offsets": int(len(rows)),
        "r2_time_step": r2_time, "time_step_at_s": at_s if np.isfinite(at_s) else None,
        "r2_range": r2_range, "offset_per_m_range": slope_range, "r2_incidence": r2_angle,  # away from the sensor
        "offset_per_deg_incidence": slope_angle,
        "range_m_a": float(rng[in_a].mean()) if in_a.any() else None,
        "range_m_b": float(rng[in_b].mean()) if in_b.any() else None,
        "incidence_deg_a": float(inc[in_a].mean()) if in_a.any() else None,
        "incidence_deg_b": float(inc[in_b].mean()) if in_b.any() else None,
        "time_span_s_a": [float(stamps[rows_a].min()), float(stamps[rows_a].max())] if len(rows_a) else None,
        "time_span_s_b": [float(stamps[rows_b].min()), float(stamps[rows_b].max())] if len(rows_b) else None,
        "range_auc": _auc(rng[in_a], rng[in_b]), "incidence_auc": _auc(inc[in_a], inc[in_b]),
    }
    if shared >= GEOMETRY_MIN_SHARED:
        return RegionCause("geometry", f"{100 * shared:.0f} % of its frames put points on both layers: structure "
                                       "with two layers, not two placements of one surface", ev)
    models = {"pose": r2_time, "depth_range": r2_range, "viewing_angle": r2_angle}
    best = max(models, key=models.get)
    others = ", ".join(f"{k.replace('_', ' ')} {v:.2f}" for k, v in models.items() if k != best)
    if models[best] < MIN_R2:
        return RegionCause("undetermined", f"neither a step in time (R^2 {r2_time:.2f}) nor the viewing range "
                                           f"({r2_range:.2f}) or angle ({r2_angle:.2f}) explains the frames' offsets", ev)
    if best == "pose":
        t_rows = stamps[rows]
        before, after = rows[t_rows < at_s], rows[t_rows > at_s]
        ids = (int(placed.frame_ids[before[np.argmax(t_rows[t_rows < at_s])]]),
               int(placed.frame_ids[after[np.argmin(t_rows[t_rows > at_s])]]))
        ev["time_step_between_frames"] = list(ids)
        text = (f"the frames' offsets step between frames {ids[0]} and {ids[1]} ({at_s:.2f} s; R^2 {r2_time:.2f}, "
                f"against range {r2_range:.2f} and angle {r2_angle:.2f}): a pose error between the frames before and after")
    elif best == "depth_range":
        text = (f"the frames' offsets grow with the viewing range, {100 * slope_range:.1f} cm per m (R^2 "
                f"{r2_range:.2f}; {others}): a depth error that grows with range (calibration), not drift")
    else:
        text = (f"the frames' offsets change with the viewing angle, {1000 * slope_angle:.2f} mm per deg (R^2 "
                f"{r2_angle:.2f}; {others}): a depth error that depends on the incidence, not drift")
    return RegionCause(best, text, ev)


def explain_regions(placed: PlacedCloud, walls: DoubleWallResult) -> list[RegionCause]:
    """The cause of every region of ``walls`` (same order)."""
    causes = [explain_region(placed, walls, r) for r in walls.regions]
    if causes:
        counts: dict[str, int] = {}
        for c in causes:
            counts[c.cause] = counts.get(c.cause, 0) + 1
        logger.info("double-wall causes: %s", ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    return causes
