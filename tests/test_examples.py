"""Every example in examples/ runs, so none of them can rot; the navigation example's volumetric layers and costmap
refresh are also checked in process.

Convention for examples (new ones are picked up by the glob below): ``python examples/NAME.py --out DIR
--frames N`` runs on a small frame budget, exits 0 only when its own checks pass, and writes
``DIR/result.json`` with ``"ok": true`` and the outcomes it checked.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from PIL import Image

from driftmap.datasets import embedded_dir
from driftmap.frame import PoseEstimate, PoseSource
from driftmap.geometry import make_transform
from driftmap.sources.synthetic import SyntheticLog
from driftmap.store.frame_store import FrameStore
from driftmap.volume import FREE, OCCUPIED, UNKNOWN, VolumeConfig, VolumeLayers

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((ROOT / "examples").glob("*.py"))
NAV = ROOT / "examples" / "nav_costmap.py"
FRAME_BUDGET = 24

RunExample = Callable[[Path], tuple[subprocess.CompletedProcess, Path]]


@pytest.fixture(scope="module")
def run_example(tmp_path_factory: pytest.TempPathFactory) -> RunExample:
    """Runs an example once per test module (in a fresh folder, with the venv's python) and caches it."""
    runs: dict[Path, tuple[subprocess.CompletedProcess, Path]] = {}

    def run(example: Path) -> tuple[subprocess.CompletedProcess, Path]:
        if example not in runs:
            out = tmp_path_factory.mktemp(example.stem)
            proc = subprocess.run([sys.executable, str(example), "--out", str(out), "--frames", str(FRAME_BUDGET)],
                                  cwd=out, capture_output=True, text=True, timeout=600)
            runs[example] = (proc, out)
        return runs[example]

    return run


def test_examples_are_discovered() -> None:
    assert NAV in EXAMPLES


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.stem)
def test_example_runs_and_passes_its_checks(example: Path, run_example: RunExample) -> None:
    proc, out = run_example(example)
    assert proc.returncode == 0, (f"{example.name} exited {proc.returncode}:\n"
                                  f"{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    result = json.loads((out / "result.json").read_text())
    assert result["ok"] is True


def test_nav_costmap_refreshes_only_changed_regions_and_equals_a_rebuild(run_example: RunExample) -> None:
    proc, out = run_example(NAV)
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads((out / "result.json").read_text())
    corrections = result["corrections"]
    assert result["frames"] == FRAME_BUDGET
    assert len(corrections) >= 2
    for c in corrections:
        assert c["layers_equal_to_rebuild"] is True, c
        assert c["costmap_equal_to_rebuild"] is True, c
        assert c["adds_equal_to_rebuild"] is True, c
        assert c["unknown_never_free"] is True, c
        assert c["layers_rebuilt_fallback"] is False, c
        assert 0 < c["cells_refreshed"] < c["cells_total"], c
        assert 0 < c["voxels_state_changed"] < c["voxels_total"], c
        # frames stored before the window were pinned: only the window's frames may move
        assert 0 < c["frames_moved"] <= c["window"][1] - c["window"][0] + 1, c
    assert all(c["frames_moved"] < c["frames_total"] for c in corrections[1:])
    assert sum(c["cells_cost_changed"] for c in corrections) > 0, "the corrections should change the costmap"
    assert result["layers_equal_to_rebuild"] is True and result["costmap_equal_to_rebuild"] is True
    assert result["unknown_never_free"] is True
    assert all(result["query_checks"].values()), result["query_checks"]
    assert proc.stdout.count("equals rebuild: yes") == len(corrections)
    cells = result["costmap_cells"]
    assert min(cells.values()) > 0 and sum(cells.values()) == result["cells_total"]  # free, costs, lethal, unknown
    # the costmap's states are those of the nav2 map export of the same layers (the room lies inside both grids)
    exported = result["exports"]["grid2d_cells"]
    assert exported["occupied"] == cells["lethal"]
    assert exported["free"] == cells["free"] + cells["cost"] + cells["inscribed"]
    assert Path(result["exports"]["grid2d_pgm"]).read_bytes().startswith(b"P5")
    assert Path(result["exports"]["octomap"]).stat().st_size > 0

    png = np.asarray(Image.open(result["png"]).convert("RGB"))
    assert png.shape[1] > 800 and png.std() > 10, "costmap.png should not be blank"
    colours = {tuple(c) for c in png.reshape(-1, 3)[:: 7].tolist()}
    assert len(colours) > 5, "free, costs, lethal and unknown cells should be distinguishable"

    # the queries it printed agree with layers rebuilt here from the store it left
    q = result["queries"]
    with FrameStore.open(result["store"]) as store:
        assert store.head == result["revisions"] == len(corrections) == q["revision"]
        layers = VolumeLayers.from_store(store, config=VolumeConfig(**result["volume_config"]))
    path = np.asarray(q["path_m"])
    seg = float(np.linalg.norm(path[1] - path[0]))
    n = q["path_samples"] - 1
    samples = np.array([path[0]] + [path[0] + (path[1] - path[0]) * (j / n) for j in range(1, n + 1)])
    states = layers.states(samples)
    assert {k: int(np.sum(states == v)) for k, v in (("free", FREE), ("occupied", OCCUPIED), ("unknown", UNKNOWN))} \
        == q["path_states"]
    first = np.flatnonzero(states != FREE)[0]
    assert q["path_first_not_free_m"] == pytest.approx(seg * first / n)
    robots = np.asarray(q["robot_points_m"])
    assert layers.clearance_m(robots).tolist() == q["clearance_m"]
    assert layers.clearance_m(robots, unknown_is="free").tolist() == q["clearance_unknown_free_m"]
    assert np.all(np.asarray(q["clearance_m"]) <= np.asarray(q["clearance_unknown_free_m"]))
    sphere = layers.sweep(path, radius_m=q["sweep_sphere"]["radius_m"])
    assert sphere.outcome == q["sweep_sphere"]["outcome"] == "contact"
    assert sphere.distance_m == q["sweep_sphere"]["distance_m"]
    assert sphere.frames.tolist() == q["sweep_sphere"]["frames"] == q["contact_observers"] != []
    assert layers.observers(sphere.voxel_center_m[None])[0].tolist() == q["contact_observers"]
    box = layers.sweep(path, box_m=q["sweep_box"]["box_m"])
    assert (box.outcome, box.distance_m) == (q["sweep_box"]["outcome"], q["sweep_box"]["distance_m"])


# ---------------------------------------------------------------------------------------------- in process


@pytest.fixture(scope="module")
def nav() -> ModuleType:
    spec = importlib.util.spec_from_file_location("nav_costmap_example", NAV)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file executes
    spec.loader.exec_module(module)
    return module


CONFIG = VolumeConfig(voxel_size_m=0.05)


@pytest.fixture(scope="module")
def frames() -> list:
    log = SyntheticLog(embedded_dir() / "synthetic-loop", pixel_stride=4)
    return [log.depth_frame(i) for i in range(0, 36, 3)]


@pytest.fixture(scope="module")
def moved_store(tmp_path_factory: pytest.TempPathFactory, frames: list) -> tuple[FrameStore, list[int]]:
    """A store of real frames at their poses (revision 0) and revision 1, in which the second half is moved by
    1.1 m and 29 degrees."""
    shift = make_transform(np.array([[np.cos(0.5), -np.sin(0.5), 0], [np.sin(0.5), np.cos(0.5), 0], [0, 0, 1]]),
                           (1.0, -0.5, 0.0))
    moved = [f.frame_id for f in frames[len(frames) // 2 :]]
    path = tmp_path_factory.mktemp("nav") / "store"
    with FrameStore.create(path) as store:
        for f in frames:
            store.append(f.with_pose(PoseEstimate(f.T_world_sensor, source=PoseSource.GROUND_TRUTH)))
        store.add_revision({f.frame_id: shift @ f.T_world_sensor if f.frame_id in moved else f.T_world_sensor
                            for f in frames}, source=PoseSource.GROUND_TRUTH, propagate=False)
    return FrameStore.open(path), moved


def test_costmap_refresh_after_apply_equals_rebuild(nav: ModuleType, moved_store: tuple) -> None:
    store, moved = moved_store
    spec = nav.CostmapSpec()
    layers = VolumeLayers.from_store(store, 0, CONFIG)
    costmap = nav.Costmap.rebuild(spec, layers)
    before = costmap.cost.copy()

    change = layers.apply(1, store)
    assert sorted(change.frame_ids.tolist()) == moved and not change.rebuilt
    stats, region = costmap.refresh(layers, change)
    rebuilt = VolumeLayers.from_store(store, 1, CONFIG)
    assert layers.equals(rebuilt)
    assert costmap.equals(nav.Costmap.rebuild(spec, rebuilt))
    assert 0 < stats.cells_refreshed < spec.n_cells
    assert np.count_nonzero(before != costmap.cost) > 0
    assert np.all(region[before != costmap.cost])  # every cell whose cost changed was in the refreshed region
    assert nav.unknown_never_free(layers, costmap)


def test_costmap_refresh_needs_the_boxes_before_the_move(nav: ModuleType, moved_store: tuple) -> None:
    """Refreshing only where the frames' rays are now leaves their old obstacles and free space behind: the check
    can fail."""
    store, _ = moved_store
    spec = nav.CostmapSpec()
    layers = VolumeLayers.from_store(store, 0, CONFIG)
    costmap = nav.Costmap.rebuild(spec, layers)
    change = layers.apply(1, store)
    after_only = dataclasses.replace(change, boxes_m=change.boxes_m[len(change.frame_ids):])  # the new boxes only
    costmap.refresh(layers, after_only)
    assert not costmap.equals(nav.Costmap.rebuild(spec, layers))


def test_new_frames_integrate_to_exactly_a_rebuild(nav: ModuleType, frames: list, tmp_path: Path) -> None:
    """The example's live loop: frames appended one by one and integrated into the layers give the layers built
    from scratch; each VolumeChange's flipped voxels lie in its boxes."""
    with FrameStore.create(tmp_path / "live") as store:
        store.append(frames[0].with_pose(PoseEstimate(frames[0].T_world_sensor, source=PoseSource.ODOMETRY)))
        layers = VolumeLayers.from_store(store, config=CONFIG)
        for f in frames[1:6]:
            store.append(f.with_pose(PoseEstimate(f.T_world_sensor, source=PoseSource.ODOMETRY)))
            change = nav.integrate_new_frames(layers, store)
            assert change.frame_ids.tolist() == [f.frame_id] and change.n_state_changed > 0
            (lo, hi), = change.boxes_m
            assert np.all((change.changed_centers_m >= lo - 0.05) & (change.changed_centers_m <= hi + 0.05))
        assert nav.integrate_new_frames(layers, store).frame_ids.size == 0  # nothing new
        assert layers.equals(VolumeLayers.from_store(store, config=CONFIG))
