"""What the decisions reuse across queries (issue 25, speed) must not change a record: answered together, with the
map's voxel normals shared (``decisions.voxel_normals``), the frame spreads of shared evidence points remembered,
the collision candidates pruned by their bounds and the unknown voxels of a clearance's balls counted in one lookup,
every query gets the record it gets answered alone on the reference path (every normal fitted on its region, every
ball candidate evaluated, one lookup per point) -- the same decision, margin, failure label, uncertainty, frames,
evidence and details, compared exactly (latency aside). On a real store: 7-Scenes frames with the data set's poses."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest

from driftmap.decisions import decide, parse_queries
from driftmap.decisions import space, surface
from driftmap.decisions.query_file import QuerySet
from driftmap.decisions.point_index import PointIndex
from driftmap.pipeline.build import build
from driftmap.store.frame_store import FrameStore
from driftmap.volume import VolumeLayers

decide_module = importlib.import_module("driftmap.decisions.decide")  # the module (``decide`` is its function)

FRAMES = "0:1000:100"


@pytest.fixture(scope="module")
def kitchen(sevenscenes_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[FrameStore, VolumeLayers]:
    out = tmp_path_factory.mktemp("batch") / "kitchen"
    build(sevenscenes_dir, out, poses_from_source=True, loop_closure=False, frames=FRAMES)
    store = FrameStore.open(out)
    return store, VolumeLayers.from_store(store, store.head)


def _queries(layers: VolumeLayers, seed: int = 0) -> QuerySet:
    """Queries of every kind at map points (as the benchmark's, fewer): clearance and collision near the surface,
    grasp ROIs and foothold patches on it, explore boxes around it."""
    view = layers.view
    pts = np.asarray(view.points_world, dtype=np.float64)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    rng = np.random.default_rng(seed)

    def point() -> np.ndarray:
        return pts[rng.integers(len(pts))]

    def unit() -> np.ndarray:
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    out = []
    for k in range(12):
        a = point() + unit() * rng.uniform(0.02, 0.3)
        out.append({"id": f"clearance-{k}", "kind": "clearance", "radius_m": float(rng.uniform(0.05, 0.3)),
                    "points_m": (a + np.arange(int(rng.integers(1, 4)))[:, None] * unit() * 0.1).tolist()})
    for k in range(10):
        a = point() + unit() * rng.uniform(0.1, 0.5)
        fp = ({"box_m": rng.uniform(0.08, 0.35, 3).tolist()} if k % 2 else
              {"cylinder_m": [float(rng.uniform(0.05, 0.2)), float(rng.uniform(0.1, 0.5))]})
        out.append({"id": f"collision-{k}", "kind": "collision", "footprint": fp,
                    "path_m": [a.tolist(), (a + unit() * rng.uniform(0.2, 0.6)).tolist()]})
    for k in range(10):
        p, h = point(), rng.uniform(0.02, 0.06, 3)
        out.append({"id": f"grasp-{k}", "kind": "grasp", "roi_min_m": (p - h).tolist(), "roi_max_m": (p + h).tolist()})
    for k in range(10):
        out.append({"id": f"foothold-{k}", "kind": "foothold", "center_m": point().tolist(),
                    "radius_m": float(rng.uniform(0.05, 0.15)), "max_slope_deg": float(rng.uniform(10, 30))})
    for k in range(6):
        c, h = point(), rng.uniform(0.1, 0.5, 3)
        out.append({"id": f"explore-{k}", "kind": "explore", "min_m": (c - h).tolist(), "max_m": (c + h).tolist(),
                    "max_unknown_fraction": 0.3})
    return parse_queries({"queries": out})


def _record(d) -> dict:
    j = d.to_json()
    j.pop("latency_s")
    return j


def test_answered_together_as_each_alone_on_the_reference_path(kitchen, monkeypatch: pytest.MonkeyPatch) -> None:
    store, layers = kitchen
    qs = _queries(layers)
    shared_rows = []
    box_with_voxels = PointIndex.box_with_voxels

    def counting(self: PointIndex, lo: np.ndarray, hi: np.ndarray, voxel_rows: np.ndarray) -> tuple:
        out = box_with_voxels(self, lo, hi, voxel_rows)
        shared_rows.append(len(out[2]))
        return out

    with monkeypatch.context() as m:
        m.setattr(decide_module, "SHARED_NORMALS_MIN_QUERIES", 1)  # 48 queries: share the map's normals all the same
        m.setattr(PointIndex, "box_with_voxels", counting)
        together = decide(store, qs, layers=layers)
    assert sum(shared_rows) > 0, "no normal was taken from the map's voxel normals: the test checks nothing"
    assert {d.kind for d in together.decisions} == {"clearance", "collision", "grasp", "foothold", "explore"}

    with monkeypatch.context() as m:  # the reference: nothing shared, one ball at a time
        m.setattr(surface, "voxel_normals", lambda layers, config, **kw: None)
        m.setattr(space, "unknown_in_balls",
                  lambda layers, points, r: sum(space.unknown_in_ball(layers, p, r) for p in points))
        alone = [decide(store, QuerySet([q]), layers=layers).decisions[0] for q in qs]
    for a, b in zip(together.decisions, alone):
        assert _record(a) == _record(b), a.id
