"""Every example in examples/ runs, so none of them can rot; the navigation example's costmap refresh is
also checked in process.

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
from driftmap.geometry import make_transform
from driftmap.map.view import MapView
from driftmap.sources.synthetic import SyntheticLog
from driftmap.store.frame_store import FrameStore

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
        assert c["costmap_equal_to_rebuild"] is True, c
        assert c["adds_equal_to_rebuild"] is True, c
        assert 0 < c["cells_refreshed"] < c["cells_total"], c
        # frames stored before the window were pinned: only the window's frames may move
        assert 0 < c["frames_moved"] <= c["window"][1] - c["window"][0] + 1, c
    assert all(c["frames_moved"] < c["frames_total"] for c in corrections[1:])
    assert sum(c["cells_cost_changed"] for c in corrections) > 0, "the corrections should change the costmap"
    assert result["costmap_equal_to_rebuild"] is True
    assert proc.stdout.count("equals rebuild: yes") == len(corrections)

    png = np.asarray(Image.open(result["png"]).convert("L"))
    assert png.shape[1] > 800 and png.std() > 10, "costmap.png should not be blank"

    # the queries it printed agree with brute force over the map it left in the store
    with FrameStore.open(result["store"]) as store:
        assert store.head == result["revisions"] == len(corrections)
        points = store.map().points_world.astype(np.float64)
    q = result["queries"]
    d2 = np.sum((points - np.asarray(q["position_m"])) ** 2, axis=1)
    band = (points[:, 2] >= 0.10) & (points[:, 2] <= 1.80)  # the example's obstacle band
    assert q["clearance_m"] == pytest.approx(float(np.sqrt(d2[band].min())), abs=1e-9)
    assert q["radius_points"] == np.count_nonzero(d2 <= q["radius_m"] ** 2)
    assert q["radius_obstacle_points"] == np.count_nonzero((d2 <= q["radius_m"] ** 2) & band)
    inside = np.all((points >= q["box_ahead_min_m"]) & (points <= q["box_ahead_max_m"]), axis=1)
    assert q["box_ahead_points"] == np.count_nonzero(inside)


# ---------------------------------------------------------------------------------------------- in process


@pytest.fixture(scope="module")
def nav() -> ModuleType:
    spec = importlib.util.spec_from_file_location("nav_costmap_example", NAV)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file executes
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def frames() -> list:
    log = SyntheticLog(embedded_dir() / "synthetic-loop", pixel_stride=4)
    return [log.depth_frame(i) for i in range(0, 36, 3)]


def _moved_view(frames: list) -> tuple[MapView, np.ndarray, list[int]]:
    """A map of real frames in which the second half is moved by 40 cm and 10 degrees."""
    view = MapView.from_frames(frames)
    shift = make_transform(np.array([[np.cos(0.17), -np.sin(0.17), 0], [np.sin(0.17), np.cos(0.17), 0], [0, 0, 1]]),
                           (0.4, -0.2, 0.0))
    moved = [f.frame_id for f in frames[len(frames) // 2 :]]
    poses = np.array([shift @ f.T_world_sensor if f.frame_id in moved else f.T_world_sensor for f in frames])
    return view, poses, moved


def test_costmap_refresh_after_apply_equals_rebuild(nav: ModuleType, frames: list) -> None:
    spec = nav.CostmapSpec()
    view, poses, moved = _moved_view(frames)
    costmap = nav.Costmap(spec)
    for frame_id in view.frame_ids:  # incremental adds, frame by frame
        costmap.add_points(view.frame_points_world(int(frame_id)))
    assert costmap.equals(nav.Costmap.rebuild(spec, view.points_world))
    before = costmap.cost.copy()

    changes = view.apply(1, poses=poses)
    assert sorted(changes.frame_ids.tolist()) == moved
    stats = costmap.refresh(view, changes)
    assert costmap.equals(nav.Costmap.rebuild(spec, view.points_world))
    assert 0 < stats.cells_refreshed < spec.n_cells
    assert np.count_nonzero(before != costmap.cost) > 0
    # every cell whose cost changed lies within the inflation reach of the refreshed region
    region = costmap.cells_of_boxes(changes.boxes_m())
    assert np.all(costmap.inflation_reach(region)[before != costmap.cost])


def test_costmap_refresh_needs_the_boxes_before_the_move(nav: ModuleType, frames: list) -> None:
    """Refreshing only where the frames are now leaves their old obstacles behind: the check can fail."""
    spec = nav.CostmapSpec()
    view, poses, _ = _moved_view(frames)
    costmap = nav.Costmap.rebuild(spec, view.points_world)
    changes = view.apply(1, poses=poses)
    after_only = dataclasses.replace(
        changes, changes=[dataclasses.replace(c, box_before_m=c.box_after_m) for c in changes.changes])
    costmap.refresh(view, after_only)
    assert not costmap.equals(nav.Costmap.rebuild(spec, view.points_world))
