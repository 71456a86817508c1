"""The per-voxel two-layer test of one voxel size: does a surface group hold its surface twice, and how far
do its frames and its visits disagree (the smearing)?

Per surface group (:mod:`driftmap.diagnostics.surfaces`), in steps (:func:`evaluate_scale`):

1. **Cell reference**: offsets along the normal are referred to the mean offset of all frames in the same
   lateral cell, which removes real relief (a door recess, a curb) seen by every frame; what is left between
   frames is pose disagreement.
2. **Per frame** (:class:`FrameMeans`): the mean residual offset and its noise (pooled within-frame scatter, at
   least the sensor model's).
3. **Smearing**: between-frame dispersion of those means beyond noise, and between *visits*
   (:func:`visit_smear`) beyond noise and within-visit jitter.
4. **Two layers**: a precision-weighted 1-D 2-means split of the frames' means, scored by BIC against one
   layer, by Ashman's D and by each layer's precision.
5. **Separation** where both layers were seen (per shared lateral cell), its uncertainty and the lateral
   overlap; then the **time purity** (points of a frame lie on that frame's layer as often as noise allows).
6. The flags combine all of these with the thresholds of :class:`~driftmap.diagnostics.wall_results.DoubleWallConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

from driftmap.diagnostics.samples import PlacedCloud
from driftmap.diagnostics.surfaces import SurfaceGroups, surface_groups
from driftmap.diagnostics.wall_results import DoubleWallConfig, ScaleResult
from driftmap.kernels.groups import cell_residuals, group_min_max, group_row_sums, group_sums, layer_purity_counts
from driftmap.voxels import dense_ids


@dataclass(frozen=True)
class FrameMeans:
    """Per (surface group, frame) entry of one voxel size: how many points the frame put in the group and
    their mean offset from the cell reference; per group the per-point noise those means are judged against."""

    entry: NDArray[np.int64]
    """Per grouped point: its (group, frame) entry."""
    group: NDArray[np.int64]
    frame: NDArray[np.int64]
    """Per entry: the group and the frame row."""
    n_points: NDArray[np.float64]
    """Per entry: points with a cell reference (cells seen by more than one frame)."""
    mean_m: NDArray[np.float64]
    """Per entry: mean residual offset (0 where not ``ok``)."""
    ok: NDArray[np.bool_]
    """Per entry: enough points (``min_points_per_frame``) to count."""
    var_m2: NDArray[np.float64]
    """Per entry: noise variance of ``mean_m`` (inf where not ``ok``)."""
    point_var_m2: NDArray[np.float64]
    """Per group: per-point variance along the normal (pooled within-frame scatter, at least the sensor model's)."""
    n_frames: NDArray[np.int64]
    """Per group: frames that count."""
    n_valid: NDArray[np.float64]
    """Per group: points of the frames that count."""

    @property
    def okf(self) -> NDArray[np.float64]:
        return self.ok.astype(np.float64)

    @property
    def weight(self) -> NDArray[np.float64]:
        """Per entry: its point count where it counts, else 0."""
        return np.where(self.ok, self.n_points, 0.0)


def _cell_residuals(sg: SurfaceGroups, f: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Per grouped point: its offset minus the mean offset of its lateral cell, and whether the cell holds more
    than one distinct frame (only then is the cell a reference)."""
    return cell_residuals(sg.cell, sg.n_cells, sg.offset_m, f)


def frame_means(sg: SurfaceGroups, f: NDArray[np.int64], n_frames_total: int, s2: NDArray[np.float64],
                min_points_per_frame: int) -> FrameMeans:
    """:class:`FrameMeans` of surface groups ``sg`` whose points come from frame rows ``f`` (``s2``: each point's
    sensor-noise variance along the normal)."""
    g, G, M = sg.group, sg.n_groups, n_frames_total
    r, valid = _cell_residuals(sg, f)
    gf, gf_keys = dense_ids(g * M + f)
    E = len(gf_keys)
    e_group, e_frame = gf_keys // M, gf_keys % M
    rows = np.empty((4, len(gf)))
    wv = rows[0]
    wv[:] = valid
    np.multiply(r, wv, out=rows[1])
    np.multiply(r * r, wv, out=rows[2])
    np.multiply(s2, wv, out=rows[3])
    e_n, e_sum, e_sq, e_s2 = group_row_sums(gf, E, rows)
    e_ok = e_n >= min_points_per_frame
    okf = e_ok.astype(np.float64)
    e_mean = np.where(e_ok, e_sum / np.maximum(e_n, 1), 0.0)
    # per-point scatter along the normal: pooled within-frame variance, at least the sensor model's
    within = np.maximum(e_sq - e_n * e_mean**2, 0.0) * okf
    dof = group_sums(e_group, G, np.maximum(e_n - 1, 0) * okf)
    point_var = np.maximum(group_sums(e_group, G, within) / np.maximum(dof, 1),
                           group_sums(e_group, G, e_s2 * okf) / np.maximum(group_sums(e_group, G, e_n * okf), 1))
    point_var = np.maximum(point_var, 1e-8)
    e_v = np.where(e_ok, point_var[e_group] / np.maximum(e_n, 1), np.inf)
    w = np.where(e_ok, e_n, 0.0)
    n_frames = group_sums(e_group, G, okf).astype(np.int64)
    n_valid = group_sums(e_group, G, w)
    return FrameMeans(gf, e_group, e_frame, e_n, e_mean, e_ok, e_v, point_var, n_frames, n_valid)


def _smearing(fm: FrameMeans, G: int, path_length_m: NDArray[np.float64],
              visit_gap_m: float) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Per group: frame-level smearing (between-frame dispersion of the means, point-weighted, minus the noise
    part), the path travelled between its first and last frame, the visit-level smearing and the visits."""
    e_group, e_mean, e_ok, w = fm.group, fm.mean_m, fm.ok, fm.weight
    W = np.maximum(fm.n_valid, 1e-12)
    mbar = group_sums(e_group, G, w * e_mean) / W
    disp = group_sums(e_group, G, w * (e_mean - mbar[e_group]) ** 2) / W
    noise = fm.point_var_m2 * fm.n_frames / W
    smear = np.sqrt(np.maximum(disp - noise, 0.0))
    # path travelled between the first and the last frame that saw the group (a revisit when large)
    e_path = path_length_m[fm.frame]
    s_lo, s_hi = group_min_max(e_group[e_ok], G, e_path[e_ok])
    path_span = np.where(fm.n_frames > 0, s_hi - s_lo, 0.0)
    visits, n_visits = visit_smear(e_group, e_path, fm.n_points.astype(np.float64), e_mean, e_ok, fm.point_var_m2, G,
                                   visit_gap_m)
    return smear, path_span, visits, n_visits


@dataclass(frozen=True)
class _Layers:
    """The two-layer split of every group's frames (A: lower mean offset, B: higher)."""

    is_b: NDArray[np.bool_]
    """Per entry: the frame is on layer B."""
    n_a: NDArray[np.float64]
    n_b: NDArray[np.float64]
    """Per group: frames per layer; below, points per layer."""
    w_a: NDArray[np.float64]
    w_b: NDArray[np.float64]
    delta_bic: NDArray[np.float64]
    ashman_d: NDArray[np.float64]
    prec_a: NDArray[np.float64]
    prec_b: NDArray[np.float64]
    """Per group: the precision of each layer's mean (inverse variance)."""


def _wmeans(e_group: NDArray[np.int64], G: int, weights: NDArray[np.float64], *values: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Per group, the ``weights``-weighted mean of each of ``values`` (the sums in one pass)."""
    rows = np.empty((len(values) + 1, len(e_group)))
    rows[0] = weights
    for k, v in enumerate(values):
        np.multiply(weights, v, out=rows[k + 1])
    sums = group_row_sums(e_group, G, rows)
    total = np.maximum(sums[0], 1e-300)
    return [sums[k + 1] / total for k in range(len(values))]


def _layer_fit(fm: FrameMeans, G: int, member: NDArray[np.bool_], pw: NDArray[np.float64], ev: NDArray[np.float64],
               floor2: float) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Mean, between-frame jitter (moments, noise removed), observed width and log-likelihood of a layer."""
    e_group, e_mean = fm.group, fm.mean_m
    m = member & fm.ok
    wt = np.where(m, pw, 0.0)
    mu, = _wmeans(e_group, G, wt, e_mean)
    obs, mean_ev = _wmeans(e_group, G, wt, (e_mean - mu[e_group]) ** 2, ev)
    tau2 = np.maximum(obs - mean_ev, 0.0)
    for _ in range(2):
        wt = np.where(m, 1.0 / (tau2[e_group] + ev + floor2), 0.0)
        mu, = _wmeans(e_group, G, wt, e_mean)
        spread, mean_ev = _wmeans(e_group, G, wt, (e_mean - mu[e_group]) ** 2, ev)
        tau2 = np.maximum(spread - mean_ev, 0.0)
    var = tau2[e_group] + ev + floor2
    ll = -0.5 * group_sums(e_group, G, np.where(m, np.log(2 * np.pi * var) + (e_mean - mu[e_group]) ** 2 / var, 0.0))
    return mu, tau2, obs, ll


def _two_layers(fm: FrameMeans, G: int, cfg: DoubleWallConfig) -> _Layers:
    """Precision-weighted 1-D 2-means on the per-frame means, then both layers fitted and compared with one."""
    e_group, e_mean, e_ok, okf, w = fm.group, fm.mean_m, fm.ok, fm.okf, fm.weight
    floor2 = cfg.frame_jitter_floor_m**2
    pw = np.where(e_ok, 1.0 / (np.where(e_ok, fm.var_m2, 1.0) + floor2), 0.0)
    thr, = _wmeans(e_group, G, pw, e_mean)
    rows = np.empty((6, len(e_mean)))
    for _ in range(cfg.kmeans_iterations):
        isB = e_mean > thr[e_group]
        np.multiply(pw, ~isB, out=rows[0])
        np.multiply(rows[0], e_mean, out=rows[1])
        np.multiply(pw, isB, out=rows[2])
        np.multiply(rows[2], e_mean, out=rows[3])
        np.multiply(okf, ~isB, out=rows[4])
        np.multiply(okf, isB, out=rows[5])
        sums = group_row_sums(e_group, G, rows)
        muA, muB = sums[1] / np.maximum(sums[0], 1e-300), sums[3] / np.maximum(sums[2], 1e-300)
        both = (sums[4] > 0) & (sums[5] > 0)
        thr = np.where(both, 0.5 * (muA + muB), thr)
    isB = e_mean > thr[e_group]
    np.multiply(okf, ~isB, out=rows[0])
    np.multiply(okf, isB, out=rows[1])
    np.multiply(w, ~isB, out=rows[2])
    np.multiply(w, isB, out=rows[3])
    nA, nB, wA, wB = group_row_sums(e_group, G, rows[:4])
    ev = np.where(e_ok, fm.var_m2, 0.0)
    muA, tauA2, obsA, llA = _layer_fit(fm, G, ~isB, pw, ev, floor2)
    muB, tauB2, obsB, llB = _layer_fit(fm, G, isB, pw, ev, floor2)
    _, _, _, ll1 = _layer_fit(fm, G, np.ones(len(e_mean), bool), pw, ev, floor2)
    nF = np.maximum(nA + nB, 1)
    ll2 = llA + llB + cfg.bic_mixing_weight * (nA * np.log(np.maximum(nA, 1e-12) / nF) + nB * np.log(np.maximum(nB, 1e-12) / nF))
    delta_bic = 2.0 * (ll2 - ll1) - 3.0 * np.log(nF)
    ashman = (muB - muA) / np.sqrt(0.5 * (obsA + obsB) + floor2)
    precA = group_sums(e_group, G, np.where(e_ok & ~isB, 1.0 / (tauA2[e_group] + ev + floor2), 0.0))
    precB = group_sums(e_group, G, np.where(e_ok & isB, 1.0 / (tauB2[e_group] + ev + floor2), 0.0))
    return _Layers(isB, nA, nB, wA, wB, delta_bic, ashman, precA, precB)


@dataclass(frozen=True)
class _Separation:
    """Where both layers were seen: per cell the layers' counts and offset sums, per group the separation."""

    entry_layer: NDArray[np.int8]
    """Per (group, frame) entry: the frame's layer (0: A, 1: B, -1: the frame does not count)."""
    layer: NDArray[np.int8]
    """Per grouped point: its frame's layer."""
    shared: NDArray[np.bool_]
    c_a: NDArray[np.float64]
    c_b: NDArray[np.float64]
    s_a: NDArray[np.float64]
    s_b: NDArray[np.float64]
    separation_m: NDArray[np.float64]
    sigma_m: NDArray[np.float64]
    n_shared: NDArray[np.float64]
    overlap: NDArray[np.float64]


def _separation(sg: SurfaceGroups, fm: FrameMeans, layers: _Layers) -> _Separation:
    """Per shared lateral cell, mean(B) - mean(A) of the raw offsets; per group their weighted mean, its
    uncertainty (spread over cells and each layer's frame-to-frame jitter) and the smaller layer's share of points
    in shared cells."""
    c, C, o, G, cell_group = sg.cell, sg.n_cells, sg.offset_m, sg.n_groups, sg.cell_group
    e_layer = np.where(fm.ok, layers.is_b.astype(np.int8), np.int8(-1))
    layer = e_layer[fm.entry]
    rows = np.empty((4, len(c)))
    inA, inB = rows[0], rows[1]
    inA[:], inB[:] = layer == 0, layer == 1
    np.multiply(inA, o, out=rows[2])
    np.multiply(inB, o, out=rows[3])
    cA, cB, sA, sB = group_row_sums(c, C, rows)
    shared = (cA > 0) & (cB > 0)
    d_c = np.where(shared, sB / np.maximum(cB, 1) - sA / np.maximum(cA, 1), 0.0)
    w_c = np.where(shared, cA * cB / np.maximum(cA + cB, 1), 0.0)
    Wc = group_sums(cell_group, G, w_c)
    sep = group_sums(cell_group, G, w_c * d_c) / np.maximum(Wc, 1e-12)
    var_c = group_sums(cell_group, G, w_c * (d_c - sep[cell_group]) ** 2) / np.maximum(Wc, 1e-12)
    neff = Wc**2 / np.maximum(group_sums(cell_group, G, w_c**2), 1e-12)
    n_shared = group_sums(cell_group, G, shared.astype(np.float64))
    sep_sigma = np.sqrt(var_c / np.maximum(neff, 1.0) + 1.0 / np.maximum(layers.prec_a, 1e-12)
                        + 1.0 / np.maximum(layers.prec_b, 1e-12))
    # lateral overlap: share of the smaller layer's points in shared cells
    ptsA, ptsB = group_sums(cell_group, G, cA), group_sums(cell_group, G, cB)
    shA, shB = group_sums(cell_group, G, cA * shared), group_sums(cell_group, G, cB * shared)
    small_is_A = ptsA <= ptsB
    overlap = np.where(small_is_A, shA / np.maximum(ptsA, 1), shB / np.maximum(ptsB, 1))
    return _Separation(e_layer, layer, shared, cA, cB, sA, sB, sep, sep_sigma, n_shared, overlap)


def _purity(sg: SurfaceGroups, sep: _Separation, point_var: NDArray[np.float64]) -> NDArray[np.float64]:
    """Noise-normalised time purity in the shared cells: how often a point lies on its frame's layer (beyond the
    midpoint), against what the separation and the noise allow (1: always; 0: as mixed as chance)."""
    c, g, o, G = sg.cell, sg.group, sg.offset_m, sg.n_groups
    shared, layer = sep.shared, sep.layer
    mid = np.where(shared, 0.5 * (sep.s_a / np.maximum(sep.c_a, 1) + sep.s_b / np.maximum(sep.c_b, 1)), 0.0)
    expect = ndtr(np.abs(sep.separation_m) / (2.0 * np.sqrt(point_var)))  # per group: the share noise allows
    n_sh, n_correct, n_expect = layer_purity_counts(c, g, G, o, layer, shared, mid, np.sign(sep.separation_m), expect)
    purity = (n_correct - 0.5 * n_sh) / np.maximum(n_expect - 0.5 * n_sh, 1e-12)
    return np.clip(purity, 0.0, 1.5)


def evaluate_scale(cloud: PlacedCloud, size_m: float, cfg: DoubleWallConfig) -> ScaleResult:
    """Every surface group of voxel size ``size_m``: evaluated or not, flagged as a double wall or not, with the
    separation, its evidence and the smearing (the steps of the module docstring)."""
    sg = surface_groups(cloud, size_m, normal_max_angle_deg=cfg.normal_max_angle_deg, second_surface=cfg.second_surface,
                        min_points=cfg.min_points, cell_fraction=cfg.cell_fraction, max_cell_m=cfg.max_cell_m)
    G = sg.n_groups
    f = cloud.frame_index[sg.point_index]
    s2 = cloud.sigma_normal_m[sg.point_index].astype(np.float64) ** 2
    fm = frame_means(sg, f, cloud.samples.n_frames, s2, cfg.min_points_per_frame)
    evaluated = (fm.n_frames >= cfg.min_frames) & (fm.n_valid >= cfg.min_points)
    smear, path_span, visits, n_visits = _smearing(fm, G, cloud.path_length_m, cfg.visit_gap_m)
    layers = _two_layers(fm, G, cfg)
    sep = _separation(sg, fm, layers)
    purity = _purity(sg, sep, fm.point_var_m2)
    layer_fraction = np.minimum(layers.w_a, layers.w_b) / np.maximum(layers.w_a + layers.w_b, 1e-12)
    abs_sep = np.abs(sep.separation_m)
    flagged = (
        evaluated
        & (layers.n_a >= cfg.min_frames_per_layer) & (layers.n_b >= cfg.min_frames_per_layer)
        & (layer_fraction >= cfg.min_layer_fraction)
        & (sep.n_shared >= cfg.min_shared_cells)
        & (sep.overlap >= cfg.min_overlap)
        & (abs_sep >= cfg.min_separation_m)
        & (abs_sep >= cfg.min_separation_sigmas * sep.sigma_m)
        & (layers.ashman_d >= cfg.min_ashman_d)
        & (layers.delta_bic >= cfg.min_delta_bic)
        & (purity >= cfg.min_purity)
    )
    return ScaleResult(
        voxel_size_m=size_m, centers_m=sg.centers_m, normals=sg.normals, n_points=sg.n_points.astype(np.int64),
        n_frames=fm.n_frames, evaluated=evaluated, flagged=flagged, separation_m=sep.separation_m,
        separation_sigma_m=sep.sigma_m, ashman_d=layers.ashman_d, delta_bic=layers.delta_bic, purity=purity,
        overlap=sep.overlap, layer_fraction=layer_fraction, smear_m=smear, path_span_m=path_span,
        visit_smear_m=visits, n_visits=n_visits,
        gf_group=fm.group, gf_frame=fm.frame, gf_points=fm.n_points.astype(np.int64), gf_mean_m=fm.mean_m, gf_layer=sep.entry_layer,
        grouped_point_index=sg.point_index.astype(np.int32), grouped_point_group=sg.group.astype(np.int32),
        min_separation_m=cfg.min_separation_m,
    )


def visit_smear(e_group: NDArray[np.int64], e_path: NDArray[np.float64], e_n: NDArray[np.float64], e_mean: NDArray[np.float64],
                e_ok: NDArray[np.bool_], point_var: NDArray[np.float64], G: int, gap_m: float) -> tuple[NDArray, NDArray]:
    """Per group: how far its visits disagree beyond what noise and frame-to-frame jitter explain (m; NaN with one visit).

    A visit is a run of the group's frames, ordered by path travelled, without a gap of more than ``gap_m``. Each
    visit's mean offset is point-weighted; the frame-to-frame jitter *within* visits (sensor distortion that changes
    with the viewpoint, pose jitter) is estimated from the group itself and removed from the visit means' variance, so
    what is left is the disagreement that needs travel: drift, a pose jump, a loop that did not close."""
    idx = np.flatnonzero(e_ok)
    n_visits = np.zeros(G, np.int64)
    out = np.full(G, np.nan)
    if idx.size == 0:
        return out, n_visits
    idx = idx[np.lexsort((e_path[idx], e_group[idx]))]
    g, p, n, m = e_group[idx], e_path[idx], e_n[idx], e_mean[idx]
    start = np.r_[True, (g[1:] != g[:-1]) | (np.diff(p) > gap_m)]
    v = np.cumsum(start) - 1
    V = int(v[-1]) + 1
    vg = g[start]
    n_visits = np.bincount(vg, minlength=G).astype(np.int64)
    N = group_sums(v, V, n)
    mv = group_sums(v, V, n * m) / np.maximum(N, 1e-12)
    pv = point_var[vg]
    # within-visit jitter tau^2 (pooled per group): E[sum n (m - m_v)^2] = pv (F_v - 1) + tau^2 (N_v - sum n^2 / N_v)
    n2 = group_sums(v, V, n * n)
    F = np.bincount(v, minlength=V).astype(np.float64)
    A = group_sums(vg, G, group_sums(v, V, n * (m - mv[v]) ** 2))
    B = group_sums(vg, G, pv * (F - 1.0))
    C = group_sums(vg, G, N - n2 / np.maximum(N, 1e-12))
    tau2 = np.where(C > 0, np.maximum(A - B, 0.0) / np.maximum(C, 1e-12), 0.0)
    var_v = pv / np.maximum(N, 1e-12) + tau2[vg] * n2 / np.maximum(N, 1e-12) ** 2
    # between visits: point-weighted dispersion of the visit means minus its expectation under noise alone
    W = group_sums(vg, G, N)
    mbar = group_sums(vg, G, N * mv) / np.maximum(W, 1e-12)
    disp = group_sums(vg, G, N * (mv - mbar[vg]) ** 2) / np.maximum(W, 1e-12)
    noise = group_sums(vg, G, N * var_v * (1.0 - N / np.maximum(W[vg], 1e-12))) / np.maximum(W, 1e-12)
    out = np.where(n_visits >= 2, np.sqrt(np.maximum(disp - noise, 0.0)), np.nan)
    return out, n_visits
