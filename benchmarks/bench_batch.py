"""Issue 27, the batch benchmark: a fleet of synthetic logs on the embedded Ray, 1 worker vs 2 workers, and the batch
against a plain sequential loop over the same logs.

Eight synthetic room logs (``driftmap.fleet.synth_fleet``, seed 7, 40 frames of 200x150 depth each: the logs
``driftmap synth --fleet 8`` writes) are processed three ways, each into a fresh folder, one after the other:

* ``sequential``: a plain loop of ``driftmap.fleet.run_log`` (build -> diagnose -> exports, one thread) in this
  process, no Ray;
* ``batch_1_worker``: ``run_batch(..., workers=1)`` with one thread per log (``[fleet] threads_per_log = 1``): an
  embedded Ray started and stopped by the call, one log at a time;
* ``batch_2_workers``: the same with two workers (two logs at once on this 2-core machine).

Targets (issue 27): speed-up of 2 workers over 1 worker >= 1.7x; the batch's overhead per log against the plain
loop <= 10 % (1 worker's wall time / the loop's - 1; it includes starting and stopping Ray, which is reported
apart in the details). The check: every log gives the same poses to the bit three ways (and ``ok`` rows).

``--quick``: 4 logs of 20 frames (a smoke run: Ray's start-up then weighs more).
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from pathlib import Path

from _harness import check

from driftmap.fleet import BatchConfig, FleetSettings, expand_inputs, run_batch, run_log, synth_fleet
from driftmap.store.frame_store import FrameStore

N_LOGS, FRAMES = 8, 40
QUICK_LOGS, QUICK_FRAMES = 4, 20
SPEEDUP_TARGET = 1.7
OVERHEAD_TARGET = 0.10


def _poses(folder: Path) -> dict[str, bytes]:
    out = {}
    for log in sorted(p for p in folder.iterdir() if (p / "store").is_dir()):
        with FrameStore.open(log / "store") as store:
            out[log.name] = store.poses(store.head).tobytes()
    return out


def _timing(seconds: float, n_logs: int) -> dict:
    per_log = seconds / n_logs
    return {"median_s": per_log, "min_s": per_log, "max_s": per_log, "repeats": 1, "items": n_logs,
            "page_faults_per_item": 0.0, "samples_s": [per_log]}


def run(quick: bool = False) -> list[dict]:
    n_logs, frames = (QUICK_LOGS, QUICK_FRAMES) if quick else (N_LOGS, FRAMES)
    config = BatchConfig(fleet=FleetSettings(threads_per_log=1))
    logging.getLogger("driftmap").setLevel(logging.ERROR)
    with tempfile.TemporaryDirectory(prefix="driftmap-bench-batch-") as tmp:
        root = Path(tmp)
        synth_fleet(root / "logs", n_logs, frames=frames)
        specs = expand_inputs([str(root / "logs" / "*")])
        check(len(specs) == n_logs, f"{len(specs)} logs found, {n_logs} written")

        seq_dir = root / "sequential"
        seq_dir.mkdir()
        t0 = time.perf_counter()
        rows = [run_log(spec, config, seq_dir, threads=1, config_file=config.write_tables(seq_dir)) for spec in specs]
        sequential_s = time.perf_counter() - t0
        check(all(r["status"] == "ok" for r in rows), f"sequential: {[r['error'] for r in rows if r['status'] != 'ok']}")

        walls, ray_s = {}, {}
        for workers in (1, 2):
            out = root / f"batch{workers}"
            t0 = time.perf_counter()
            result = run_batch(specs, out, config, workers=workers)
            walls[workers] = time.perf_counter() - t0
            ray_s[workers] = walls[workers] - sum(r["time_s"] for r in result.rows) / workers
            check(not result.failed, f"batch with {workers} worker(s): {result.failed}")
        reference = _poses(seq_dir)
        for workers in (1, 2):
            check(_poses(root / f"batch{workers}") == reference,
                  f"batch with {workers} worker(s): poses differ from the sequential loop's")

    speedup = walls[1] / walls[2]
    overhead = walls[1] / sequential_s - 1.0
    n = n_logs
    base = {"n_logs": n, "frames_per_log": frames, "sequential_s": sequential_s, "batch_1_worker_s": walls[1],
            "batch_2_workers_s": walls[2], "speedup_2_vs_1": speedup, "overhead_per_log_vs_loop": overhead,
            "outside_logs_s": ray_s, "load_avg": [round(v, 2) for v in os.getloadavg()]}
    return [
        {
            "name": "batch_speedup",
            "description": f"driftmap batch of {n} synthetic logs ({frames} frames each) on the embedded Ray: 2 workers "
                           f"vs 1 worker, one thread per log (speed-up {speedup:.2f}x; target >= {SPEEDUP_TARGET}x)",
            "unit": "log",
            "ours": _timing(walls[2], n),
            "anchors": {"batch_1_worker": _timing(walls[1], n)},
            "target_ratio": 1.0 / SPEEDUP_TARGET,
            "check": "every log gives the same poses to the bit with 1 and 2 workers and in the plain loop",
            "details": base,
        },
        {
            "name": "batch_overhead",
            "description": f"the same batch with 1 worker vs a plain sequential loop of run_log (overhead per log "
                           f"{100 * overhead:.1f} %, Ray's start and stop included; target <= {100 * OVERHEAD_TARGET:.0f} %)",
            "unit": "log",
            "ours": _timing(walls[1], n),
            "anchors": {"sequential_loop": _timing(sequential_s, n)},
            "target_ratio": 1.0 + OVERHEAD_TARGET,
            "check": "as batch_speedup",
            "details": base,
        },
    ]


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run("--quick" in sys.argv), indent=1, default=str))
