"""The figures of a diagnosis (matplotlib, headless ``Agg`` backend): the map's top view with the flagged double
walls, the per-frame disagreement over time with the change points, and a before/after comparison of the
smearing scores; :func:`write_report` writes them as PNG files.

:func:`plot_state_top_view` draws the volumetric layers (:mod:`driftmap.volume`) from above: free / occupied /
unknown space in a height band (``driftmap diagnose --report``, the demo and ``driftmap view --color state`` all
draw it with this one function)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from driftmap.diagnostics.diagnosis import Diagnosis  # noqa: E402
from driftmap.diagnostics.samples import PlacedCloud  # noqa: E402
from driftmap.errors import ConfigError  # noqa: E402
from driftmap.frame import SensorKind  # noqa: E402

if TYPE_CHECKING:
    from driftmap.volume.grid import GridSpec

logger = logging.getLogger(__name__)


def sensor_up(poses: NDArray[np.floating], sensor_kind: SensorKind) -> NDArray[np.float64]:
    """World 'up' from how the sensors were held (``poses``: (N, 4, 4) T_world_sensor): minus the mean camera y
    axis (image down) for depth cameras, the mean sensor z axis for LiDAR; +z when they cancel out."""
    R = np.asarray(poses, dtype=np.float64)[:, :3, :3]
    up = R[:, :, 2].mean(axis=0) if sensor_kind is SensorKind.LIDAR else -R[:, :, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])


def _up_axis(placed: PlacedCloud) -> NDArray[np.float64]:
    kinds = placed.samples.sensor_kinds
    lidar = sum(k is SensorKind.LIDAR for k in kinds) > len(kinds) / 2
    return sensor_up(placed.poses, SensorKind.LIDAR if lidar else SensorKind.DEPTH_CAMERA)


def _plane_axes(up: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - up * (helper @ up)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def plot_double_walls(path: str | Path, diagnosis: Diagnosis, *, max_points: int = 150_000, title: str | None = None) -> Path:
    """Top view of the map (grey) with every flagged surface group coloured by its separation (cm)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    placed, walls = diagnosis.placed, diagnosis.double_walls
    up = _up_axis(placed)
    e1, e2 = _plane_axes(up)
    P = placed.points_world
    if len(P) > max_points:
        P = P[np.random.default_rng(0).choice(len(P), max_points, replace=False)]
    fig, ax = plt.subplots(figsize=(8.0, 7.0))
    ax.scatter(P @ e1, P @ e2, s=0.2, c="0.75", linewidths=0, rasterized=True)
    centers, seps, sizes = [], [], []
    for s in walls.scales:
        sel = s.flagged
        centers.append(s.centers_m[sel])
        seps.append(np.abs(s.separation_m[sel]) * 100)
        sizes.append(np.full(int(sel.sum()), s.voxel_size_m))
    if centers and sum(len(c) for c in centers):
        C, S, Z = np.concatenate(centers), np.concatenate(seps), np.concatenate(sizes)
        order = np.argsort(-Z)  # large voxels first, small ones on top
        sc = ax.scatter(C[order] @ e1, C[order] @ e2, c=S[order], s=8 + 120 * Z[order] / Z.max(), cmap="inferno_r",
                        vmin=0, vmax=max(float(np.percentile(S, 95)), 1.0), edgecolors="k", linewidths=0.3)
        fig.colorbar(sc, ax=ax, label="double-wall separation (cm)", shrink=0.8)
        for k, region in enumerate(walls.regions[:8]):
            ax.annotate(f"{k + 1}", (region.center_m @ e1, region.center_m @ e2), fontsize=8, color="navy",
                        xytext=(4, 4), textcoords="offset points")
    traj = placed.origins_world
    ax.plot(traj @ e1, traj @ e2, "-", color="tab:blue", lw=0.8, alpha=0.7, label="sensor path")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    ax.grid(alpha=0.3)
    ax.set_title(title or (f"revision {diagnosis.revision}: {walls.voxels_flagged} of {walls.voxels_evaluated} surface "
                           f"voxels doubled ({100 * walls.fraction_flagged:.1f} %), smearing "
                           f"{1000 * walls.smearing_score_m:.1f} mm"), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_frame_disagreement(path: str | Path, diagnosis: Diagnosis, *, title: str | None = None) -> Path:
    """Per-frame disagreement with the map and jump against the frames before, over time, with change points."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    at = diagnosis.attribution
    cfg = at.config
    x = at.frame_ids
    est = at.disagreement.estimated(cfg.min_correspondences)
    obs = at.disagreement.observable(cfg.min_correspondences)
    fig, axes = plt.subplots(2, 1, figsize=(10.0, 6.0), sharex=True)
    step = at.split.step_norm_m
    step_label = f"step: {cfg.split_window} frames from here vs the {cfg.split_window} before"
    for ax, d, j, unit, scale, label in (
            (axes[0], at.disagreement.translation_norm_m, step, "mm", 1000.0, step_label),
            (axes[1], at.disagreement.rotation_norm_deg, at.jumps.rotation_norm_deg, "deg", 1.0, f"jump vs the {cfg.window} frames before")):
        ax.plot(x[est], d[est] * scale, ".-", ms=3, lw=0.8, color="tab:blue", label="disagreement with the map")
        ax.plot(x[est & ~obs], d[est & ~obs] * scale, "x", ms=4, color="0.5", label="(a direction unobservable)")
        ax.plot(x, j * scale, "-", lw=0.8, color="tab:orange", label=label)
        for cp in at.change_points:
            ax.axvline(cp.frame_id, color="crimson", lw=1.0, alpha=0.8)
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
    if at.change_points:
        axes[0].plot([], [], color="crimson", label="change point")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[1].legend(loc="upper right", fontsize=8)
    axes[1].set_xlabel("frame id")
    drift = at.drift
    rate = ("no revisit: drift invisible" if drift.percent_per_m is None
            else f"drift ~{drift.percent_per_m:.2f} %/m, {drift.deg_per_m:.3f} deg/m")
    axes[0].set_title(title or f"revision {diagnosis.revision}: per-frame disagreement; {len(at.change_points)} change "
                               f"points; {rate}; revisited {100 * at.revisit_fraction:.0f} %", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_score_comparison(path: str | Path, diagnoses: dict[str, Diagnosis], *, title: str | None = None) -> Path:
    """Smearing score per voxel scale and overall, and the share of doubled voxels, for several revisions
    (e.g. before / after a correction)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = list(diagnoses)
    scales = sorted({s for d in diagnoses.values() for s in d.double_walls.score_per_scale_m})
    groups = [f"{s:g} m" for s in scales] + ["overall"]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11.0, 4.2), gridspec_kw={"width_ratios": [3, 1]})
    width = 0.8 / max(len(labels), 1)
    for k, label in enumerate(labels):
        d = diagnoses[label].double_walls
        vals = [d.score_per_scale_m.get(s, float("nan")) * 1000 for s in scales] + [d.smearing_score_m * 1000]
        ax.bar(np.arange(len(groups)) + k * width, vals, width, label=label)
        bar = ax2.bar(k, 100 * d.fraction_flagged, 0.6, label=label, color=f"C{k}")
        ax2.bar_label(bar, fmt="%.2f %%", fontsize=8)
    ax.set_xticks(np.arange(len(groups)) + width * (len(labels) - 1) / 2, groups)
    ax.set_ylabel("smearing score (mm)")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    ax2.set_xticks(range(len(labels)), [label.replace(" (", "\n(") for label in labels], fontsize=7)
    ax2.set_ylabel("surface voxels doubled (%)")
    ax2.grid(axis="y", alpha=0.3)
    fig.suptitle(title or "smearing before / after", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_report(out_dir: str | Path, diagnosis: Diagnosis, *, compare: dict[str, Diagnosis] | None = None) -> dict[str, Path]:
    """The PNG figures of a diagnosis (and, with ``compare``, the before/after score figure)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "double_walls": plot_double_walls(out / f"double_walls_rev{diagnosis.revision}.png", diagnosis),
        "frame_disagreement": plot_frame_disagreement(out / f"frame_disagreement_rev{diagnosis.revision}.png", diagnosis),
    }
    if compare:
        files["score_comparison"] = plot_score_comparison(out / "smearing_before_after.png", compare)
    return files


# ------------------------------------------------------------------------------- volumetric layers from above
STATE_TOP_VIEW_RGB = {1: (25, 25, 25), 0: (240, 240, 232), -1: (150, 156, 172)}
"""Cell colours of :func:`plot_state_top_view`: occupied black, free near white, unknown grey-blue (as ROS maps)."""
STATE_TOP_VIEW_LABELS = {1: "occupied", 0: "free", -1: "unknown"}
SENSOR_PATH_RGB = (31, 119, 180)
BAND_BELOW_SENSOR_M = 0.7
BAND_ABOVE_SENSOR_M = 0.3
"""The default height band of a top view: from this far below the sensors' median height to this far above it
(walls and furniture at sensor height; the floor and the ceiling left out)."""
TOP_VIEW_MAP_PX = 720
"""The longer side of a top view's map area (pixels); the shorter one follows the extent's aspect."""
TOP_VIEW_MARGINS_PX = (70, 170, 46, 50)
"""Left, right (the legend), top (the title) and bottom margins around the map area (pixels)."""
TOP_VIEW_DPI = 100


def up_grid_axis(up: Sequence[float] | NDArray[np.floating]) -> tuple[int, int]:
    """The world (= grid) axis nearest the direction ``up`` and its sign: a top view looks down along it."""
    u = np.asarray(up, dtype=np.float64)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or not np.any(u):
        raise ConfigError(f"top view: 'up' must be a finite non-zero 3-vector, got {up!r}")
    k = int(np.argmax(np.abs(u)))
    return k, 1 if u[k] > 0 else -1


def sensor_band_m(sensor_origins_m: NDArray[np.floating], up: Sequence[float] | NDArray[np.floating] = (0.0, 0.0, 1.0),
                  below_m: float = BAND_BELOW_SENSOR_M, above_m: float = BAND_ABOVE_SENSOR_M) -> tuple[float, float]:
    """The height band ``(lo, hi)`` (metres along the grid axis nearest ``up``) around the sensors' median height."""
    origins = np.asarray(sensor_origins_m, dtype=np.float64).reshape(-1, 3)
    if len(origins) == 0:
        raise ConfigError("top view: no sensor origin to place the height band at")
    k, sign = up_grid_axis(up)
    height = float(np.median(sign * origins[:, k]))
    return height - below_m, height + above_m


@dataclass(frozen=True)
class StateTopView:
    """The volumetric layers from above: each column of voxels in a height band reduced to one cell, occupied
    (1) if any of its voxels is, else free (0) if any is, else unknown (-1) (as :func:`driftmap.volume.export.
    occupancy_grid2d` does for z up)."""

    cells: NDArray[np.int8]
    """``[i, j]``: the column ``i`` along the image's right axis, ``j`` along its up axis"""
    axes: tuple[int, int]
    """the world axes along the image's right and up (x, y for a z-up world)"""
    up_axis: int
    up_sign: int
    min_m: tuple[float, float]
    """world coordinates (along :attr:`axes`) of the corner of cell ``(0, 0)``"""
    voxel_size_m: float
    band_m: tuple[float, float]
    n_layers: int
    """voxel layers inside the band"""

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """``(right_min, right_max, up_min, up_max)`` in metres."""
        (a0, b0), vs = self.min_m, self.voxel_size_m
        return a0, a0 + self.cells.shape[0] * vs, b0, b0 + self.cells.shape[1] * vs

    def counts(self) -> dict[str, int]:
        return {name: int(np.sum(self.cells == state)) for state, name in STATE_TOP_VIEW_LABELS.items()}

    def plane_m(self, points_m: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 3) world points -> (N, 2) their coordinates along the image's right and up axes."""
        return np.asarray(points_m, dtype=np.float64).reshape(-1, 3)[:, list(self.axes)]

    def cell_index(self, points_m: NDArray[np.floating]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """(N, 3) world points -> (N, 2) the cells they fall in, and which lie inside the view."""
        idx = np.floor((self.plane_m(points_m) - np.asarray(self.min_m)) / self.voxel_size_m).astype(np.int64)
        return idx, np.all((idx >= 0) & (idx < np.asarray(self.cells.shape)), axis=1)


def state_top_view(states: NDArray[np.integer], grid: GridSpec, band_m: Sequence[float],
                   up: Sequence[float] | NDArray[np.floating] = (0.0, 0.0, 1.0)) -> StateTopView:
    """``states`` (a state grid shaped as ``grid``: 1 occupied, 0 free, -1 unknown) seen from above along the grid
    axis nearest ``up``, its voxel layers with centres in ``band_m`` (metres along that signed axis) reduced per
    column. Raises :class:`ConfigError` for a grid of another shape or a band that holds no voxel layer."""
    states = np.asarray(states)
    if states.shape != tuple(grid.shape):
        raise ConfigError(f"top view: a state grid of shape {states.shape} does not fit the grid ({grid.describe()})")
    lo, hi = (float(v) for v in band_m)
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
        raise ConfigError(f"top view: the height band must be finite and ordered, got {lo:g} .. {hi:g} m")
    k, sign = up_grid_axis(up)
    vs = grid.voxel_size_m
    heights = sign * (grid.origin_index[k] + np.arange(grid.shape[k]) + 0.5) * vs
    sel = np.flatnonzero((heights >= lo) & (heights <= hi))
    if len(sel) == 0:
        raise ConfigError(f"top view: the band {lo:g} .. {hi:g} m holds no voxel layer (layer centres span "
                          f"{heights.min():.3f} .. {heights.max():.3f} m)")
    column = np.take(states, sel, axis=k)
    occupied, free = np.any(column == 1, axis=k), np.any(column == 0, axis=k)
    cells = np.where(occupied, 1, np.where(free, 0, -1)).astype(np.int8)
    a, b = (k + 1) % 3, (k + 2) % 3  # e_a x e_b = e_k: looking down, right x up points at the viewer
    if sign < 0:
        a, b = b, a
    if a > b:  # the cells are indexed by the two remaining axes in increasing order
        cells = np.ascontiguousarray(cells.T)
    return StateTopView(cells, (a, b), k, sign, (grid.origin_index[a] * vs, grid.origin_index[b] * vs), vs,
                        (lo, hi), len(sel))


@dataclass(frozen=True)
class TopViewLayout:
    """Where a top view's map area lies in its PNG: the image size and the map box (pixels), and the world extent
    the box shows (metres along the image's right and up axes)."""

    width_px: int
    height_px: int
    box_px: tuple[int, int, int, int]
    """left, top, right, bottom of the map area (image rows grow downwards)"""
    extent_m: tuple[float, float, float, float]

    def pixels(self, plane_m: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 2) coordinates along the image's right and up axes (metres) -> (N, 2) pixel (column, row)."""
        p = np.asarray(plane_m, dtype=np.float64).reshape(-1, 2)
        (l, t, r, b), (a0, a1, b0, b1) = self.box_px, self.extent_m
        return np.c_[l + (p[:, 0] - a0) / (a1 - a0) * (r - l), t + (b1 - p[:, 1]) / (b1 - b0) * (b - t)]


def top_view_layout(extent_m: Sequence[float]) -> TopViewLayout:
    """The PNG layout :func:`plot_state_top_view` uses for ``extent_m`` (right_min, right_max, up_min, up_max): the
    map area's longer side :data:`TOP_VIEW_MAP_PX`, the margins :data:`TOP_VIEW_MARGINS_PX`."""
    a0, a1, b0, b1 = (float(v) for v in extent_m)
    if not (a1 > a0 and b1 > b0):
        raise ConfigError(f"top view: an empty extent {extent_m!r}")
    scale = TOP_VIEW_MAP_PX / max(a1 - a0, b1 - b0)
    map_w, map_h = max(round((a1 - a0) * scale), 1), max(round((b1 - b0) * scale), 1)
    left, right, top, bottom = TOP_VIEW_MARGINS_PX
    return TopViewLayout(left + map_w + right, top + map_h + bottom, (left, top, left + map_w, top + map_h),
                         (a0, a1, b0, b1))


def union_extent(*extents_m: Sequence[float]) -> tuple[float, float, float, float]:
    """The smallest extent holding every one of ``extents_m`` (to draw several top views alike)."""
    e = np.asarray(extents_m, dtype=np.float64).reshape(-1, 4)
    return float(e[:, 0].min()), float(e[:, 1].max()), float(e[:, 2].min()), float(e[:, 3].max())


@dataclass(frozen=True)
class TopViewFigure:
    """What :func:`plot_state_top_view` drew: the file, the cells and the layout (to trace pixels to the world)."""

    path: Path
    view: StateTopView
    layout: TopViewLayout


def plot_state_top_view(path: str | Path, states: NDArray[np.integer], grid: GridSpec, *,
                        band_m: Sequence[float] | None = None,
                        up: Sequence[float] | NDArray[np.floating] = (0.0, 0.0, 1.0),
                        sensor_origins_m: NDArray[np.floating] | None = None, extent_m: Sequence[float] | None = None,
                        title: str | None = None) -> TopViewFigure:
    """A PNG of the volumetric layers from above (:func:`state_top_view`): occupied / free / unknown cells in the
    colours :data:`STATE_TOP_VIEW_RGB`, the sensor path (``sensor_origins_m``) on top, axes in metres.

    ``band_m``: the height band (default: :func:`sensor_band_m` of ``sensor_origins_m``). ``extent_m``: the world
    box drawn (default: the grid's; several views drawn with one extent are pixel-aligned, :func:`union_extent`).
    The layout is :func:`top_view_layout`'s, so :meth:`TopViewLayout.pixels` traces a pixel to the world."""
    if band_m is None:
        if sensor_origins_m is None:
            raise ConfigError("top view: give the height band or the sensor origins to place it")
        band_m = sensor_band_m(sensor_origins_m, up)
    view = state_top_view(states, grid, band_m, up)
    layout = top_view_layout(view.extent_m if extent_m is None else extent_m)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    dpi = TOP_VIEW_DPI
    fig = plt.figure(figsize=(layout.width_px / dpi, layout.height_px / dpi), dpi=dpi)
    (l, t, r, b), W, H = layout.box_px, layout.width_px, layout.height_px
    ax = fig.add_axes((l / W, 1.0 - b / H, (r - l) / W, (b - t) / H))
    lut = np.zeros((3, 3), dtype=np.uint8)
    for state, rgb in STATE_TOP_VIEW_RGB.items():
        lut[state + 1] = rgb
    ax.imshow(lut[view.cells.astype(np.int64) + 1].transpose(1, 0, 2), origin="lower", extent=view.extent_m,
              interpolation="nearest", aspect="auto")
    if sensor_origins_m is not None and len(sensor_origins_m):
        path_m = view.plane_m(sensor_origins_m)
        ax.plot(path_m[:, 0], path_m[:, 1], "-", color=np.asarray(SENSOR_PATH_RGB) / 255, lw=1.0, label="sensor path")
    ax.set_xlim(*layout.extent_m[:2])
    ax.set_ylim(*layout.extent_m[2:])
    ax.set_xlabel(f"{'xyz'[view.axes[0]]} (m)")
    ax.set_ylabel(f"{'xyz'[view.axes[1]]} (m)")
    counts, n = view.counts(), view.cells.size
    handles = [plt.Rectangle((0, 0), 1, 1, facecolor=np.asarray(STATE_TOP_VIEW_RGB[s]) / 255, edgecolor="0.3",
                             label=f"{name} ({100 * counts[name] / n:.0f} %)") for s, name in STATE_TOP_VIEW_LABELS.items()]
    handles += ax.get_legend_handles_labels()[0]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)
    sign = "" if view.up_sign > 0 else "-"
    fig.text(0.5, 1.0 - 0.5 * t / H, title or f"free / occupied / unknown from above ({sign}{'xyz'[view.up_axis]} "
             f"{view.band_m[0]:.2f} .. {view.band_m[1]:.2f} m, voxel {view.voxel_size_m:g} m)",
             ha="center", va="center", fontsize=10)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    logger.info("top view: %s, %s", path, ", ".join(f"{v} {k}" for k, v in counts.items()))
    return TopViewFigure(path, view, layout)
