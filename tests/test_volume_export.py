"""Exports of the volumetric layers (issue 24), each read back with the consuming tool's own reader: the TSDF mesh
(PLY / OBJ / STL through Open3D), the OctoMap ``.bt`` (pyoctomap's ``readBinary``), the ``map_server`` YAML + PGM
(a YAML parser, a minimal P5 reader and map_server's trinary rule) and the Foxglove topics (``mcap`` + the protobuf
decoders); bad inputs raise typed errors and leave no file."""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import pyoctomap
import pytest
import yaml
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial import cKDTree

from driftmap.errors import ConfigError, EmptyExportError, OutputInsideStoreError
from driftmap.map.foxglove_export import TOPIC_GRID2D, TOPIC_MESH, export_foxglove_mcap
from driftmap.pipeline.build import build
from driftmap.store.frame_store import FrameStore
from driftmap.volume import VolumeConfig, VolumeLayers
from driftmap.volume.export import (
    FREE_THRESH,
    OCCUPIED_THRESH,
    _octomap_log_odds,
    occupancy_grid2d,
    write_grid2d,
    write_mesh,
    write_octomap,
)

LOG = Path(__file__).resolve().parents[1] / "datasets" / "synthetic-loop"
VOXEL_M = 0.05
BAND_M = (0.2, 1.2)
"""Above the synthetic room's floor, below its ceiling: walls and furniture occupied, the room's inside free."""


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> FrameStore:
    out = tmp_path_factory.mktemp("volx") / "store"
    build(LOG, out, poses_file=LOG / "groundtruth.txt", loop_closure=False)
    s = FrameStore.open(out)
    yield s
    s.close()


@pytest.fixture(scope="module")
def layers(store: FrameStore) -> VolumeLayers:
    return VolumeLayers.from_store(store, config=VolumeConfig(voxel_size_m=VOXEL_M))


def _leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if ".tmp" in p.name]


def triangle_corners(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T, 9) the corners of every triangle, rows sorted: the mesh independent of its vertex numbering (Open3D's
    marching cubes numbers the vertices in its hash map's order, which differs between two extractions)."""
    c = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)].reshape(len(triangles), 9)
    return c[np.lexsort(c.T[::-1])]


# ---------------------------------------------------------------------------------------------------- mesh
@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl"])
def test_mesh_file_holds_the_tsdf_mesh(layers: VolumeLayers, tmp_path: Path, suffix: str) -> None:
    mesh = layers.mesh()
    V, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert len(T) > 10_000
    path = tmp_path / f"mesh{suffix}"
    summary = write_mesh(layers, path)
    assert summary.n_triangles == len(T) and summary.n_vertices == len(V) and summary.bytes == path.stat().st_size
    back = o3d.io.read_triangle_mesh(str(path))
    BV, BT = np.asarray(back.vertices), np.asarray(back.triangles)
    assert len(BT) == len(T)
    # every triangle's corners as the file holds them (STL repeats the vertices of each triangle)
    corners, back = triangle_corners(V, T), triangle_corners(BV, BT)
    if suffix == ".ply":  # doubles: the same triangles exactly
        np.testing.assert_array_equal(back, corners)
    else:  # OBJ: 6 significant digits, STL: float32: every triangle of either has one of the other within rounding
        assert cKDTree(corners).query(back)[0].max() < 1e-5
        assert cKDTree(back).query(corners)[0].max() < 1e-5
    tol = 0.0 if suffix == ".ply" else 1e-5
    np.testing.assert_allclose(BV.min(axis=0), summary.bounds_min_m, atol=tol, rtol=0)
    np.testing.assert_allclose(BV.max(axis=0), summary.bounds_max_m, atol=tol, rtol=0)
    assert _leftovers(tmp_path) == [] and sorted(p.name for p in tmp_path.iterdir()) == [path.name]


def test_mesh_refuses_an_empty_mesh_a_wrong_suffix_and_a_store_path(layers: VolumeLayers, store: FrameStore,
                                                                     tmp_path: Path) -> None:
    with pytest.raises(EmptyExportError, match=r"--mesh .*empty.ply.*no surface"):
        write_mesh(layers, tmp_path / "empty.ply", weight_threshold=1e9)  # no sample is observed that often
    unseen = dataclasses.replace(layers.arrays, tsdf_count=np.zeros_like(layers.arrays.tsdf_count),
                                 tsdf_sum=np.zeros_like(layers.arrays.tsdf_sum))
    with pytest.raises(EmptyExportError, match=r"--mesh .*empty.stl.*no surface .*\(0 voxels with a TSDF sample"):
        write_mesh(dataclasses.replace(layers, arrays=unseen, cache={}), tmp_path / "empty.stl")
    # one sample, observed often enough, but no cube of eight: Open3D's marching cubes finds no triangle
    one = dataclasses.replace(unseen, tsdf_count=unseen.tsdf_count.copy())
    one.tsdf_count[layers.grid.n_voxels // 2] = 10
    with pytest.raises(EmptyExportError, match=r"--mesh .*empty.obj.*\(1 voxels with a TSDF sample, 1 of them"):
        write_mesh(dataclasses.replace(layers, arrays=one, cache={}), tmp_path / "empty.obj")
    with pytest.raises(ConfigError, match=r"--mesh .*\.ply, \.obj, \.stl"):
        write_mesh(layers, tmp_path / "mesh.off")
    with pytest.raises(OutputInsideStoreError, match="--mesh"):
        write_mesh(layers, Path(store.path) / "mesh.ply")
    assert list(tmp_path.iterdir()) == [] and not (Path(store.path) / "mesh.ply").exists()


# ------------------------------------------------------------------------------------------------- octomap
def _with_threshold(layers: VolumeLayers, occupancy_threshold: float, clamp_max: float) -> VolumeLayers:
    """The same evidence read with another sensor model (the counts are shared, nothing is re-integrated)."""
    cfg = layers.config.model_copy(update={"occupancy_threshold": occupancy_threshold, "clamp_max": clamp_max})
    return dataclasses.replace(layers, config=cfg, cache={})


@pytest.mark.parametrize("model", ["octomap-defaults", "threshold-0.6"])
def test_octomap_bt_reads_back_with_every_observed_voxel_in_its_state(layers: VolumeLayers, tmp_path: Path,
                                                                      model: str) -> None:
    if model == "threshold-0.6":
        # voxels with log-odds in [0, logit 0.6) are free here and occupied under OctoMap's default threshold: the
        # round trip only holds if the tree was given the layers' threshold
        between = layers.log_odds_flat(np.arange(layers.grid.n_voxels))
        seen = (layers.arrays.hits + layers.arrays.misses) > 0
        assert np.sum(seen & (between >= 0) & (between < np.log(0.6 / 0.4))) > 100
        layers = _with_threshold(layers, 0.6, 0.95)
    states = layers.state_grid().ravel()
    path = tmp_path / "map.bt"
    summary = write_octomap(layers, path)
    assert path.read_bytes().startswith(b"# Octomap OcTree binary file")

    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(path))
    assert tree.getResolution() == pytest.approx(VOXEL_M, abs=1e-12) == summary.resolution_m
    observed = np.flatnonzero(states >= 0)
    labels = tree.getLabels(layers.grid.centers_m(observed))
    np.testing.assert_array_equal(labels, states[observed])
    assert summary.n_occupied == int(np.sum(states == 1)) and summary.n_free == int(np.sum(states == 0))
    unknown = np.flatnonzero(states < 0)
    assert np.all(tree.getLabels(layers.grid.centers_m(unknown)) == -1)  # unknown stays absent
    # the tree's metric bounds are those of the observed voxels (their outer faces)
    lattice = layers.grid.unflat(observed) + np.asarray(layers.grid.origin_index)
    lo, hi = lattice.min(axis=0) * VOXEL_M, (lattice.max(axis=0) + 1) * VOXEL_M
    np.testing.assert_allclose(tree.getMetricMin(), lo, atol=1e-5)
    np.testing.assert_allclose(tree.getMetricMax(), hi, atol=1e-5)
    # pruned: fewer leaves than observed voxels (maximum likelihood makes whole free / occupied blocks equal)
    assert tree.getNumLeafNodes() == summary.n_leaf_nodes < len(observed)
    assert _leftovers(tmp_path) == []


def test_octomap_log_odds_keep_their_state_through_float32() -> None:
    """Log-odds within float32 rounding of the threshold land on the side driftmap's double comparison puts them."""
    thr = float(np.log(0.6 / 0.4))
    thr32 = np.float32(thr)
    eps = np.linspace(-1e-7, 1e-7, 41)
    values = thr + eps
    occupied = values >= thr
    raw = values.astype(np.float32)
    assert np.any((raw >= thr32) != occupied)  # without the nudge some would flip
    fixed = _octomap_log_odds(values, occupied, float(thr32))
    np.testing.assert_array_equal(fixed >= thr32, occupied)
    assert np.max(np.abs(fixed - raw)) <= np.spacing(thr32) * 2


def test_octomap_refuses_a_wrong_suffix_nothing_observed_and_a_store_path(layers: VolumeLayers, store: FrameStore,
                                                                          tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"--octomap .*'\.bt'"):
        write_octomap(layers, tmp_path / "map.ot")
    with pytest.raises(OutputInsideStoreError, match="--octomap"):
        write_octomap(layers, Path(store.path) / "map.bt")
    arrays = dataclasses.replace(layers.arrays, hits=np.zeros_like(layers.arrays.hits),
                                 misses=np.zeros_like(layers.arrays.misses))
    with pytest.raises(EmptyExportError, match="no voxel .* is observed"):
        write_octomap(dataclasses.replace(layers, arrays=arrays, cache={}), tmp_path / "map.bt")
    far = dataclasses.replace(layers.grid, origin_index=(40_000, 0, 0))  # the same voxels 2 km away: keys overflow
    with pytest.raises(ConfigError, match=r"--octomap .*beyond OctoMap's 16-bit keys"):
        write_octomap(dataclasses.replace(layers, grid=far, cache={}), tmp_path / "map.bt")
    assert list(tmp_path.iterdir()) == []


# -------------------------------------------------------------------------------------------------- 2-D map
def read_pgm(path: Path) -> np.ndarray:
    """A binary (P5) 8-bit PGM as (height, width) uint8; comments allowed in the header."""
    raw = path.read_bytes()
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while raw[pos:pos + 1].isspace():
            pos += 1
        if raw[pos:pos + 1] == b"#":
            pos = raw.index(b"\n", pos) + 1
            continue
        end = pos
        while not raw[end:end + 1].isspace():
            end += 1
        tokens.append(raw[pos:end])
        pos = end
    pos += 1  # the single whitespace after maxval
    magic, width, height, maxval = tokens[0], int(tokens[1]), int(tokens[2]), int(tokens[3])
    assert magic == b"P5" and maxval == 255
    data = np.frombuffer(raw[pos:], dtype=np.uint8)
    assert len(data) == width * height
    return data.reshape(height, width)


def map_server_states(image: np.ndarray, occupied_thresh: float, free_thresh: float) -> np.ndarray:
    """ROS map_server's trinary rule (negate 0): p = (255 - value) / 255; 100 if p > occupied_thresh, 0 if
    p < free_thresh, else -1; then its row flip (image row 0 = the map's last row). Returns cells[x, y]."""
    p = (255.0 - image.astype(np.float64)) / 255.0
    state = np.where(p > occupied_thresh, 100, np.where(p < free_thresh, 0, -1)).astype(np.int8)
    return state[::-1].T


def expected_columns(layers: VolumeLayers, band_m: tuple[float, float]) -> np.ndarray:
    """Per voxel column in the band, straight from the 3-D states: 100 / 0 / -1."""
    g = layers.grid
    zc = (g.origin_index[2] + np.arange(g.shape[2]) + 0.5) * g.voxel_size_m
    s = layers.state_grid()[:, :, (zc >= band_m[0]) & (zc <= band_m[1])]
    return np.where((s == 1).any(axis=2), 100, np.where((s == 0).any(axis=2), 0, -1)).astype(np.int8)


def test_grid2d_is_a_map_server_map_of_the_band(layers: VolumeLayers, tmp_path: Path) -> None:
    summary = write_grid2d(layers, tmp_path / "map.yaml", band_m=BAND_M)
    meta = yaml.safe_load((tmp_path / "map.yaml").read_text())
    assert meta["image"] == "map.pgm" and meta["mode"] == "trinary" and meta["negate"] == 0
    assert meta["resolution"] == VOXEL_M
    assert meta["occupied_thresh"] == OCCUPIED_THRESH and meta["free_thresh"] == FREE_THRESH
    g = layers.grid
    np.testing.assert_allclose(meta["origin"], [g.min_m[0], g.min_m[1], 0.0], atol=1e-12)
    image = read_pgm(tmp_path / meta["image"])
    assert image.shape == (g.shape[1], g.shape[0]) == (summary.height, summary.width)
    assert set(np.unique(image).tolist()) == {0, 205, 254}

    expected = expected_columns(layers, BAND_M)
    cells = map_server_states(image, meta["occupied_thresh"], meta["free_thresh"])
    np.testing.assert_array_equal(cells, expected)
    counts = {v: int(np.sum(expected == v)) for v in (100, 0, -1)}
    assert min(counts.values()) > 500  # walls, the room's inside and the outside all show
    assert (summary.n_occupied, summary.n_free, summary.n_unknown) == (counts[100], counts[0], counts[-1])
    np.testing.assert_array_equal(occupancy_grid2d(layers, BAND_M).cells, expected)

    # placement as map_server computes it: an occupied voxel in the band falls on an occupied pixel
    states = layers.state_grid().ravel()
    centres = g.centers_m(np.flatnonzero(states == 1))
    centres = centres[(centres[:, 2] >= BAND_M[0]) & (centres[:, 2] <= BAND_M[1])]
    col = np.floor((centres[:, 0] - meta["origin"][0]) / meta["resolution"]).astype(int)
    row = image.shape[0] - 1 - np.floor((centres[:, 1] - meta["origin"][1]) / meta["resolution"]).astype(int)
    assert len(centres) > 1000 and np.all(image[row, col] == 0)
    assert _leftovers(tmp_path) == []


def test_grid2d_band_errors_name_the_flag_and_write_nothing(layers: VolumeLayers, store: FrameStore,
                                                            tmp_path: Path) -> None:
    g = layers.grid
    top = float(g.max_m[2])
    with pytest.raises(ConfigError, match=r"--band-m: .*inverted"):
        write_grid2d(layers, tmp_path / "map.yaml", band_m=(1.2, 0.2))
    with pytest.raises(ConfigError, match=r"--band-m: .*holds no voxel centre"):
        write_grid2d(layers, tmp_path / "map.yaml", band_m=(top + 1.0, top + 2.0))
    with pytest.raises(ConfigError, match=r"--band-m: .*holds no voxel centre"):  # between two voxel centres
        write_grid2d(layers, tmp_path / "map.yaml", band_m=(1.0 * VOXEL_M + 0.01, 1.0 * VOXEL_M + 0.02))
    with pytest.raises(ConfigError, match=r"--band-m: no voxel in the band .* is observed"):
        write_grid2d(layers, tmp_path / "map.yaml", band_m=(top - VOXEL_M, top))  # the grid's padding above the room
    with pytest.raises(ConfigError, match=r"--band-m: .*finite"):
        write_grid2d(layers, tmp_path / "map.yaml", band_m=(0.0, float("nan")))
    with pytest.raises(ConfigError, match=r"--grid2d .*\.yaml or \.yml"):
        write_grid2d(layers, tmp_path / "map.pgm", band_m=BAND_M)
    with pytest.raises(OutputInsideStoreError, match="--grid2d"):
        write_grid2d(layers, Path(store.path) / "map.yaml", band_m=BAND_M)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------- Foxglove
def _read_mcap(path: Path) -> tuple[dict[str, list[Any]], dict[str, str], set[str]]:
    by_topic: dict[str, list[Any]] = defaultdict(list)
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        schemas = {s.name for s in reader.get_summary().schemas.values()}
        for _, channel, _, decoded in reader.iter_decoded_messages(log_time_order=False):
            by_topic[channel.topic].append(decoded)
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return by_topic, meta["driftmap.foxglove_export"], schemas


def test_foxglove_export_adds_the_mesh_and_the_grid(store: FrameStore, layers: VolumeLayers, tmp_path: Path) -> None:
    path = tmp_path / "volume.mcap"
    summary = export_foxglove_mcap(store, path, volume=layers, grid2d_band_m=BAND_M, include_frames=False,
                                   map_voxel_size_m=VOXEL_M)
    by_topic, meta, schemas = _read_mcap(path)
    assert {"foxglove.SceneUpdate", "foxglove.Grid", "foxglove.PointCloud"} <= schemas
    assert {t: len(m) for t, m in by_topic.items()} == summary.message_counts == {
        "/map": 1, "/trajectory": 1, "/tf": len(store), TOPIC_MESH: 1, TOPIC_GRID2D: 1}
    assert meta["topics"].split(",")[-2:] == [TOPIC_MESH, TOPIC_GRID2D]
    assert float(meta["volume_voxel_size_m"]) == VOXEL_M and meta["grid2d_band_m"] == "0.2,1.2"

    # the mesh: one entity, one triangle list, the layers' mesh vertex for vertex
    mesh = layers.mesh()
    V, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    (scene,) = by_topic[TOPIC_MESH]
    (entity,) = scene.entities
    assert entity.frame_id == "world" and entity.id == "tsdf_mesh"
    (tri,) = entity.triangles
    points = np.array([[p.x, p.y, p.z] for p in tri.points])
    indices = np.asarray(tri.indices, dtype=np.int64)
    assert len(indices) == 3 * len(T) == 3 * summary.n_mesh_triangles and len(points) == len(V)
    np.testing.assert_array_equal(triangle_corners(points, indices.reshape(-1, 3)), triangle_corners(V, T))
    np.testing.assert_array_equal(points.min(axis=0), mesh.get_min_bound())
    np.testing.assert_array_equal(points.max(axis=0), mesh.get_max_bound())
    assert tri.pose.orientation.w == 1.0 and tri.color.a == 1.0
    assert {kv.key: kv.value for kv in entity.metadata}["n_triangles"] == str(len(T))

    # the grid: the cells write_grid2d puts in the PGM, with Foxglove's layout (rows along +y from the corner)
    (grid,) = by_topic[TOPIC_GRID2D]
    assert grid.frame_id == "world" and grid.cell_size.x == grid.cell_size.y == VOXEL_M
    fields = {f.name: (f.offset, f.type) for f in grid.fields}
    assert fields["occupancy"] == (0, 2)  # INT8
    assert {fields[c][1] for c in ("red", "green", "blue", "alpha")} == {1}  # UINT8
    raw = np.frombuffer(grid.data, dtype=np.uint8).reshape(-1, grid.row_stride)
    occupancy = raw[:, fields["occupancy"][0]::grid.cell_stride][:, :grid.column_count].view(np.int8)
    write_grid2d(layers, tmp_path / "map.yaml", band_m=BAND_M)
    meta_yaml = yaml.safe_load((tmp_path / "map.yaml").read_text())
    pgm_cells = map_server_states(read_pgm(tmp_path / "map.pgm"), meta_yaml["occupied_thresh"],
                                  meta_yaml["free_thresh"])
    np.testing.assert_array_equal(occupancy.T, pgm_cells)
    assert summary.grid2d_shape == pgm_cells.shape
    assert (grid.pose.position.x, grid.pose.position.y) == tuple(meta_yaml["origin"][:2])
    assert grid.pose.position.z == BAND_M[0]


def test_foxglove_volume_inputs_are_checked_before_writing(store: FrameStore, layers: VolumeLayers,
                                                           tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    with pytest.raises(ConfigError, match="revision 3"):
        export_foxglove_mcap(store, path, volume=dataclasses.replace(layers, revision=3), include_frames=False)
    with pytest.raises(ConfigError, match="needs the volume layers"):
        export_foxglove_mcap(store, path, grid2d_band_m=BAND_M, include_frames=False)
    with pytest.raises(ConfigError, match="--band-m"):
        export_foxglove_mcap(store, path, volume=layers, grid2d_band_m=(2.0, 1.0), include_frames=False)
    assert list(tmp_path.iterdir()) == []


def test_cli_export_writes_the_volumetric_layers_and_checks_its_flags(store: FrameStore, tmp_path: Path) -> None:
    """`driftmap export --mesh / --octomap / --grid2d --band-m / --mcap` through the command line, with the
    [volume] table of --config: the files hold the layers of the store's revision; a bad band, an output inside the
    store and an existing file without --overwrite are refused before anything is written."""
    from typer.testing import CliRunner

    from driftmap.cli import app

    cfg = tmp_path / "c.toml"
    cfg.write_text("[volume]\nvoxel_size_m = 0.05\n")
    out = {k: tmp_path / n for k, n in (("mesh", "m.ply"), ("bt", "o.bt"), ("grid", "g.yaml"), ("mcap", "f.mcap"))}
    run = CliRunner().invoke(app, ["export", str(store.path), "--config", str(cfg), "--mesh", str(out["mesh"]),
                                   "--octomap", str(out["bt"]), "--grid2d", str(out["grid"]), "--band-m", "0.1,1.5",
                                   "--mcap", str(out["mcap"])])
    assert run.exit_code == 0, (run.output, run.exception)
    layers = VolumeLayers.from_store(store, config=VolumeConfig(voxel_size_m=0.05))
    mesh = o3d.io.read_triangle_mesh(str(out["mesh"]))
    assert len(mesh.triangles) == len(layers.mesh().triangles) > 0
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(out["bt"])) and tree.getResolution() == pytest.approx(0.05)
    meta = yaml.safe_load(out["grid"].read_text())
    assert meta["resolution"] == pytest.approx(0.05) and (tmp_path / "g.pgm").exists()
    with out["mcap"].open("rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert {TOPIC_MESH, TOPIC_GRID2D} <= topics
    before = {p: p.stat().st_mtime_ns for p in out.values()}
    for args, flag in ((["--grid2d", str(tmp_path / "x.yaml"), "--band-m", "1.5,0.1"], "--band-m"),
                       (["--mesh", str(store.path / "m.ply")], "--mesh"),
                       (["--mesh", str(out["mesh"])], "--mesh")):
        bad = CliRunner().invoke(app, ["export", str(store.path), *args])
        assert bad.exit_code != 0 and flag in (bad.output + str(bad.exception)), (bad.output, bad.exception)
    assert {p: p.stat().st_mtime_ns for p in out.values()} == before and not (tmp_path / "x.yaml").exists()
