"""The map viewer's headless path on the embedded synthetic log (odometry = revision 0 with its doubled loop
wall, ground truth = revision 1, a translation of three frames = revision 2): PNG views of the requested size,
colours that mean what they say (frame, per-point displacement, double-wall separation), the z-buffer, the
Open3D offscreen backend against the software one, the fallback, and typed errors."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree

from driftmap import viewer
from driftmap.demo import embedded_log_path
from driftmap.errors import ConfigError, DriftmapError, StoreError
from driftmap.map.view import MapView
from driftmap.pipeline.build import build
from driftmap.sources.synthetic import ROOM_MAX_M
from driftmap.store.frame_store import FrameStore
from driftmap.viewer import BACKGROUND_RGB, GREY_RGB, ViewCamera, colored_map, render_software, view_store

W, H = 320, 240
MOVED_FRAMES = (0, 3, 6)
SHIFT_M = np.array([0.05, 0.0, 0.0])
DW_BUDGET = 100_000  # double-wall samples (diagnose uses 600k; the flags on this log are the same kind)


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> FrameStore:
    log = embedded_log_path()
    path = tmp_path_factory.mktemp("viewer") / "store"
    build(log, path, poses_from_source=True, loop_closure=False, frames="0:60:3")  # odometry poses: revision 0
    with FrameStore.open(path, "a") as s:
        s.import_poses(log / "groundtruth.txt", format="tum", source="ground_truth")  # revision 1
        ids = [int(i) for i in s.frame_ids]
        moved = {}
        for fid in MOVED_FRAMES:
            T = s.poses(1)[ids.index(fid)].copy()
            T[:3, 3] += SHIFT_M
            moved[fid] = T
        s.add_revision(moved, source="external_file", propagate=False, note="three frames shifted")  # revision 2
    s = FrameStore.open(path)
    assert s.head == 2
    yield s
    s.close()


def load(path: Path) -> np.ndarray:
    image = Image.open(path)
    assert image.size == (W, H), f"{path.name}: {image.size}"
    return np.asarray(image.convert("RGB")).astype(np.int16)


def drawn(image: np.ndarray) -> np.ndarray:
    return np.any(np.abs(image - np.array(BACKGROUND_RGB)) > 6, axis=2)


def coloured(image: np.ndarray) -> np.ndarray:
    """Pixels that are neither background nor grey (r = g = b)."""
    return drawn(image) & (image.max(axis=2) - image.min(axis=2) > 12)


def pixel_colours(image: np.ndarray, camera: ViewCamera, points: np.ndarray) -> np.ndarray:
    uv, z = camera.project(points)
    ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H) & camera.visible(points)
    u, v = uv[ok, 0].astype(int), uv[ok, 1].astype(int)
    rgb = image[v, u]
    return rgb[drawn(image)[v, u]]


# ---------------------------------------------------------------------------------------------- colour modes


def test_frame_colouring_headless_views(store: FrameStore, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    result = view_store(store, revision=1, color="frame", out_dir=tmp_path, voxel_size_m=None, headless=None,
                        backend="software", width_px=W, height_px=H)
    assert result.backend == "software" and result.revision == 1 and result.voxel_size_m == 0.02
    assert set(result.files) == {"top", "oblique-a", "oblique-b", "overview"}
    cm = result.colored
    assert 0 < result.n_points_shown < result.n_points_map
    # one real point per 2 cm voxel: no two kept points share a voxel
    keys = np.floor(cm.points_world / 0.02).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    assert len(np.unique((keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2])) == len(keys)
    for cam in result.cameras:
        image = load(result.files[cam.name])
        assert drawn(image).mean() > 0.15, cam.name
        assert len(np.unique(image.reshape(-1, 3), axis=0)) > 500, cam.name
    assert Image.open(result.files["overview"]).size[0] > 2 * W
    # early frames and frames half a loop later project to pixels of their own colours
    top = load(result.files["top"])
    cam = result.cameras[0]
    early = cm.points_world[cm.frame_ids <= 6]
    later = cm.points_world[(cm.frame_ids >= 27) & (cm.frame_ids <= 33)]
    expected_early = cm.colors[cm.frame_ids <= 6].astype(float).mean(axis=0)
    expected_later = cm.colors[(cm.frame_ids >= 27) & (cm.frame_ids <= 33)].astype(float).mean(axis=0)
    got_early = np.median(pixel_colours(top, cam, early), axis=0)
    got_later = np.median(pixel_colours(top, cam, later), axis=0)
    assert np.linalg.norm(expected_early - expected_later) > 100  # turbo: blue vs green/yellow
    assert np.linalg.norm(got_early - expected_early) < 0.5 * np.linalg.norm(got_early - expected_later)
    assert np.linalg.norm(got_later - expected_later) < 0.5 * np.linalg.norm(got_later - expected_early)


def test_revision_colouring_is_the_exact_per_point_displacement(store: FrameStore) -> None:
    cm = colored_map(store, revision=1, color="revision")
    assert cm.reference_revision == 0
    # independent: the same point in the full maps of revision 0 and 1 (same order), moved by |p1 - p0|
    p0, p1 = MapView.from_store(store, 0).points_world, MapView.from_store(store, 1).points_world
    pick = np.random.default_rng(0).choice(cm.n_points, 2000, replace=False)
    dist, index = cKDTree(p1).query(cm.points_world[pick])
    assert np.all(dist == 0)
    expected = np.linalg.norm(p1[index].astype(np.float64) - p0[index], axis=1)
    # frames whose pose the correction kept (the odometry starts at the true pose) are grey, the rest coloured
    kept = store.frame_ids[np.all(store.poses(0) == store.poses(1), axis=(1, 2))]
    assert 0 < len(kept) < len(store.frame_ids) // 2
    grey = np.isin(cm.frame_ids[pick], kept)
    assert np.array_equal(np.isnan(cm.values[pick]), grey) and np.all(expected[grey] == 0)
    np.testing.assert_allclose(cm.values[pick][~grey], expected[~grey], atol=2e-6, rtol=0)
    assert cm.value_range[1] > 0.05  # the odometry drifted by decimetres


def test_revision_colouring_greys_frames_the_correction_left_alone(store: FrameStore, tmp_path: Path) -> None:
    result = view_store(store, revision=2, color="revision", out_dir=tmp_path, voxel_size_m=0.03, headless=True,
                        backend="software", width_px=W, height_px=H)
    cm = result.colored
    assert cm.reference_revision == 1 and result.reference_revision == 1
    moved = np.isin(cm.frame_ids, MOVED_FRAMES)
    assert moved.any() and (~moved).any()
    np.testing.assert_allclose(cm.values[moved], np.linalg.norm(SHIFT_M), atol=1e-6)  # a pure translation
    assert np.all(np.isnan(cm.values[~moved]))
    assert np.all(cm.colors[~moved] == GREY_RGB)
    images = [load(result.files[c.name]) for c in result.cameras]
    n_coloured = sum(int(coloured(i).sum()) for i in images)
    n_grey = sum(int((drawn(i) & ~coloured(i)).sum()) for i in images)
    assert n_coloured > 500 and n_grey > n_coloured  # three of twenty frames moved


def test_double_wall_colouring_marks_the_doubled_loop_wall_only_in_the_drifted_revision(store: FrameStore, tmp_path: Path) -> None:
    drifted = view_store(store, revision=0, color="double-wall", out_dir=tmp_path / "odometry", headless=True,
                         backend="software", width_px=W, height_px=H, double_wall_points_budget=DW_BUDGET)
    cm = drifted.colored
    assert drifted.n_double_wall_voxels and drifted.n_double_wall_voxels == cm.double_walls.voxels_flagged > 0
    on_wall = np.isfinite(cm.values)
    assert 100 < on_wall.sum() < 0.5 * cm.n_points
    # the odometry doubles the +y wall, seen at the start and at the end of the loop (docs/synthetic-log.md)
    assert np.median(cm.points_world[on_wall, 1]) > ROOM_MAX_M[1] - 0.6
    assert np.all(cm.values[on_wall] >= cm.double_walls.config.min_separation_m)
    assert sum(int(coloured(load(drifted.files[c.name])).sum()) for c in drifted.cameras) > 300
    truth = colored_map(store, revision=1, color="double-wall", double_wall_points_budget=DW_BUDGET)
    assert truth.double_walls.voxels_flagged == 0
    assert np.all(np.isnan(truth.values)) and np.all(truth.colors == GREY_RGB)


# ---------------------------------------------------------------------------------------------- renderers


def test_software_zbuffer_nearest_point_wins() -> None:
    grid = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 200), np.linspace(-0.5, 0.5, 200)), axis=-1).reshape(-1, 2)
    near = np.c_[grid * 0.5, np.full(len(grid), 2.0)]  # a small square in front ...
    far = np.c_[grid, np.full(len(grid), 3.0)]  # ... of a large one
    colours = np.r_[np.tile([[255, 0, 0]], (len(near), 1)), np.tile([[0, 0, 255]], (len(far), 1))].astype(np.uint8)
    cam = ViewCamera("test", np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]]), np.eye(4), W, H)
    for order in (slice(None), slice(None, None, -1)):  # drawing order must not matter
        image = render_software(np.r_[near, far][order], colours[order], cam, shading=False).astype(int)
        assert tuple(image[H // 2, W // 2]) == (255, 0, 0)
        assert tuple(image[H // 2, W // 2 + 45]) == (0, 0, 255)  # outside the near square (37.5 px), inside the far (50 px)
        assert tuple(image[5, 5]) == BACKGROUND_RGB


def test_auto_headless_backend_renders_and_agrees_with_the_software_renderer(store: FrameStore, tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """No display: ``auto`` tries Open3D's OffscreenRenderer (in a child process) and falls back to software.

    ``scripts/setup.sh`` installs what the OffscreenRenderer needs (EGL, Vulkan, Mesa's lavapipe), so here it
    must be Open3D that renders: a fallback would compare the software renderer with itself (the fallback has
    its own test below)."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    result = view_store(store, revision=1, color="frame", out_dir=tmp_path, voxel_size_m=0.04, width_px=W, height_px=H)
    assert result.backend == "open3d", f"fell back to software: {result.fallback_reason}"
    assert result.fallback_reason is None
    cm = result.colored
    for cam in result.cameras:
        image = load(result.files[cam.name])
        reference = render_software(cm.points_world, cm.colors, cam, shading=False).astype(np.int16)
        a, b = drawn(image), drawn(reference)
        assert a.mean() > 0.15
        assert (a == b).mean() > 0.95, cam.name  # the same camera model: the same pixels covered
        # the same colours where both drew (the winning point may differ, Open3D blends point edges); an
        # sRGB/linear mix-up or tone mapping would darken every colour by far more
        both = a & b
        x, y = image[both] - np.array(BACKGROUND_RGB), reference[both] - np.array(BACKGROUND_RGB)
        assert np.median(np.abs(x - y).sum(axis=1)) < 40, cam.name
        cosine = (x * y).sum(axis=1) / np.linalg.norm(x, axis=1) / np.linalg.norm(y, axis=1)
        assert np.median(cosine) > 0.99, cam.name


def test_a_crashing_open3d_renderer_falls_back_to_software(store: FrameStore, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    def crash(*args, **kwargs) -> subprocess.CompletedProcess:
        return subprocess.CompletedProcess(args, -6, "", "Failed to load vulkan library!\n")

    monkeypatch.setattr(viewer.subprocess, "run", crash)
    result = view_store(store, revision=1, color="frame", out_dir=tmp_path, voxel_size_m=0.05, headless=True,
                        backend="open3d", width_px=W, height_px=H)
    assert result.backend == "software" and "vulkan" in result.fallback_reason
    assert all(drawn(load(result.files[c.name])).mean() > 0.1 for c in result.cameras)


# ---------------------------------------------------------------------------------------------- errors


def test_bad_input_raises_typed_errors(store: FrameStore, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ConfigError, match="--color"):
        view_store(store, color="rainbow", out_dir=tmp_path, headless=True)
    with pytest.raises(StoreError, match="revision 7 does not exist"):
        view_store(store, revision=7, out_dir=tmp_path, headless=True)
    with pytest.raises(StoreError, match="--reference 9"):
        colored_map(store, revision=2, color="revision", reference_revision=9)
    with pytest.raises(ConfigError, match="voxel"):
        colored_map(store, voxel_size_m=0.0)
    with pytest.raises(ConfigError, match="output folder"):
        view_store(store, out_dir=None, headless=True, backend="software")
    with pytest.raises(ConfigError, match="--backend"):
        view_store(store, out_dir=tmp_path, headless=True, backend="vtk")
    with pytest.raises(ConfigError, match="display"):
        view_store(store, out_dir=tmp_path, headless=True, backend="window")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(viewer.sys, "platform", "linux")
    with pytest.raises(ConfigError, match="no display"):
        view_store(store, out_dir=tmp_path, headless=False)
    assert not list(tmp_path.iterdir())  # nothing written before the input was checked
    try:
        import rerun  # noqa: F401
    except ImportError:
        with pytest.raises(DriftmapError, match=r"driftmap\[viewer\]"):
            view_store(store, out_dir=tmp_path, headless=True, backend="rerun", voxel_size_m=0.1)
    else:
        result = view_store(store, out_dir=tmp_path, headless=True, backend="rerun", voxel_size_m=0.1)
        assert result.files["rrd"].stat().st_size > 0


def test_cli_view_headless_writes_png_views(tmp_path: Path) -> None:
    """`driftmap view` without a display renders PNG views and says which backend drew them."""
    import os
    import subprocess
    import sys

    from driftmap.demo import embedded_log_path
    from driftmap.pipeline.build import build

    store = tmp_path / "store"
    build(embedded_log_path(), store, poses_from_source=True, frames="0:12", loop_closure=False)
    env = {**os.environ, "COLUMNS": "200", "DISPLAY": "", "WAYLAND_DISPLAY": ""}
    out = subprocess.run([sys.executable, "-m", "driftmap.cli", "view", str(store), "--out", str(tmp_path / "v"),
                          "--backend", "software"], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    assert "backend software" in out.stdout
    pngs = sorted((tmp_path / "v").glob("*.png"))
    assert len(pngs) >= 3
    img = np.asarray(Image.open(pngs[0]).convert("RGB"))
    assert img.std() > 10 and len(np.unique(img.reshape(-1, 3), axis=0)) > 50
    bad = subprocess.run([sys.executable, "-m", "driftmap.cli", "view", str(store), "--color", "rainbow", "--out",
                          str(tmp_path / "v2")], capture_output=True, text=True, timeout=300, env=env)
    assert bad.returncode == 2 and "rainbow" in bad.stderr and "Traceback" not in bad.stderr  # a usage error


# ---------------------------------------------------------------------------------------------- volumetric layers


def test_cli_view_state_renders_the_volumetric_layers(store: FrameStore, tmp_path: Path) -> None:
    """`driftmap view STORE --color state --out DIR --headless`: the occupied voxels of the revision's volumetric
    layers as points coloured by height (the usual PNG views), and free / occupied / unknown from above in one more
    PNG, each state in its own colour and every cell where the layers put it."""
    import os
    import sys

    from driftmap.diagnostics.figures import STATE_TOP_VIEW_RGB, sensor_band_m
    from driftmap.volume import OCCUPIED
    from driftmap.volume.export import GRID_FREE, GRID_OCCUPIED, occupancy_grid2d

    env = {**os.environ, "COLUMNS": "200", "DISPLAY": "", "WAYLAND_DISPLAY": ""}
    out = subprocess.run([sys.executable, "-m", "driftmap.cli", "view", str(store.path), "--revision", "1", "--color",
                          "state", "--out", str(tmp_path / "cli"), "--headless"], capture_output=True, text=True,
                         timeout=600, env=env)
    assert out.returncode == 0, out.stderr
    assert "colour state" in out.stdout and "occupied voxels" in out.stdout
    views = ("top", "oblique-a", "oblique-b", "overview", "states-top")
    assert {p.name for p in (tmp_path / "cli").glob("*.png")} == {f"{v}_rev1_state.png" for v in views}
    # the same view through the library: what was drawn
    result = view_store(store, revision=1, color="state", out_dir=tmp_path / "lib", headless=True, backend="software",
                        width_px=W, height_px=H)
    cm, layers = result.colored, result.colored.layers
    assert result.voxel_size_m == layers.grid.voxel_size_m == 0.02  # the depth camera's default voxel
    # every occupied voxel, once, at its centre; nothing else
    assert np.all(layers.states(cm.points_world) == OCCUPIED)
    assert cm.n_points == result.n_points_map == result.volume_counts["occupied"] == layers.stats().occupied > 10_000
    assert sum(result.volume_counts.values()) == layers.grid.n_voxels
    # coloured by height along the up axis: the lowest and the highest tenth in far apart colours
    np.testing.assert_allclose(cm.values, cm.points_world.astype(np.float64) @ cm.up, atol=1e-5)
    low, high = cm.values <= np.percentile(cm.values, 10), cm.values >= np.percentile(cm.values, 90)
    assert np.linalg.norm(cm.colors[low].mean(axis=0) - cm.colors[high].mean(axis=0)) > 100
    assert all(drawn(load(result.files[c.name])).mean() > 0.1 for c in result.cameras)
    # free / occupied / unknown from above: the CLI drew the same picture
    top = np.asarray(Image.open(result.files["states-top"]).convert("RGB")).astype(int)
    cli_top = np.asarray(Image.open(tmp_path / "cli" / "states-top_rev1_state.png").convert("RGB")).astype(int)
    assert np.array_equal(top, cli_top)
    figure = result.state_top_view
    assert top.shape == (figure.layout.height_px, figure.layout.width_px, 3)
    colours = np.array(list(STATE_TOP_VIEW_RGB.values()))
    assert min(np.linalg.norm(a - b) for k, a in enumerate(colours) for b in colours[k + 1:]) > 80
    # its cells are the 2-D occupancy map of the same band (volume.export, z up), each drawn in its state's colour
    view = figure.view
    assert view.axes == (0, 1) and view.band_m == sensor_band_m(cm.sensor_origins_world, cm.up)
    grid2d = occupancy_grid2d(layers, view.band_m)
    expected = np.where(grid2d.cells == GRID_OCCUPIED, 1, np.where(grid2d.cells == GRID_FREE, 0, -1))
    assert np.array_equal(view.cells, expected)
    for state, rgb in STATE_TOP_VIEW_RGB.items():
        ij = np.argwhere(view.cells == state)
        assert len(ij) > 1000, state
        centres = np.asarray(view.min_m) + (ij + 0.5) * view.voxel_size_m
        px = figure.layout.pixels(centres).astype(int)
        assert np.mean(np.all(top[px[:, 1], px[:, 0]] == rgb, axis=1)) > 0.9, state  # the sensor path covers a few
