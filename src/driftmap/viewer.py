"""The map viewer behind ``driftmap view``: a store's map in one revision, coloured by frame, by how far a
correction moved each point, by double-wall separation, or by session (``session``: each session of a merged store
in its own colour, :data:`~driftmap.render.SESSION_PALETTE_RGB`); or (``state``) the revision's volumetric layers
(:mod:`driftmap.volume`): every occupied voxel coloured by its height, and free / occupied / unknown space from
above in one more PNG (``states-top``).

Backends (``backend=``):

- ``window``: an interactive Open3D window (``draw_geometries``); needs a display.
- ``open3d``: Open3D's ``OffscreenRenderer`` (Filament) writes PNG views. It runs in a child process,
  because Filament aborts the whole process when it finds no EGL/Vulkan driver; any failure (or a blank
  image) falls back to ``software``.
- ``software``: a numpy z-buffer splatter (nearest point wins per pixel, light eye-dome shading) writes
  the same PNG views with the same cameras and colours; needs nothing but numpy, Pillow and matplotlib.
- ``rerun``: logs the coloured cloud and the sensor path to rerun (optional extra ``driftmap[viewer]``):
  a spawned viewer when a display exists, else ``OUT/map_rev<N>_<color>.rrd``.
- ``auto`` (default): ``window`` with a display, else ``open3d`` falling back to ``software``.

Every PNG view is exactly ``width_px x height_px`` with a pinhole camera (:class:`ViewCamera`, OpenCV
convention: x right, y down, z forward), so a pixel can be traced back to world points; ``overview``
puts the views side by side with a colour bar. See ``docs/viewer.md``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap, Normalize  # noqa: E402
from numpy.typing import NDArray  # noqa: E402
from PIL import Image  # noqa: E402

from driftmap.diagnostics.figures import TopViewFigure, plot_state_top_view, sensor_band_m, sensor_up  # noqa: E402
from driftmap.errors import ConfigError, StoreError  # noqa: E402
from driftmap.frame import SensorKind  # noqa: E402
from driftmap.map.view import MapView  # noqa: E402
from driftmap.preprocess.scene import LIDAR_OUTDOOR_P99_RANGE_M, scan_reach_m  # noqa: E402
from driftmap.render import (  # noqa: E402,F401
    BACKGROUND_RGB,
    SESSION_PALETTE_RGB,
    ViewCamera,
    display_available,
    display_problem,
    fit_camera,
    look_along,
    render_software,
)
from driftmap.viewer_sessions import SessionColor, latest_state_of, session_colours, store_session_ids  # noqa: E402,F401
from driftmap.viewer_walls import double_wall_values  # noqa: E402
from driftmap.voxels import ABSOLUTE_GRID, random_per_key, voxel_keys  # noqa: E402

if TYPE_CHECKING:
    from driftmap.diagnostics.wall_results import DoubleWallResult
    from driftmap.store.frame_store import FrameStore
    from driftmap.volume import VolumeLayers

logger = logging.getLogger(__name__)

COLOR_MODES = ("frame", "revision", "double-wall", "state", "session")
BACKENDS = ("auto", "window", "open3d", "software", "rerun")
DISPLAY_POSE_EPSILON = 1e-12
"""``--color revision`` draws a frame grey (not moved) when no entry of its pose changed by more than this."""
#: Display voxel size per sensor kind (m).
DEFAULT_VOXEL_SIZE_M = {SensorKind.DEPTH_CAMERA: 0.02, SensorKind.LIDAR: 0.2}
#: Top views of depth-camera maps drop points this far above the mean sensor height (ceilings hide the room).
DEFAULT_TOP_VIEW_CLIP_M = {SensorKind.DEPTH_CAMERA: 0.6, SensorKind.LIDAR: None}
GREY_RGB = (120, 120, 120)
"""Points without a value: unchanged by the correction, or not on a flagged double wall."""
# (colormap, lower, upper end used): both ends stay visible on the dark background
_PALETTES = {"frame": ("turbo", 0.08, 0.95), "revision": ("inferno", 0.3, 1.0), "double-wall": ("inferno", 0.3, 1.0),
             "state": ("viridis", 0.15, 1.0)}
_OPEN3D_TIMEOUT_S = 300.0


# ---------------------------------------------------------------------------------------------- data


@dataclass(frozen=True)
class ColoredMap:
    """The voxel-downsampled map of one revision with one colour per point.

    ``values`` is what the colour encodes (frame id, displacement in m, double-wall separation in m, height in
    m); NaN where a point is grey. ``frame_ids`` is the frame each kept point came from (one real point per voxel).
    Colour ``state``: the points are the centres of the occupied voxels of ``layers``, ``frame_ids`` the first frame
    whose rays ended in each (-1: none), ``n_points_map`` the number of occupied voxels.
    """

    revision: int
    color: str
    points_world: NDArray[np.float32]
    frame_ids: NDArray[np.int64]
    colors: NDArray[np.uint8]
    values: NDArray[np.float64]
    value_label: str
    value_range: tuple[float, float]
    colormap: ListedColormap
    n_points_map: int
    voxel_size_m: float
    sensor_kind: SensorKind
    up: NDArray[np.float64]
    sensor_origins_world: NDArray[np.float64]
    reference_revision: int | None = None
    double_walls: DoubleWallResult | None = None
    layers: VolumeLayers | None = None
    sessions: tuple[SessionColor, ...] | None = None
    """Colour ``session``: every session of the store with its colour (one entry for a store that no merge made)."""
    double_wall_caveats: tuple[str, ...] = ()
    """Colour ``double-wall``: why the flagged count is no verdict (empty: the surfaces allow one)."""

    @property
    def n_points(self) -> int:
        return len(self.points_world)


@dataclass(frozen=True)
class ViewResult:
    """What :func:`view_store` did: the backend that drew, the files written, the cameras used."""

    backend: str
    revision: int
    color: str
    files: dict[str, Path]
    cameras: list[ViewCamera]
    n_points_map: int
    n_points_shown: int
    voxel_size_m: float
    value_label: str
    value_range: tuple[float, float]
    reference_revision: int | None = None
    n_double_wall_voxels: int | None = None
    fallback_reason: str | None = None
    """Why the ``open3d`` backend fell back to ``software`` (None: it did not)."""
    seconds: dict[str, float] = field(default_factory=dict)
    colored: ColoredMap | None = field(default=None, repr=False)
    """The points, frame ids, values and colours that were drawn."""
    volume_counts: dict[str, int] | None = None
    """Colour ``state``: the layers' voxels by state (occupied / free / unknown)."""
    state_top_view: TopViewFigure | None = field(default=None, repr=False)
    """Colour ``state`` with an output folder: the free / occupied / unknown top view (``files["states-top"]``)."""
    sessions: tuple[SessionColor, ...] | None = None
    """Colour ``session``: every session with its colour, frames, source store and points shown."""


# ---------------------------------------------------------------------------------------------- helpers


def store_sensor_kind(store: FrameStore) -> SensorKind:
    """The sensor kind of most of the store's frames."""
    if len(store) == 0:
        raise StoreError(f"{store.path}: the store has no frames")
    kinds = [SensorKind(store.frame_info(int(f))["sensor_kind"]) for f in store.frame_ids]
    return max(set(kinds), key=kinds.count)


def default_voxel_size_m(store: FrameStore) -> float:
    """2 cm for depth-camera maps and LiDAR maps of a room (the first scan reaches < 25 m), 20 cm for outdoor
    LiDAR maps."""
    kind = store_sensor_kind(store)
    if kind is SensorKind.LIDAR:
        first = next(f for f in store.frame_ids if store.frame_info(int(f))["sensor_kind"] == kind.value)
        reach_m = scan_reach_m(store.frame(int(first)))
        if reach_m is not None and reach_m < LIDAR_OUTDOOR_P99_RANGE_M:  # a room, a corridor
            return DEFAULT_VOXEL_SIZE_M[SensorKind.DEPTH_CAMERA]
    return DEFAULT_VOXEL_SIZE_M[kind]


def _check_color(color: str) -> str:
    if color not in COLOR_MODES:
        raise ConfigError(f"--color must be one of {', '.join(COLOR_MODES)}, got {color!r}")
    return color


def _check_revision(store: FrameStore, revision: int | None, what: str = "--revision") -> int:
    rev = store.head if revision is None else revision
    if not isinstance(rev, (int, np.integer)) or not 0 <= int(rev) <= store.head:
        raise StoreError(f"{store.path}: {what} {rev} does not exist (the store has revisions 0..{store.head})")
    return int(rev)


def _downsample(store: FrameStore, revision: int, voxel_size_m: float, max_points: int,
                seed: int) -> tuple[NDArray[np.float32], NDArray[np.int64], int]:
    """One real point per occupied voxel (chosen at random, so no frame is favoured), with its frame id."""
    view = MapView.from_store(store, revision)
    rng = np.random.default_rng(seed)
    kept_p, kept_f, kept_k = [], [], []
    chunk: list[int] = []
    size = 0

    def flush() -> None:
        nonlocal chunk, size
        if not chunk:
            return
        parts = [view.frame_points_world(f) for f in chunk]
        pts = np.concatenate(parts)
        fid = np.repeat(np.asarray(chunk, np.int64), [len(p) for p in parts])
        ok = np.all(np.isfinite(pts), axis=1)
        pts, fid = pts[ok], fid[ok]
        keys = voxel_keys(pts, voxel_size_m, grid=ABSOLUTE_GRID,  # compared across chunks below
                          what=f"view --voxel-size-m {voxel_size_m:g}")
        sel = random_per_key(keys, rng)
        kept_p.append(pts[sel])
        kept_f.append(fid[sel])
        kept_k.append(keys[sel])
        chunk, size = [], 0

    for fid in view.frame_ids:
        chunk.append(int(fid))
        size += len(view.frame_points_world(int(fid)))
        if size >= 4_000_000:
            flush()
    flush()
    n_map = view.n_points
    if not kept_p:
        raise StoreError(f"{store.path}: revision {revision} has no points to show")
    sel = random_per_key(np.concatenate(kept_k), rng)
    points, frame_ids = np.concatenate(kept_p)[sel], np.concatenate(kept_f)[sel]
    if len(points) > max_points:
        logger.info("view: %d voxels; showing a random %d of them", len(points), max_points)
        pick = np.sort(rng.choice(len(points), max_points, replace=False))
        points, frame_ids = points[pick], frame_ids[pick]
    if len(points) == 0:
        raise StoreError(f"{store.path}: revision {revision} has no finite points to show")
    return np.ascontiguousarray(points, np.float32), frame_ids, n_map


def _up_axis(poses: NDArray[np.float64], kind: SensorKind) -> NDArray[np.float64]:
    """World 'up': the mean sensor z axis for LiDAR, minus the mean camera y axis (image down) otherwise."""
    return sensor_up(poses, kind)


def _palette(color: str) -> ListedColormap:
    if color == "session":
        return ListedColormap(np.asarray(SESSION_PALETTE_RGB) / 255.0, name="tab10")
    name, lo, hi = _PALETTES[color]
    return ListedColormap(plt.get_cmap(name)(np.linspace(lo, hi, 256)), name=f"{name}[{lo}:{hi}]")


def _apply_palette(values: NDArray[np.float64], value_range: tuple[float, float], cmap: ListedColormap) -> NDArray[np.uint8]:
    lo, hi = value_range
    t = np.clip((values - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0)
    rgb = (cmap(np.nan_to_num(t, nan=0.0))[:, :3] * 255 + 0.5).astype(np.uint8)
    rgb[~np.isfinite(values)] = GREY_RGB
    return rgb


def _displacement_m(points: NDArray[np.float32], rows: NDArray[np.int64], T_now: NDArray[np.float64],
                    T_ref: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """How far each point moved from the reference revision to now (exact per point), and whether its frame moved."""
    moved_frame = np.any(np.abs(T_now - T_ref) > DISPLAY_POSE_EPSILON, axis=(1, 2))
    p = points.astype(np.float64)
    # p_ref = T_ref T_now^-1 p, frame by frame (rows index the frames)
    delta = T_ref @ np.linalg.inv(T_now)
    p_ref = np.einsum("nij,nj->ni", delta[rows, :3, :3], p) + delta[rows, :3, 3]
    return np.linalg.norm(p_ref - p, axis=1), moved_frame[rows]


def colored_map(store: FrameStore, *, revision: int | None = None, color: str = "frame", voxel_size_m: float | None = None,
                reference_revision: int | None = None, max_points: int = 3_000_000, double_wall_points_budget: int | None = None,
                seed: int = 0, latest_state: bool = False) -> ColoredMap:
    """The map of ``revision`` (default head), one random real point per ``voxel_size_m`` voxel, coloured by:

    - ``frame``: the frame id of the point (time order; turbo colour map);
    - ``revision``: how far the point moved from ``reference_revision`` (default: the revision's parent)
      to ``revision``, per point and exactly (rotations move far points more); points of frames the
      correction did not move are grey. Revision 0 has no parent: give ``reference_revision``.
    - ``double-wall``: the separation of the flagged double-wall voxel (finest scale) the point lies in,
      from the same detector and configuration as ``driftmap diagnose``; every other point grey.
    - ``state``: not the map's points but the revision's volumetric layers (:func:`state_map`);
    - ``session``: the session of the point's frame, each session in its own colour (:data:`SESSION_PALETTE_RGB`,
      tab10; a store that no merge made is one session, one colour), listed in :attr:`ColoredMap.sessions`.
    ``latest_state`` (colour ``state``, a merged store): the latest-state layers (:func:`latest_state_of`).
    """
    color = _check_color(color)
    rev = _check_revision(store, revision)
    if color == "state" or latest_state:
        return state_map(store, rev, voxel_size_m=voxel_size_m, max_points=max_points, seed=seed,
                         layers=latest_state_of(store, rev, voxel_size_m, color) if latest_state else None)
    kind = store_sensor_kind(store)
    vs = DEFAULT_VOXEL_SIZE_M[kind] if voxel_size_m is None else float(voxel_size_m)
    if not vs > 0 or not math.isfinite(vs):
        raise ConfigError(f"--voxel-size-m must be positive, got {voxel_size_m}")
    if max_points < 1:
        raise ConfigError(f"max_points must be positive, got {max_points}")
    ref = None
    if color == "revision":
        ref = store.revisions[rev].parent_id if reference_revision is None else _check_revision(store, reference_revision, "--reference")
    points, frame_ids, n_map = _downsample(store, rev, vs, max_points, seed)
    extent = np.ptp(points, axis=0) if len(points) else np.zeros(3)
    if len(points) and vs > float(np.max(extent)):
        raise ConfigError(f"--voxel-size-m {vs:g} is larger than the map itself ({extent[0]:.1f} x {extent[1]:.1f} x "
                          f"{extent[2]:.1f} m): the picture would hold {len(points)} points; leave it out for the "
                          f"sensor's default ({DEFAULT_VOXEL_SIZE_M[kind]:g} m)")
    poses = store.poses(rev)
    rows = np.searchsorted(store.frame_ids, frame_ids)
    cmap = _palette(color)
    walls = None
    caveats: list[str] = []
    legend = None
    if color == "session":
        values, colors, legend = session_colours(store, frame_ids)
        value_range = (float(legend[0].session), float(legend[-1].session))
        label = "session"
    elif color == "frame":
        values = frame_ids.astype(np.float64)
        shown = store.members(rev)  # the revision's frames, not frames stored after it (trial 18 W6)
        value_range = (float(shown.min()), float(shown.max()))
        label = "frame id"
    elif color == "revision":
        label = f"displacement from revision {ref} (m)" if ref is not None else "displacement (m)"
        if ref is None:
            logger.warning("view: revision %d has no parent revision; nothing moved (every point grey)", rev)
            values = np.full(len(points), np.nan)
        else:
            disp, moved = _displacement_m(points, rows, poses, store.poses(ref))
            # a frame the reference does not place (appended or resumed since) has no displacement from it: grey,
            # outside the scale (trial 18 B3: 4 m against its unmerged pose)
            new = ~np.isin(store.frame_ids, store.members(ref))[rows]
            moved &= ~new
            values = np.where(moved, disp, np.nan)
            logger.info("view: %d of %d shown points moved from revision %d to %d (max %.4f m)%s", int(moved.sum()),
                        len(points), ref, rev, float(disp[moved].max(initial=0.0)),
                        f"; {int(new.sum())} are of frames revision {ref} does not place (grey)" if new.any() else "")
        finite = values[np.isfinite(values)]
        value_range = (0.0, max(float(np.percentile(finite, 99)), 1e-6) if finite.size else 1e-3)
    else:
        values, walls, caveats = double_wall_values(store, rev, points, double_wall_points_budget)
        label = "double-wall separation (m)"
        finite = values[np.isfinite(values)]
        value_range = (0.0, max(float(np.percentile(finite, 95)), 0.01) if finite.size else 0.05)
        logger.info("view: %d flagged double-wall voxels, %d of %d shown points on them", walls.voxels_flagged,
                    finite.size, len(points))
    if color != "session":
        colors = _apply_palette(values, value_range, cmap)
    return ColoredMap(rev, color, points, frame_ids, colors, values, label, value_range, cmap, n_map, vs, kind,
                      _up_axis(poses, kind), poses[:, :3, 3].copy(), ref, walls, sessions=legend,
                      double_wall_caveats=tuple(caveats))


def state_map(store: FrameStore, revision: int | None = None, *, voxel_size_m: float | None = None,
              max_points: int = 3_000_000, seed: int = 0, layers: VolumeLayers | None = None) -> ColoredMap:
    """The volumetric layers of ``revision`` (:meth:`VolumeLayers.from_store`, or ``layers`` made already; ``voxel_size_m``
    None: the sensor's default, 2 cm for a depth camera) as a :class:`ColoredMap`: the centre of every occupied voxel
    (a random ``max_points`` of them when there are more), coloured by its height along the up axis; the layers
    themselves, free and unknown space included, in :attr:`ColoredMap.layers`."""
    from driftmap.volume import OCCUPIED, VolumeConfig, VolumeLayers

    rev = _check_revision(store, revision)
    if voxel_size_m is not None and not (math.isfinite(voxel_size_m) and voxel_size_m > 0):
        raise ConfigError(f"--voxel-size-m must be positive, got {voxel_size_m}")
    if max_points < 1:
        raise ConfigError(f"max_points must be positive, got {max_points}")
    kind = store_sensor_kind(store)
    if layers is None:
        layers = VolumeLayers.from_store(store, rev, VolumeConfig(voxel_size_m=voxel_size_m))
    occupied = np.flatnonzero(layers.state_grid().ravel() == OCCUPIED)
    if len(occupied) == 0:
        raise StoreError(f"{store.path}: revision {rev} has no occupied voxel to show ({layers.grid.describe()})")
    n_occupied = len(occupied)
    if n_occupied > max_points:
        logger.info("view: %d occupied voxels; showing a random %d of them", n_occupied, max_points)
        occupied = np.sort(np.random.default_rng(seed).choice(occupied, max_points, replace=False))
    centres = layers.grid.centers_m(occupied)
    poses = store.poses(rev)[store.ledger.member_rows(rev)]
    up = _up_axis(poses, kind)
    heights = centres @ up
    lo, hi = (float(v) for v in np.percentile(heights, [1.0, 99.0]))
    value_range = (lo, hi if hi > lo else lo + layers.grid.voxel_size_m)
    cmap = _palette("state")
    first_frame = np.array([f.min() if len(f) else -1 for f in layers.observers(centres)], dtype=np.int64)
    logger.info("view: revision %d, %d occupied voxels of %g m (%s)", rev, n_occupied, layers.grid.voxel_size_m,
                layers.grid.describe())
    return ColoredMap(rev, "state", np.ascontiguousarray(centres, np.float32), first_frame,
                      _apply_palette(heights, value_range, cmap), heights, "height of occupied voxels (m)", value_range,
                      cmap, n_occupied, layers.grid.voxel_size_m, kind, up, poses[:, :3, 3].copy(), layers=layers)


def write_state_top_view(cmap: ColoredMap, out_dir: Path) -> TopViewFigure:
    """Free / occupied / unknown space of ``cmap.layers`` from above (:func:`~driftmap.diagnostics.figures.
    plot_state_top_view`, the height band around the sensors): ``states-top_rev<N>_state.png`` in ``out_dir``."""
    if cmap.layers is None:
        raise ConfigError("a top view of free / occupied / unknown space needs the volumetric layers (--color state)")
    layers = cmap.layers
    band = sensor_band_m(cmap.sensor_origins_world, cmap.up)
    return plot_state_top_view(out_dir / f"states-top_rev{cmap.revision}_{cmap.color}.png", layers.state_grid(),
                               layers.grid, band_m=band, up=cmap.up, sensor_origins_m=cmap.sensor_origins_world,
                               title=f"revision {cmap.revision}: free / occupied / unknown from above (heights "
                                     f"{band[0]:.2f} .. {band[1]:.2f} m, voxel {cmap.voxel_size_m:g} m)")


# ---------------------------------------------------------------------------------------------- cameras


def view_cameras(cmap: ColoredMap, *, width_px: int = 1024, height_px: int = 768,
                 top_view_clip_m: float | None | str = "auto") -> list[ViewCamera]:
    """Three views fitted to the map: ``top`` (straight down along the up axis, narrow field of view) and
    two oblique views (35 deg elevation, from opposite corners).

    ``top_view_clip_m``: the top view leaves out points higher than this above the mean sensor height
    (``auto``: 0.6 m for depth cameras, so ceilings do not hide the room; none for LiDAR).
    """
    if width_px < 16 or height_px < 16:
        raise ConfigError(f"image size must be at least 16x16 pixels, got {width_px}x{height_px}")
    up = cmap.up
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - up * (helper @ up)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    pts = cmap.points_world.astype(np.float64)
    if len(pts) > 200_000:
        pts = pts[np.random.default_rng(1).choice(len(pts), 200_000, replace=False)]
    clip = DEFAULT_TOP_VIEW_CLIP_M[cmap.sensor_kind] if top_view_clip_m == "auto" else top_view_clip_m
    clip_max = None if clip is None else float(np.mean(cmap.sensor_origins_world @ up)) + float(clip)
    top_pts = pts if clip_max is None else pts[pts @ up <= clip_max]
    if len(top_pts) < 10:
        top_pts, clip_max = pts, None
    lo, hi = np.percentile(top_pts, 0.5, axis=0), np.percentile(top_pts, 99.5, axis=0)
    center = (lo + hi) / 2
    top = fit_camera("top", look_along(-up, e2), top_pts, center, 30.0, width_px, height_px)
    if clip_max is not None:
        top = ViewCamera(top.name, top.K, top.T_cam_world, width_px, height_px, up.copy(), clip_max)
    cams = [top]
    center = (np.percentile(pts, 0.5, axis=0) + np.percentile(pts, 99.5, axis=0)) / 2
    elevation = math.radians(35.0)
    for name, azimuth_deg in (("oblique-a", 225.0), ("oblique-b", 45.0)):
        az = math.radians(azimuth_deg)
        toward_eye = math.cos(elevation) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(elevation) * up
        cams.append(fit_camera(name, look_along(-toward_eye, up), pts, center, 50.0, width_px, height_px))
    return cams


# ---------------------------------------------------------------------------------------------- open3d offscreen


def _open3d_worker(job_path: str) -> int:
    """Child-process entry: render the job's views with Open3D's OffscreenRenderer (exit code 0: all written)."""
    import open3d as o3d

    job = np.load(job_path)
    spec = json.loads(str(job["spec"]))
    points, colors = job["points"].astype(np.float64), job["colors"].astype(np.float64) / 255.0
    W, H = spec["width_px"], spec["height_px"]
    renderer = o3d.visualization.rendering.OffscreenRenderer(W, H)
    bg = np.asarray(spec["background"]) / 255.0  # Filament turns the background from sRGB to linear: pre-compensate
    renderer.scene.set_background(np.r_[np.where(bg <= 0.0031308, 12.92 * bg, 1.055 * bg ** (1 / 2.4) - 0.055), 1.0])
    renderer.scene.view.set_post_processing(False)  # exact colours: no tone mapping, no anti-aliasing blur
    material = o3d.visualization.rendering.MaterialRecord()
    material.shader = "defaultUnlit"
    material.point_size = float(spec["point_size_px"])
    for k, view in enumerate(spec["views"]):
        mask = job[f"mask{k}"]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[mask]))
        cloud.colors = o3d.utility.Vector3dVector(colors[mask])
        renderer.scene.clear_geometry()
        renderer.scene.add_geometry("map", cloud, material)
        renderer.setup_camera(np.asarray(view["K"]), np.asarray(view["T_cam_world"]), W, H)
        image = np.asarray(renderer.render_to_image())
        Image.fromarray(image[:, :, :3]).save(view["path"])
    return 0


def _render_open3d(cmap: ColoredMap, cameras: list[ViewCamera], paths: list[Path], point_size_px: int) -> str | None:
    """Render with Open3D in a child process; returns None on success, else why it failed."""
    try:
        import open3d  # noqa: F401
    except ImportError as exc:
        return f"open3d is not importable ({exc})"
    with tempfile.TemporaryDirectory(prefix="driftmap-view-") as tmp:
        job = Path(tmp) / "job.npz"
        spec = {"width_px": cameras[0].width_px, "height_px": cameras[0].height_px, "background": list(BACKGROUND_RGB),
                "point_size_px": point_size_px,
                "views": [{"K": c.K.tolist(), "T_cam_world": c.T_cam_world.tolist(), "path": str(p)} for c, p in zip(cameras, paths)]}
        np.savez(job, points=cmap.points_world, colors=cmap.colors, spec=json.dumps(spec),
                 **{f"mask{k}": c.visible(cmap.points_world) for k, c in enumerate(cameras)})
        code = "import sys; from driftmap.viewer import _open3d_worker; sys.exit(_open3d_worker(sys.argv[1]))"
        try:
            proc = subprocess.run([sys.executable, "-c", code, str(job)], capture_output=True, text=True, timeout=_OPEN3D_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            return f"Open3D offscreen rendering took more than {_OPEN3D_TIMEOUT_S:.0f} s"
    if proc.returncode != 0:
        tail = " | ".join(line for line in (proc.stderr or "").strip().splitlines()[-3:])
        return f"Open3D offscreen rendering failed (exit code {proc.returncode}: {tail or 'no message'})"
    for path in paths:
        if not path.exists():
            return f"Open3D offscreen rendering wrote no {path.name}"
        image = np.asarray(Image.open(path).convert("RGB"))
        drawn = np.any(np.abs(image.astype(np.int16) - np.array(BACKGROUND_RGB)) > 8, axis=2)
        if drawn.mean() < 1e-3:
            return f"Open3D offscreen rendering produced a blank {path.name} (broken EGL/Vulkan driver?)"
    return None


# ---------------------------------------------------------------------------------------------- outputs


def write_overview(path: Path, images: list[NDArray[np.uint8]], cameras: list[ViewCamera], cmap: ColoredMap,
                   title: str) -> Path:
    """The views side by side with the colour bar (matplotlib)."""
    n = len(images)
    aspect = cameras[0].height_px / cameras[0].width_px
    fig, axes = plt.subplots(1, n, figsize=(5.0 * n + 0.8, 5.0 * aspect + 0.6), squeeze=False, layout="constrained")
    for ax, image, cam in zip(axes[0], images, cameras):
        ax.imshow(image)
        ax.set_title(cam.name + ("" if cam.clip_max_m is None else " (ceiling cut)"), fontsize=9)
        ax.set_axis_off()
    if cmap.sessions is not None:  # a legend: one patch per session
        from matplotlib.patches import Patch

        handles = [Patch(color=np.asarray(s.rgb) / 255.0,
                         label=f"session {s.session}: {s.n_frames} frames" + ("" if s.source_store is None
                                                                               else f" ({Path(s.source_store).name})"))
                   for s in cmap.sessions]
        fig.legend(handles=handles, loc="outside right upper", fontsize=8,
                   title="one session (not a merged store)" if len(cmap.sessions) == 1 and cmap.sessions[0].source_store
                   is None else "session", title_fontsize=8)
    else:
        sm = plt.cm.ScalarMappable(norm=Normalize(*cmap.value_range), cmap=cmap.colormap)
        bar = fig.colorbar(sm, ax=list(axes[0]), shrink=0.9, fraction=0.02, pad=0.01)
        bar.set_label(cmap.value_label + ("" if cmap.color in ("frame", "state") else "; grey: none"), fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _show_window(cmap: ColoredMap, title: str, width_px: int, height_px: int) -> None:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cmap.points_world.astype(np.float64)))
    cloud.colors = o3d.utility.Vector3dVector(cmap.colors.astype(np.float64) / 255.0)
    if cmap.color == "state":  # occupied voxels as cubes (their centres lie on the voxel lattice)
        cloud = o3d.geometry.VoxelGrid.create_from_point_cloud(cloud, cmap.voxel_size_m)
    path = o3d.geometry.LineSet(o3d.utility.Vector3dVector(cmap.sensor_origins_world),
                                o3d.utility.Vector2iVector(np.c_[np.arange(len(cmap.sensor_origins_world) - 1),
                                                                 np.arange(1, len(cmap.sensor_origins_world))]))
    o3d.visualization.draw_geometries([cloud, path], window_name=title, width=width_px, height=height_px)


def _require_rerun():
    try:
        import rerun as rr
    except ImportError as exc:
        raise ConfigError("the rerun backend needs rerun-sdk: pip install 'driftmap[viewer]'") from exc
    return rr


def _log_rerun(cmap: ColoredMap, out_dir: Path | None, headless: bool, title: str) -> dict[str, Path]:
    rr = _require_rerun()
    files: dict[str, Path] = {}
    rr.init("driftmap", spawn=not headless)
    if headless:
        if out_dir is None:
            raise ConfigError("the rerun backend without a display writes a .rrd file: give an output folder")
        out_dir.mkdir(parents=True, exist_ok=True)
        files["rrd"] = out_dir / f"map_rev{cmap.revision}_{cmap.color}.rrd"
        rr.save(str(files["rrd"]))
    radius = 0.5 * cmap.voxel_size_m
    rr.log(f"map/revision_{cmap.revision}/{cmap.color}", rr.Points3D(cmap.points_world, colors=cmap.colors, radii=radius))
    rr.log(f"map/revision_{cmap.revision}/sensor_path", rr.LineStrips3D([cmap.sensor_origins_world]))
    if headless and hasattr(rr, "disconnect"):
        rr.disconnect()  # flushes and closes the .rrd file
    logger.info("view: logged %s to rerun", title)
    return files


# ---------------------------------------------------------------------------------------------- entry point


def _resolve_backend(backend: str, headless: bool | None, out_dir: Path | None, point_size_px: int) -> tuple[str, bool]:
    """The backend to use and whether to render headless, or a :class:`ConfigError` for what does not fit."""
    if backend not in BACKENDS:
        raise ConfigError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    problem = display_problem()
    if headless is None:
        headless = problem is not None
        if problem is not None and (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            logger.warning("no window: %s; rendering headless PNG views", problem)
    elif not headless and problem is not None:
        raise ConfigError(f"no display ({problem}): render headless PNG views instead (headless=True; CLI: --headless, or leave --no-headless out)")
    if backend == "auto":
        backend = "open3d" if headless else "window"
    if backend == "window" and headless:
        raise ConfigError("the window backend needs a display; use --backend open3d or software for PNG views")
    if backend in ("open3d", "software") and out_dir is None:
        raise ConfigError("headless rendering writes PNG files: give an output folder")
    if backend == "rerun":
        _require_rerun()
        if headless and out_dir is None:
            raise ConfigError("the rerun backend without a display writes a .rrd file: give an output folder")
    if point_size_px < 1:
        raise ConfigError(f"point size must be at least 1 pixel, got {point_size_px}")
    return backend, headless


def _state_outputs(cmap: ColoredMap, out_dir: Path | None) -> tuple[dict[str, Path], TopViewFigure | None, dict | None]:
    """Colour ``state``: the free / occupied / unknown top view (with an output folder) and the voxel counts."""
    if cmap.layers is None:
        return {}, None, None
    stats = cmap.layers.stats()
    counts = {"occupied": stats.occupied, "free": stats.free, "unknown": stats.unknown}
    if out_dir is None:
        return {}, None, counts
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    figure = write_state_top_view(cmap, Path(out_dir))
    return {"states-top": figure.path}, figure, counts


def view_store(store: FrameStore, *, revision: int | None = None, color: str = "frame", out_dir: Path | None = None,
               voxel_size_m: float | None = None, headless: bool | None = None, backend: str = "auto",
               reference_revision: int | None = None, width_px: int = 1024, height_px: int = 768, point_size_px: int = 2,
               top_view_clip_m: float | None | str = "auto", max_points: int = 3_000_000,
               double_wall_points_budget: int | None = None, latest_state: bool = False) -> ViewResult:
    """Show (window) or render (PNG views in ``out_dir``) the map of ``revision`` coloured by ``color``.

    ``headless=None`` detects it (no ``DISPLAY``/``WAYLAND_DISPLAY`` on Linux). ``voxel_size_m=None``: 2 cm
    for depth cameras, 20 cm for LiDAR (``state``: the volumetric layers' default). See the module docstring for
    the backends and :func:`colored_map` for the colour modes. PNG files: ``<view>_rev<N>_<color>.png`` per view and
    ``overview_rev<N>_<color>.png`` (colour ``session``: with a legend of the sessions' colours instead of a colour
    bar); colour ``state`` also ``states-top_rev<N>_state.png`` (free / occupied /
    unknown from above), with every backend when ``out_dir`` is given.
    """
    _check_color(color)
    _check_revision(store, revision)
    backend, headless = _resolve_backend(backend, headless, out_dir, point_size_px)
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    cmap = colored_map(store, revision=revision, color=color, voxel_size_m=voxel_size_m, reference_revision=reference_revision,
                       max_points=max_points, double_wall_points_budget=double_wall_points_budget,
                       latest_state=latest_state)
    seconds["colour"] = time.perf_counter() - t
    title = (f"{store.path.name}: revision {cmap.revision}, colour {color}"
             + (f" (from revision {cmap.reference_revision})" if cmap.reference_revision is not None else "")
             + f", {cmap.n_points:,} of {cmap.n_points_map:,} {'occupied voxels' if color == 'state' else 'points'}"
             + f" (voxel {cmap.voxel_size_m:g} m)")
    n_walls = cmap.double_walls.voxels_flagged if cmap.double_walls is not None else None
    state_files, state_figure, counts = _state_outputs(cmap, out_dir)
    common = dict(revision=cmap.revision, color=color, n_points_map=cmap.n_points_map, n_points_shown=cmap.n_points,
                  voxel_size_m=cmap.voxel_size_m, value_label=cmap.value_label, value_range=cmap.value_range,
                  reference_revision=cmap.reference_revision, n_double_wall_voxels=n_walls, colored=cmap,
                  volume_counts=counts, state_top_view=state_figure, sessions=cmap.sessions)
    if backend == "window":
        logger.info("view: backend window (Open3D), %d points", cmap.n_points)
        t = time.perf_counter()
        _show_window(cmap, title, width_px, height_px)
        seconds["window"] = time.perf_counter() - t
        return ViewResult(backend="window", files=state_files, cameras=[], seconds=seconds, **common)
    if backend == "rerun":
        files = {**_log_rerun(cmap, out_dir, headless, title), **state_files}
        logger.info("view: backend rerun, %d points", cmap.n_points)
        return ViewResult(backend="rerun", files=files, cameras=[], seconds=seconds, **common)
    assert out_dir is not None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cameras = view_cameras(cmap, width_px=width_px, height_px=height_px, top_view_clip_m=top_view_clip_m)
    paths = [out_dir / f"{cam.name}_rev{cmap.revision}_{color}.png" for cam in cameras]
    fallback = None
    used = backend
    t = time.perf_counter()
    if backend == "open3d":
        fallback = _render_open3d(cmap, cameras, paths, point_size_px)
        if fallback is not None:
            logger.warning("view: %s; using the software renderer", fallback)
            used = "software"
    if used == "software":
        for cam, path in zip(cameras, paths):
            Image.fromarray(render_software(cmap.points_world, cmap.colors, cam, point_size_px=point_size_px)).save(path)
    seconds["render"] = time.perf_counter() - t
    images = [np.asarray(Image.open(p).convert("RGB")) for p in paths]
    files = {cam.name: path for cam, path in zip(cameras, paths)}
    files["overview"] = write_overview(out_dir / f"overview_rev{cmap.revision}_{color}.png", images, cameras, cmap,
                                       f"{title}; {used} renderer")
    files.update(state_files)
    logger.info("view: backend %s wrote %d PNG views of %d points to %s", used, len(cameras), cmap.n_points, out_dir)
    return ViewResult(backend=used, files=files, cameras=cameras, fallback_reason=fallback, seconds=seconds, **common)
