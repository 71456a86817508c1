#!/usr/bin/env python
"""The perturbation sweep of the decisions (docs/decisions.md, "The perturbation sweep").

The embedded synthetic loop log placed with its ground-truth poses, its 333 generated queries
(datasets/synthetic-loop-queries.json); every assumption of :mod:`driftmap.decisions.sweep` at its default (4 or 6)
magnitudes and the given seeds. Writes OUT/sweep.json (every run), OUT/sweep.md (the table) and one plot per
assumption, OUT/sweep-<assumption>.png (flipped fraction against the magnitude, a line per seed).

Usage: .venv/bin/python scripts/decision_sweep.py [--out docs/sweep] [--seeds 0,1] [--only pose_drift,motion]
(with --only, the other assumptions' runs already in OUT/sweep.json are kept and the table and plots cover all)
(about 20 s per perturbed store on 2 shared cores: 72 stores, 25 minutes)
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from driftmap.decisions import load_queries
from driftmap.decisions.sweep import ASSUMPTIONS, spearman_by_assumption, sweep
from driftmap.pipeline.build import build
from driftmap.store.frame_store import FrameStore

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "datasets" / "synthetic-loop"
QUERIES = ROOT / "datasets" / "synthetic-loop-queries.json"


def table(result: dict) -> str:
    rows = ["| assumption | unit | flipped % at each magnitude (mean over seeds) | Spearman (magnitude, flipped fraction; every seed) |",
            "|---|---|---|---|"]
    for name, rho in result["spearman"].items():
        runs = [r for r in result["runs"] if r["assumption"] == name]
        cells = []
        for m in sorted({r["magnitude"] for r in runs}):
            f = [r["flipped_fraction"] for r in runs if r["magnitude"] == m]
            cells.append(f"{m:g}: {100 * np.mean(f):.1f}")
        rho_text = "n/a (nothing flipped)" if rho is None else f"{rho:.2f}"
        rows.append(f"| `{name}` | {ASSUMPTIONS[name].unit} | {', '.join(cells)} | {rho_text} |")
    return "\n".join(rows) + "\n"


def plot(result: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for name in result["spearman"]:
        runs = [r for r in result["runs"] if r["assumption"] == name]
        fig, ax = plt.subplots(figsize=(4.0, 3.0), dpi=100)
        for seed in sorted({r["seed"] for r in runs}):
            pts = sorted((r["magnitude"], 100 * r["flipped_fraction"]) for r in runs if r["seed"] == seed)
            ax.plot(*zip(*pts), marker="o", label=f"seed {seed}")
        ax.set_xlabel(f"{name} ({ASSUMPTIONS[name].unit})")
        ax.set_ylabel("decisions flipped (%)")
        ax.set_title(name)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / f"sweep-{name}.png")
        plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "sweep")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--only", default=None, help="comma-separated assumptions (default: all)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    names = args.only.split(",") if args.only else None
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="driftmap-sweep-") as tmp:
        store_path = Path(tmp) / "gt"
        build(LOG, store_path, poses_file=LOG / "groundtruth.txt", loop_closure=False)
        result = sweep(FrameStore.open(store_path), load_queries(QUERIES), Path(tmp) / "work", assumptions=names,
                       seeds=seeds, progress=lambda m: print(f"[{time.perf_counter() - t0:6.0f} s] {m}", flush=True))
    data = result.to_json()
    kept_file = args.out / "sweep.json"
    if names and kept_file.exists():  # the other assumptions' runs of an earlier sweep stay (same queries)
        kept = json.loads(kept_file.read_text())
        if kept.get("n_queries") == data["n_queries"]:
            runs = [r for r in kept["runs"] if r["assumption"] not in names] + data["runs"]
            order = {name: k for k, name in enumerate(ASSUMPTIONS)}
            runs.sort(key=lambda r: (order.get(r["assumption"], len(order)), r["magnitude"], r["seed"]))
            data = {"n_queries": data["n_queries"], "runs": runs, "spearman": spearman_by_assumption(runs)}
    kept_file.write_text(json.dumps(data, indent=1))
    (args.out / "sweep.md").write_text(table(data))
    plot(data, args.out)
    print(table(data))


if __name__ == "__main__":
    main()
