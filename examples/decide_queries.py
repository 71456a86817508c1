#!/usr/bin/env python3
"""Action decisions from a navigation stack, with driftmap's library API only (no CLI, no ROS).

1. The embedded synthetic log's first ``--frames`` frames (at least 20) are stored with the log's drifting odometry
   (revision 0); its ground truth stands in for a localiser's correction (revision 1).
2. The stack asks its questions in code -- the clearance of robot positions, a box and a cylinder swept along a
   path past the table and into its top, a grasp on the table top, a foothold on the floor, whether the space under
   the table and a corner the robot has not faced yet need a look -- and :func:`driftmap.decisions.decide_revisions` answers them on both revisions (the volumetric layers
   are built once and updated to the correction, not rebuilt).
3. :func:`driftmap.decisions.compare` lists the decisions the correction flipped, how far each margin moved and
   which frames moved the evidence.

Run it (10-30 s on a 2-core machine)::

    .venv/bin/python examples/decide_queries.py --out /tmp/decide

It prints every decision and the flips, writes ``decisions.json`` (what ``driftmap decide --compare 0,1`` writes),
``decisions.png`` (the top view) and ``result.json`` (the checks), and exits 0 only when every check holds.
See docs/decisions.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from driftmap.datasets import embedded_dir
from driftmap.decisions import compare, decide_revisions, parse_queries
from driftmap.decisions.compare import output_json
from driftmap.decisions.figure import write_figure
from driftmap.pipeline.build import build
from driftmap.store.frame_store import FrameStore

CONTRACT_KEYS = {"id", "kind", "decision", "margin", "uncertainty", "failure_label", "frames", "stamp_ns_newest",
                 "latency_s"}

QUERIES = {"queries": [
    {"id": "robot-in-the-open", "kind": "clearance", "points_m": [[-1.5, 0.0, 0.5], [-1.5, -0.5, 0.5]], "radius_m": 0.2},
    {"id": "robot-by-the-table", "kind": "clearance", "points_m": [[0.0, 1.2, 0.4]], "radius_m": 0.15},
    {"id": "box-past-the-table", "kind": "collision", "path_m": [[-0.9, 1.15, 0.35], [0.9, 1.15, 0.35]],
     "footprint": {"box_m": [0.3, 0.3, 0.5]}},
    {"id": "cylinder-into-the-table", "kind": "collision", "path_m": [[0.0, 1.15, 0.8], [0.0, 1.8, 0.8]],
     "footprint": {"cylinder_m": [0.1, 0.12]}},
    {"id": "grasp-the-table-top", "kind": "grasp", "roi_min_m": [-0.05, 1.65, 0.72], "roi_max_m": [0.05, 1.75, 0.8]},
    {"id": "step-on-the-floor", "kind": "foothold", "center_m": [-1.5, -0.3, 0.0], "radius_m": 0.15, "max_slope_deg": 15},
    {"id": "under-the-table", "kind": "explore", "min_m": [-0.5, 1.5, 0.05], "max_m": [0.5, 2.1, 0.65],
     "max_unknown_fraction": 0.3},
    {"id": "the-unseen-corner", "kind": "explore", "min_m": [0.0, -2.2, 0.1], "max_m": [1.0, -1.5, 1.0],
     "max_unknown_fraction": 0.3},
]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("decide-example"))
    ap.add_argument("--frames", type=int, default=30, help="how many frames of the embedded log to store")
    args = ap.parse_args(argv)
    log = embedded_dir() / "synthetic-loop"
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    store_path = args.out / "store"
    if not (store_path / "store.json").exists():
        build(log, store_path, poses_file=log / "odometry.txt", loop_closure=False, frames=f"0:{args.frames}")
    with FrameStore.open(store_path, "a") as store:
        if store.head == 0:  # the localiser's correction: the log's ground truth
            store.import_poses(log / "groundtruth.txt", source="ground_truth")
    store = FrameStore.open(store_path)

    queries = parse_queries(QUERIES)
    (before, after), layers = decide_revisions(store, queries, [0, store.head])
    comparison = compare(before, after)

    for d in after.decisions:
        margin = "-" if d.margin is None else f"{d.margin:+.3f}"
        print(f"{d.id:24s} {d.kind:9s} {d.decision:15s} margin {margin:>8s}  frames {len(d.frames):2d}  "
              f"{1000 * d.latency_s:6.1f} ms  {d.failure_label or ''}")
    for f in comparison.flipped:
        print(f"flipped by the correction: {f.id}: {f.before} -> {f.after} (evidence moved "
              f"{100 * f.why['max_evidence_shift_m']:.1f} cm)")

    data = output_json(after, comparison)
    (args.out / "decisions.json").write_text(json.dumps(data, indent=1) + "\n")
    write_figure(args.out / "decisions.png", after, layers, comparison)

    checks = {
        "every_query_answered": len(after.decisions) == len(QUERIES["queries"]),
        "contract_keys": all(CONTRACT_KEYS <= set(d) for d in data["decisions"]),
        "space_decisions_in_contract": all(d["decision"] in ("free", "blocked", "unknown") for d in data["decisions"]
                                           if d["kind"] in ("clearance", "collision")),
        "representation_recorded": data["representation"]["revision"] == store.head
                                   and len(data["representation"]["settings_hash"]) == 16,
        "comparison_listed": "flipped" in data and set(data["compared"]) == {"a", "b"},
        "table_top_blocks_the_cylinder": after.by_id()["cylinder-into-the-table"].decision == "blocked",
        "unseen_corner_needs_a_look": after.by_id()["the-unseen-corner"].decision == "go_look",
    }
    ok = all(checks.values())
    result = {"ok": ok, "checks": checks, "frames": args.frames, "revisions": [0, store.head],
              "flipped": [f.to_json() for f in comparison.flipped], "counts": after.counts(),
              "seconds": round(time.perf_counter() - t0, 2)}
    (args.out / "result.json").write_text(json.dumps(result, indent=1) + "\n")
    print(f"{'ok' if ok else 'FAILED'}: {sum(checks.values())}/{len(checks)} checks, {len(comparison.flipped)} flipped, "
          f"{result['seconds']} s -> {args.out}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
