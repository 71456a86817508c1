"""Which frames are to blame, without ground truth: per-frame 6-DoF disagreement with the rest of the map,
pose jumps over time (change points), a drift-rate estimate and how much of the map was revisited.

All three use one linearised point-to-plane step (Gauss-Newton) of a frame against a *consensus*. The
samples are sorted into surface groups (voxel x dominant own-frame normal x sensor side, see
:func:`driftmap.diagnostics.surfaces.surface_groups`) and small lateral cells; the consensus plane at a
point is the group normal through the mean offset of the points that an allowed set of *other* frames put
in the same cell (so a frame that is 5 cm off still finds its consensus, which a nearest-neighbour search
would miss: the frame's own neighbours are closer). Per-cell prefix sums over frames in time order give
every allowed set in one pass. The frame's
correction ``x = [t, w]`` (translation at the centroid of its points in metres, world-frame rotation
vector about that centroid) solves ``H x = -b`` with ``J = [n, (p - c) x n]``; directions whose information is tiny
relative to the best one are *unobservable* (a frame that sees one plane cannot be placed along it) and
are left out of the step and reported.

* **disagreement**: the consensus is every other frame.
* **jumps**: the consensus is the ``window`` frames just before (frame-to-local-map, as odometry would see it).
* **change points** (:func:`split_scan`): a translation step fitted at every split of the sequence between
  the ``split_window`` frames before and the ``split_window`` frames from it on; a split whose F statistic
  is a local maximum above ``change_point_f`` is a change point. Groups of frames on both sides observe
  directions a single frame sees too weakly.
* **drift rate**: the consensus is the frames seen at least ``revisit_min_path_m`` of travel earlier; the
  disagreement grows with the path travelled in between on top of a per-frame noise floor; fitting both
  (:func:`drift_rate`) gives %/m and deg/m.
* **revisit fraction**: the share of sampled points that have such a neighbour at all. Drift without a
  revisit is invisible to every consistency measure (only ground truth can show it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import ConfigDict, Field

from driftmap.config import SettingsModel
from driftmap.diagnostics.ground_truth import SegmentErrors, ground_truth_errors, segment_errors
from driftmap.diagnostics.samples import PlacedCloud
from driftmap.diagnostics.surfaces import SurfaceGroups, surface_groups
from driftmap.voxels import dense_ids

logger = logging.getLogger(__name__)


class AttributionConfig(SettingsModel):
    """Parameters of the per-frame disagreement, change points and drift rate (indoor RGB-D defaults)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    voxel_size_m: float = Field(0.2, gt=0.0, description="voxel size of the surface groups the consensus is built on (m)")
    cell_fraction: float = Field(0.25, gt=0.0, le=1.0, description="lateral cell size as a fraction of the voxel size")
    normal_max_angle_deg: float = Field(20.0, gt=0.0, lt=90.0, description="own-frame normals within this angle of the group normal")
    min_group_points: int = Field(20, ge=3, description="points a surface group needs")
    min_neighbors: int = Field(3, ge=1, description="consensus points a point's cell needs")
    huber_m: float = Field(0.02, gt=0.0, description="Huber threshold on point-to-plane residuals (m)")
    max_residual_m: float = Field(0.1, gt=0.0, description="residuals beyond this are not used (m)")
    min_correspondences: int = Field(50, ge=6, description="correspondences a frame needs for a disagreement estimate")
    lever_m: float = Field(1.0, gt=0.0, description="length that makes rotation comparable to translation in the observability test (m)")
    min_relative_information: float = Field(0.01, gt=0.0, lt=1.0, description="a direction is unobservable below this share of the best direction's information")
    window: int = Field(5, ge=1, description="frames before a frame that form its local map for the jump series")
    split_window: int = Field(5, ge=1, description="frames on each side of a candidate split in the change-point scan")
    change_point_f: float = Field(200.0, gt=0.0, description="F statistic (explained / residual variance per degree of freedom) a split needs to be a change point")
    min_split_cells: int = Field(10, ge=4, description="lateral cells seen on both sides a split needs")
    split_jitter_m: float = Field(0.005, gt=0.0, description="pose jitter between frames in the change-point scan's cell weights (m)")
    min_jump_m: float = Field(0.01, ge=0.0, description="smallest step reported as a change point (m)")
    revisit_min_path_m: float = Field(1.0, gt=0.0, description="a place is revisited when seen again after this much travel (m)")


@dataclass(frozen=True)
class FrameAlignment:
    """One consensus step per frame (rows in the cloud's frame order)."""

    translation_m: NDArray[np.float64]
    """(M, 3) correction at the centroid of each frame's points (world frame): where the consensus wants its
    surfaces moved."""
    rotation_deg: NDArray[np.float64]
    """(M, 3) world-frame rotation vector (degrees) about that centroid."""
    n_correspondences: NDArray[np.int64]
    n_unobservable: NDArray[np.int64]
    """Directions (of 6) left out because the frame's geometry does not constrain them."""
    sigma_m: NDArray[np.float64]
    """Noise-only standard deviation of the translation step (optimistic: treats points as independent)."""
    center_m: NDArray[np.float64]
    """(M, 3) the centroid each frame's step is expressed at."""
    observed_share: NDArray[np.float64] | None = None
    """(M, 2) share of a random-direction translation / rotation the frame's step can show (1: all three
    directions observable; a frame that sees two planes shows 2/3 of a random translation's squared norm)."""

    @property
    def translation_norm_m(self) -> NDArray[np.float64]:
        return np.linalg.norm(self.translation_m, axis=1)

    @property
    def rotation_norm_deg(self) -> NDArray[np.float64]:
        return np.linalg.norm(self.rotation_deg, axis=1)

    def estimated(self, min_correspondences: int) -> NDArray[np.bool_]:
        return self.n_correspondences >= min_correspondences

    def observable(self, min_correspondences: int) -> NDArray[np.bool_]:
        return self.estimated(min_correspondences) & (self.n_unobservable == 0)


@dataclass(frozen=True)
class ChangePoint:
    frame_id: int
    stamp_ns: int
    jump_m: float
    jump_deg: float
    z_score: float
    f_statistic: float = float("nan")
    step_m: list[float] | None = None
    """World-frame step of the frames from this one on relative to the frames before."""
    step_deg: list[float] | None = None
    """World-frame rotation vector of the step (deg) when the split scan's rigid fit explains it better than a
    translation (then ``step_m`` is at this frame's sensor origin), else zeros."""

    def to_json(self) -> dict:
        return {"frame_id": int(self.frame_id), "jump_m": float(self.jump_m), "jump_deg": float(self.jump_deg),
                "stamp_ns": int(self.stamp_ns), "z_score": float(self.z_score), "f_statistic": float(self.f_statistic),
                "step_m": self.step_m, "step_deg": self.step_deg}


@dataclass(frozen=True)
class DriftRate:
    percent_per_m: float | None
    deg_per_m: float | None
    n_frames: int
    path_span_m: float
    """Largest path length between a frame and the earlier frames it was compared with."""
    noise_floor_m: float | None = None
    """What a single frame's revisit disagreement shows without any drift (the fit's intercept, metres)."""
    noise_floor_deg: float | None = None


@dataclass(frozen=True)
class Attribution:
    frame_ids: NDArray[np.int64]
    stamps_ns: NDArray[np.int64]
    path_length_m: NDArray[np.float64]
    disagreement: FrameAlignment
    jumps: FrameAlignment
    revisit: FrameAlignment
    revisit_path_m: NDArray[np.float64]
    """Per frame: mean path length travelled between it and the earlier frames it was compared with."""
    change_points: list[ChangePoint]
    drift: DriftRate
    revisit_fraction: float
    config: AttributionConfig
    split: SplitScan
    """The change-point scan (step between the frames before and from each frame on)."""

    @property
    def revisit_note(self) -> str | None:
        if self.revisit_fraction > 0:
            return None
        return (f"no part of the map was seen again after {self.config.revisit_min_path_m:g} m of travel: drift is "
                f"invisible to consistency diagnostics (only ground truth can show it)")

    def frames_json(self) -> list[dict]:
        d, j = self.disagreement, self.jumps
        est = d.estimated(self.config.min_correspondences)
        obs = d.observable(self.config.min_correspondences)
        out = []
        for k, fid in enumerate(self.frame_ids):
            out.append({
                "frame_id": int(fid),
                "stamp_ns": int(self.stamps_ns[k]),
                "disagreement_m": float(d.translation_norm_m[k]) if est[k] else 0.0,
                "disagreement_deg": float(d.rotation_norm_deg[k]) if est[k] else 0.0,
                "observable": bool(obs[k]),
                "n_correspondences": int(d.n_correspondences[k]),
                "n_unobservable_directions": int(d.n_unobservable[k]),
                "translation_m": [float(v) for v in d.translation_m[k]],
                "rotation_deg": [float(v) for v in d.rotation_deg[k]],
                "jump_m": float(j.translation_norm_m[k]),
                "jump_deg": float(j.rotation_norm_deg[k]),
                "step_m": float(self.split.step_norm_m[k]),
                "step_f": float(self.split.f_statistic[k]),
                "path_length_m": float(self.path_length_m[k]),
            })
        return out


# ---------------------------------------------------------------------------------------------- consensus step


@dataclass(frozen=True)
class _Consensus:
    """Per grouped point: residual to the consensus of an allowed frame set (and whether there was one)."""

    residual_m: NDArray[np.float64]
    valid: NDArray[np.bool_]
    mean_path_m: NDArray[np.float64]


class _CellTable:
    """Per (lateral cell, frame row) sums in (cell, row) order with prefix sums, for any frame subset that is
    a row range."""

    def __init__(self, sg: SurfaceGroups, rows: NDArray[np.int64], n_frames: int, path_m: NDArray[np.float64]):
        M = n_frames
        self.M = M
        key = sg.cell * M + rows
        self.entry, self.keys = dense_ids(key)
        E = len(self.keys)
        e_row = self.keys % M if E else np.zeros(0, np.int64)
        n_e = np.bincount(self.entry, minlength=E).astype(np.float64)
        s_e = np.bincount(self.entry, weights=sg.offset_m, minlength=E)
        self.cum_n = np.concatenate([[0.0], np.cumsum(n_e)])
        self.cum_s = np.concatenate([[0.0], np.cumsum(s_e)])
        self.cum_p = np.concatenate([[0.0], np.cumsum(n_e * path_m[e_row])]) if E else np.zeros(1)
        self.first = np.searchsorted(self.keys, np.arange(sg.n_cells) * M)
        self.own_n, self.own_s = n_e[self.entry], s_e[self.entry]

    def prefix(self, cells: NDArray[np.int64], last_row: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray]:
        """(count, offset sum, path sum) over the frames of each cell with row <= ``last_row`` (-1: none)."""
        first = self.first[cells]
        pos = np.maximum(np.searchsorted(self.keys, cells * self.M + np.minimum(last_row, self.M - 1), side="right"), first)
        return (self.cum_n[pos] - self.cum_n[first], self.cum_s[pos] - self.cum_s[first], self.cum_p[pos] - self.cum_p[first])


def _residuals(offset: NDArray[np.float64], n: NDArray, s: NDArray, p: NDArray, cfg: AttributionConfig) -> _Consensus:
    ok = n >= cfg.min_neighbors
    mean = np.where(ok, s / np.maximum(n, 1), 0.0)
    r = offset - mean
    return _Consensus(r, ok & (np.abs(r) <= cfg.max_residual_m), np.where(ok, p / np.maximum(n, 1), 0.0))


def _frame_steps(cloud: PlacedCloud, sg: SurfaceGroups, cons: _Consensus, cfg: AttributionConfig) -> FrameAlignment:
    """One robust Gauss-Newton step per frame from point-to-plane residuals (vectorised over frames)."""
    M = cloud.samples.n_frames
    idx = sg.point_index
    f = cloud.frame_index[idx]
    p = cloud.points_world[idx]
    n = sg.normals[sg.group]
    # linearise about the centroid of the frame's grouped points: t is how far its surfaces are off
    cnt = np.maximum(np.bincount(f, minlength=M), 1)[:, None]
    centroid = np.stack([np.bincount(f, weights=p[:, k], minlength=M) for k in range(3)], axis=1) / cnt
    L = cfg.lever_m
    J = np.concatenate([n, np.cross(p - centroid[f], n) / L], axis=1)  # rotation scaled to metres at lever L
    r = cons.residual_m
    sig2 = cloud.sigma_normal_m[idx].astype(np.float64) ** 2 + 1e-6
    huber = np.minimum(1.0, cfg.huber_m / np.maximum(np.abs(r), 1e-12))
    w = np.where(cons.valid, huber / sig2, 0.0)
    H = np.zeros((M, 6, 6))
    b = np.zeros((M, 6))
    for i in range(6):
        b[:, i] = np.bincount(f, weights=w * J[:, i] * r, minlength=M)
        for j in range(i, 6):
            H[:, i, j] = H[:, j, i] = np.bincount(f, weights=w * J[:, i] * J[:, j], minlength=M)
    n_corr = np.bincount(f, weights=cons.valid.astype(np.float64), minlength=M).astype(np.int64)
    lam, V = np.linalg.eigh(H)
    lam_max = np.maximum(lam[:, -1:], 1e-30)
    good = lam > cfg.min_relative_information * lam_max
    inv = np.where(good, 1.0 / np.where(good, lam, 1.0), 0.0)
    x = -np.einsum("mij,mj,mkj,mk->mi", V, inv, V, b)
    cov = np.einsum("mij,mj,mkj->mik", V, inv, V)
    has = n_corr >= 6
    x[~has] = 0.0
    n_unobs = np.where(has, 6 - good.sum(axis=1), 6)
    sigma_t = np.sqrt(np.maximum(np.linalg.eigvalsh(cov[:, :3, :3])[:, -1], 0.0))
    # trace of the projector onto the observable directions, per block: the expected share of |x|^2
    proj = np.einsum("mij,mj,mij->mi", V, good.astype(np.float64), V)
    share = np.stack([proj[:, :3].sum(axis=1), proj[:, 3:].sum(axis=1)], axis=1) / 3.0
    return FrameAlignment(
        translation_m=x[:, :3],
        rotation_deg=np.degrees(x[:, 3:] / L),
        n_correspondences=n_corr,
        n_unobservable=n_unobs.astype(np.int64),
        sigma_m=sigma_t,
        center_m=centroid,
        observed_share=np.where(has[:, None], share, 0.0),
    )


@dataclass(frozen=True)
class _Steps:
    disagreement: FrameAlignment
    jumps: FrameAlignment
    revisit: FrameAlignment
    revisit_path_m: NDArray[np.float64]
    revisit_fraction: float
    split: SplitScan


def _all_steps(cloud: PlacedCloud, cfg: AttributionConfig) -> _Steps:
    sg = surface_groups(cloud, cfg.voxel_size_m, normal_max_angle_deg=cfg.normal_max_angle_deg,
                        min_points=cfg.min_group_points, cell_fraction=cfg.cell_fraction)
    M = cloud.samples.n_frames
    rows = cloud.frame_index[sg.point_index]
    path = cloud.path_length_m
    table = _CellTable(sg, rows, M, path)
    cells, o = sg.cell, sg.offset_m
    tot_n, tot_s, tot_p = table.prefix(cells, np.full(len(cells), M - 1))
    # every other frame
    others = _residuals(o, tot_n - table.own_n, tot_s - table.own_s, tot_p - table.own_n * path[rows], cfg)
    # the window before
    a = table.prefix(cells, rows - 1)
    b = table.prefix(cells, rows - 1 - cfg.window)
    window = _residuals(o, a[0] - b[0], a[1] - b[1], a[2] - b[2], cfg)
    # frames seen at least revisit_min_path_m of travel earlier
    last_early = np.searchsorted(path, path - cfg.revisit_min_path_m, side="right") - 1
    early = table.prefix(cells, last_early[rows])
    revisit = _residuals(o, *early, cfg)
    first_late = np.searchsorted(path, path + cfg.revisit_min_path_m, side="left")
    late_n = tot_n - table.prefix(cells, first_late[rows] - 1)[0]
    revisited = (early[0] + late_n) > 0
    disagreement = _frame_steps(cloud, sg, others, cfg)
    jumps = _frame_steps(cloud, sg, window, cfg)
    rev = _frame_steps(cloud, sg, revisit, cfg)
    cnt = np.bincount(rows, weights=revisit.valid.astype(np.float64), minlength=M)
    mean_s = np.bincount(rows, weights=np.where(revisit.valid, revisit.mean_path_m, 0.0), minlength=M) / np.maximum(cnt, 1)
    revisit_path = np.where(cnt > 0, path - mean_s, 0.0)
    fraction = float(np.mean(revisited)) if len(revisited) else 0.0
    return _Steps(disagreement, jumps, rev, revisit_path, fraction, split_scan(cloud, sg, cfg))


@dataclass(frozen=True)
class SplitScan:
    """The change-point scan: per frame row ``j``, the step between the ``split_window`` frames before ``j`` and
    the ``split_window`` frames from ``j`` on (row 0 has none), fitted twice: as a translation, and as a rigid
    step (translation at frame ``j``'s sensor origin and a rotation about it, the error an odometry makes when it
    misjudges one relative pose). ``f_statistic`` is the larger of the two fits' F."""

    step_m: NDArray[np.float64]
    """(M, 3) world-frame step of the frames from ``j`` on relative to the frames before (observable part; of the
    rigid fit where its F is the larger, at the sensor origin of frame ``j``)."""
    f_statistic: NDArray[np.float64]
    """(M,) explained over residual variance per degree of freedom; 0 where fewer than ``min_split_cells`` cells."""
    n_cells: NDArray[np.int64]
    """Lateral cells seen on both sides of the split."""
    n_observable: NDArray[np.int64]
    """Directions (of 3, or 6 where the rigid fit is kept) the cells constrain."""
    rotation_deg: NDArray[np.float64] | None = None
    """(M, 3) world-frame rotation vector of the rigid fit (deg) where it is kept, else 0."""
    f_translation: NDArray[np.float64] | None = None
    f_rigid: NDArray[np.float64] | None = None
    displacement_m: NDArray[np.float64] | None = None
    """(M,) how far the kept step moves the split's surfaces (RMS over its cells; ``|step_m|`` for a translation)."""

    @property
    def step_norm_m(self) -> NDArray[np.float64]:
        """How far the step moves the surfaces (``displacement_m``; ``|step_m|`` for a translation)."""
        return np.linalg.norm(self.step_m, axis=1) if self.displacement_m is None else self.displacement_m

    @property
    def rotation_norm_deg(self) -> NDArray[np.float64]:
        return np.zeros(len(self.step_m)) if self.rotation_deg is None else np.linalg.norm(self.rotation_deg, axis=1)


def _robust_fit_per_split(J: NDArray[np.float64], d: NDArray[np.float64], w0: NDArray[np.float64],
                          j: NDArray[np.int64], M: int, cfg: AttributionConfig) -> tuple[NDArray, NDArray, NDArray]:
    """Per split ``j``: Huber-reweighted least squares of ``d = J x`` on the directions the rows constrain.
    Returns ``x`` (M, k), the F statistic (M,) and the rank (M,)."""
    k = J.shape[1]
    x = np.zeros((M, k))
    N = np.bincount(j, minlength=M)
    for _ in range(3):
        r = d - np.einsum("pi,pi->p", J, x[j])
        w = w0 * np.minimum(1.0, cfg.huber_m / np.maximum(np.abs(r), 1e-12))
        H = np.zeros((M, k, k))
        b = np.zeros((M, k))
        for a in range(k):
            b[:, a] = np.bincount(j, weights=w * d * J[:, a], minlength=M)
            for c in range(a, k):
                H[:, a, c] = H[:, c, a] = np.bincount(j, weights=w * J[:, a] * J[:, c], minlength=M)
        lam, V = np.linalg.eigh(H)
        good = lam > cfg.min_relative_information * np.maximum(lam[:, -1:], 1e-30)
        inv = np.where(good, 1.0 / np.where(good, lam, 1.0), 0.0)
        x = np.einsum("mij,mj,mkj,mk->mi", V, inv, V, b)
    rank = good.sum(axis=1)
    G = np.einsum("mi,mi->m", b, x)
    Q = np.bincount(j, weights=w * (d - np.einsum("pi,pi->p", J, x[j])) ** 2, minlength=M)
    enough = (N >= cfg.min_split_cells) & (rank > 0)
    F = np.where(enough, (G / np.maximum(rank, 1)) / np.maximum(Q / np.maximum(N - rank, 1), 1e-300), 0.0)
    x[~enough] = 0.0
    return x, F, np.where(enough, rank, 0)


def split_scan(cloud: PlacedCloud, sg: SurfaceGroups, config: AttributionConfig | None = None) -> SplitScan:
    """Fit a step at every split of the frame sequence from the surface cells both sides saw.

    For split ``j`` and every lateral cell seen by frames ``[j - W, j)`` (A) and ``[j, j + W)`` (B), the
    difference of the two sides' mean offsets along the cell's normal ``d = mean_B - mean_A`` (relief every
    frame sees cancels) is a point-to-plane observation of the step: ``d = n . t`` for a translation, ``d = n . t
    + ((p - o_j) x n) . w`` for a rigid step about frame ``j``'s sensor origin ``o_j`` (``p`` the cell's centre),
    weighted ``nA nB / (nA + nB) / sigma^2``. A few Huber-reweighted least-squares rounds give the step on the
    directions the cells constrain; ``F = (b . x / rank) / (Q / (N - rank))`` compares what the step explains
    with what it leaves (Q) over N cells. A pose jump at frame k gives the largest F at ``j = k``: every window
    around it sees both sides, and one frame later the windows already mix. A rotation error moves far surfaces
    more than near ones, which no single translation explains: a LiDAR's 3 deg yaw step is a 50 cm shift at
    10 m and 5 cm at 1 m. Both sides use surfaces of several frames, so a direction one frame alone cannot
    observe is still seen. Vectorised over all splits: every (cell, frame) entry takes part in the ``2 W``
    splits whose windows hold it."""
    cfg = config or AttributionConfig()
    M, W = cloud.samples.n_frames, cfg.split_window
    empty = SplitScan(np.zeros((M, 3)), np.zeros(M), np.zeros(M, np.int64), np.zeros(M, np.int64))
    if M < 2 or sg.n_cells == 0:
        return empty
    rows = cloud.frame_index[sg.point_index]
    s2 = cloud.sigma_normal_m[sg.point_index].astype(np.float64) ** 2
    entry, keys = dense_ids(sg.cell * M + rows)
    E = len(keys)
    e_cell, e_row = keys // M, keys % M
    n_e = np.bincount(entry, minlength=E).astype(np.float64)
    s_e = np.bincount(entry, weights=sg.offset_m, minlength=E)
    v_e = np.bincount(entry, weights=s2, minlength=E)
    # entry at row r is on side A of splits r+1 .. r+W and on side B of splits r-W+1 .. r
    shift = np.concatenate([np.arange(1, W + 1), np.arange(-W + 1, 1)])
    pe = np.repeat(np.arange(E), 2 * W)
    pj = e_row[pe] + np.tile(shift, E)
    ok = (pj >= 1) & (pj <= M - 1)
    pe, pj = pe[ok], pj[ok]
    before = pj > e_row[pe]
    pid, pkeys = dense_ids(e_cell[pe] * M + pj)
    P = len(pkeys)
    nA = np.bincount(pid, weights=np.where(before, n_e[pe], 0.0), minlength=P)
    nB = np.bincount(pid, weights=np.where(before, 0.0, n_e[pe]), minlength=P)
    sA = np.bincount(pid, weights=np.where(before, s_e[pe], 0.0), minlength=P)
    sB = np.bincount(pid, weights=np.where(before, 0.0, s_e[pe]), minlength=P)
    vv = np.bincount(pid, weights=v_e[pe], minlength=P)
    both = (nA > 0) & (nB > 0)
    nA, nB, sA, sB, vv, pkeys = nA[both], nB[both], sA[both], sB[both], vv[both], pkeys[both]
    j = pkeys % M
    cell = pkeys // M
    n = sg.normals[sg.cell_group[cell]]
    d = sB / nB - sA / nA
    # noise of d: the two sides' sensor noise plus pose jitter between frames (which more points do not average out)
    w0 = 1.0 / (vv / (nA + nB) * (1.0 / nA + 1.0 / nB) + cfg.split_jitter_m**2)
    x3, F3, rank3 = _robust_fit_per_split(n, d, w0, j, M, cfg)
    # the rigid step: cell centres relative to the split frame's sensor origin (rotation scaled to metres at lever_m)
    pts = cloud.points_world[sg.point_index]
    c_n = np.maximum(np.bincount(sg.cell, minlength=sg.n_cells), 1)
    centre = np.stack([np.bincount(sg.cell, weights=pts[:, k], minlength=sg.n_cells) for k in range(3)], axis=1) / c_n[:, None]
    arm = centre[cell] - cloud.origins_world[j]
    L = cfg.lever_m
    x6, F6, rank6 = _robust_fit_per_split(np.concatenate([n, np.cross(arm, n) / L], axis=1), d, w0, j, M, cfg)
    rigid = F6 > F3
    step = np.where(rigid[:, None], x6[:, :3], x3)
    rotation = np.where(rigid[:, None], np.degrees(x6[:, 3:] / L), 0.0)
    # how far the step moves the surfaces: RMS over the split's cells of |t + w x arm| (|t| for a translation)
    moved = step[j] + np.cross(np.radians(rotation[j]), arm)
    N = np.maximum(np.bincount(j, minlength=M), 1)
    displacement = np.where(rigid, np.sqrt(np.bincount(j, weights=np.einsum("pi,pi->p", moved, moved), minlength=M) / N),
                            np.linalg.norm(x3, axis=1))
    return SplitScan(step, np.maximum(F3, F6), np.bincount(j, minlength=M).astype(np.int64),
                     np.where(rigid, rank6, rank3).astype(np.int64), rotation, F3, F6, displacement)


def change_points(cloud: PlacedCloud, scan: SplitScan, jumps: FrameAlignment | None = None,
                  config: AttributionConfig | None = None,
                  row_sessions: NDArray[np.int64] | None = None) -> list[ChangePoint]:
    """Pose jumps: splits whose F statistic is the largest within ``split_window`` frames, at least
    ``change_point_f``, with a step of at least ``min_jump_m``. ``jump_deg`` is the rotation of the frame's
    own step against the frames just before it (``jumps``); ``z_score`` is the split's robust z-score of
    ``ln F`` over the sequence (how unusual it is for this map). ``row_sessions`` (a merged store's session of each
    frame row): a session's first frame is where two recordings meet, not a jump of one trajectory -- its split is
    left out (how the sessions sit on each other is the revisit check's cross-session pairs; hostile trial 14 W8)."""
    from scipy.ndimage import maximum_filter1d

    cfg = config or AttributionConfig()
    F, t = scan.f_statistic, scan.step_norm_m
    if row_sessions is not None and len(row_sessions) == len(F):
        starts = np.flatnonzero(np.diff(np.asarray(row_sessions)) != 0) + 1
        F = F.copy()
        F[starts] = 0.0
    if not np.any(F > 0):
        return []
    peak = F >= maximum_filter1d(F, 2 * cfg.split_window + 1, mode="constant")
    hits = np.flatnonzero(peak & (F >= cfg.change_point_f) & (t >= cfg.min_jump_m))
    logF = np.log(np.maximum(F[F > 0], 1e-12))
    med = np.median(logF)
    mad = 1.4826 * np.median(np.abs(logF - med)) + 1e-9
    rot = jumps.rotation_norm_deg if jumps is not None else np.zeros(len(F))
    step_deg = scan.rotation_deg if scan.rotation_deg is not None else np.zeros((len(F), 3))
    return [ChangePoint(int(cloud.frame_ids[k]), int(cloud.stamps_ns[k]), float(t[k]), float(rot[k]),
                        float((np.log(F[k]) - med) / mad), float(F[k]), [float(v) for v in scan.step_m[k]],
                        [float(v) for v in step_deg[k]])
            for k in hits]


def drift_rate(revisit: FrameAlignment, revisit_path_m: NDArray[np.float64], config: AttributionConfig | None = None) -> DriftRate:
    """Drift rate from the revisit disagreements: ``|x_k|^2 = floor^2 + q_k (rate * s_k)^2`` fitted by
    non-negative least squares over the frames, ``s_k`` the path travelled between frame k and the earlier
    frames it was compared with, ``q_k`` the share of a random-direction error frame k can observe
    (:attr:`FrameAlignment.observed_share`; translation and rotation separately).

    A single frame's disagreement has a noise floor that does not grow with ``s`` (sensor bias, the frame's
    weakly constrained directions: about 1 cm and 1 deg on 7-Scenes); a line through the origin of ``|x|``
    against ``s`` turns that floor into a phantom drift (0.31 %/m and 0.29 deg/m on the reference poses). The
    intercept takes it up instead; ``noise_floor_m`` / ``noise_floor_deg`` report it."""
    from scipy.optimize import nnls

    cfg = config or AttributionConfig()
    ok = revisit.estimated(cfg.min_correspondences) & (revisit_path_m >= cfg.revisit_min_path_m)
    if not ok.any():
        return DriftRate(None, None, 0, 0.0)
    s = revisit_path_m[ok]
    # with too few frames or one path length the floor cannot be told from drift: a line through the origin
    with_floor = ok.sum() >= 3 and np.ptp(s) > 0.1 * s.max()
    share = revisit.observed_share[ok] if revisit.observed_share is not None else np.ones((len(s), 2))

    def fit(y: NDArray[np.float64], q: NDArray[np.float64]) -> tuple[float, float | None]:
        A = np.stack([np.ones_like(s), q * s * s], axis=1) if with_floor else (q * s * s)[:, None]
        coef, _ = nnls(A, y * y)
        return (float(np.sqrt(coef[1])), float(np.sqrt(coef[0]))) if with_floor else (float(np.sqrt(coef[0])), None)

    rate_t, floor_t = fit(revisit.translation_norm_m[ok], share[:, 0])
    rate_r, floor_r = fit(revisit.rotation_norm_deg[ok], share[:, 1])
    return DriftRate(100.0 * rate_t, rate_r, int(ok.sum()), float(s.max()), floor_t, floor_r)


def attribute(cloud: PlacedCloud, config: AttributionConfig | None = None,
              row_sessions: NDArray[np.int64] | None = None) -> Attribution:
    """Disagreement, jumps, change points, drift rate and revisit fraction of a placed cloud (``row_sessions``: a
    merged store's session of each frame row, see :func:`change_points`)."""
    cfg = config or AttributionConfig()
    steps = _all_steps(cloud, cfg)
    cps = change_points(cloud, steps.split, steps.jumps, cfg, row_sessions)
    drift = drift_rate(steps.revisit, steps.revisit_path_m, cfg)
    result = Attribution(cloud.frame_ids.copy(), cloud.stamps_ns.copy(), cloud.path_length_m.copy(), steps.disagreement,
                         steps.jumps, steps.revisit, steps.revisit_path_m, cps, drift, steps.revisit_fraction, cfg,
                         steps.split)
    if result.revisit_note:
        logger.warning(result.revisit_note)
    logger.info("attribution: %d change points, drift %s %%/m %s deg/m, revisit fraction %.3f", len(cps),
                drift.percent_per_m, drift.deg_per_m, steps.revisit_fraction)
    return result


__all__ = [
    "Attribution", "AttributionConfig", "ChangePoint", "DriftRate", "FrameAlignment", "SegmentErrors", "SplitScan",
    "attribute", "change_points", "drift_rate", "ground_truth_errors", "segment_errors", "split_scan",
]
"""Public names; ``SegmentErrors``, ``segment_errors`` and ``ground_truth_errors`` live in
:mod:`driftmap.diagnostics.ground_truth` and are re-exported here."""
