"""Issue 27, "one long log, measured": how build + diagnose scale with the length of a log.

Synthetic room logs of increasing length (default 1k / 2k / 5k / 10k frames; ``--quick``: LiDAR only, 50 / 100 / 200) are
built (odometry, store, keyframes, loop candidates + verification, odometry edges, pose graph, correction) and
diagnosed, each size and sensor in a fresh subprocess, one at a time. Small clouds: an 8-beam x 180-azimuth
spinning LiDAR, 80 x 60 depth images. The robot keeps the default room speed (~0.11 m a frame round the 1 m
circle), so a longer log goes round more often (``loop_turns`` = 1.1 x frames / 60): more revisits, more loops.

Per stage: the wall time (``BuildResult.seconds_per_stage``, ``Diagnosis.seconds``) and the peak RSS while it
ran (``/proc/self/statm`` sampled every 10 ms in a thread; the frame loop interleaves read, odometry and store,
so they share one peak). Per size: the stored bytes (the store folder after build and diagnose).

The anchor is the same pipeline on the smallest log of the same run: for every stage, ``time(n) / time(n0)`` is
reported against ``n / n0`` and ``n log n / (n0 log n0)`` (the target), and the growth exponent is the log-log
slope of time over the sizes. A stage with an exponent above 1.15 (worse than n log n over these sizes) is
flagged, and so is a peak memory (above the process's baseline before the build) growing faster than the stored
bytes.

Standalone: ``python benchmarks/bench_long_log.py [--quick] [--sizes 1000,2000,5000,10000] [--sensors lidar,depth]``
prints the table (and ``--json``). ``run.py`` uses ``DRIFTMAP_LONG_LOG_SIZES`` and ``DRIFTMAP_LONG_LOG_SENSORS``
(comma-separated) when they are set.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
FULL_SIZES = (1000, 2000, 5000, 10000)
QUICK_SIZES = (50, 100, 200)  # LiDAR only: ~5 min on a loaded 2-core machine (depth adds ~10 min)
SENSORS = ("lidar", "depth")
EXPONENT_LIMIT = 1.15
FRAMES_PER_TURN = 60 / 1.1  # the default room log: 60 frames for 1.1 turns
STAGE_ORDER = ("read+validate", "odometry", "store", "keyframes", "loop candidates", "odometry edges", "pose graph",
               "correction", "build: outside the stages", "build total", "diagnose: sampling", "diagnose total")


def log_config(n_frames: int):
    from driftmap.sources.synthetic import SyntheticLogConfig

    return SyntheticLogConfig(n_frames=n_frames, loop_turns=n_frames / FRAMES_PER_TURN, lidar=True, lidar_beams=8,
                              lidar_azimuth_steps=180, width=80, height=60, fx=65.625, fy=65.625, cx=39.5, cy=29.5)


# --------------------------------------------------------------------------------------------- worker process


class RssSampler:
    """Resident set size of this process every ``period_s`` seconds, with the time of each sample."""

    def __init__(self, period_s: float = 0.01):
        self.period_s = period_s
        self.samples: list[tuple[float, int]] = []
        self._stop = threading.Event()
        self._page = os.sysconf("SC_PAGE_SIZE")
        self._thread = threading.Thread(target=self._run, daemon=True)

    def rss(self) -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self._page

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append((time.perf_counter(), self.rss()))
            self._stop.wait(self.period_s)

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append((time.perf_counter(), self.rss()))

    def peak(self, t0: float, t1: float) -> int:
        inside = [r for t, r in self.samples if t0 <= t <= t1]
        return max(inside) if inside else 0


def dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def worker(log: Path, sensor: str, out: Path, result_json: Path) -> None:
    import logging

    from driftmap.pipeline.build import build
    from driftmap.pipeline.diagnose import run_diagnose
    from driftmap.store.frame_store import FrameStore

    logging.basicConfig(level=logging.WARNING)
    first_tick: dict[str, float] = {}

    def tick(stage: str, done: int, total: int | None) -> None:
        first_tick.setdefault(stage, time.perf_counter())

    with RssSampler() as rss:
        time.sleep(0.05)
        baseline = rss.rss()
        t_start = time.perf_counter()
        result = build(log, out, format="synthetic", source_options={"sensor": sensor}, progress=tick)
        t_built = time.perf_counter()
        stored_after_build = dir_bytes(out)
        with FrameStore.open(out) as store:
            t_diag = time.perf_counter()
            diag = run_diagnose(store, out.parent / f"{out.name}-diagnosis.json")
            t_end = time.perf_counter()
        stored_after_diagnose = dir_bytes(out)
    stages = dict(result.seconds_per_stage)
    # stage windows for the memory peaks: the frame loop until the first keyframe tick; keyframes, loop candidates
    # and odometry edges from their ticks; pose graph and correction counted back from the end of build
    t_frames_end = first_tick.get("keyframes", t_built)
    windows = {"frame loop (read+odometry+store)": (t_start, t_frames_end)}
    ticked = [s for s in ("keyframes", "loop candidates", "odometry edges") if s in first_tick]
    for k, s in enumerate(ticked):
        end = first_tick[ticked[k + 1]] if k + 1 < len(ticked) else first_tick[s] + stages.get(s, 0.0)
        windows[s] = (first_tick[s] - 0.02, end + 0.02)
    if "correction" in stages:
        t_corr = t_built - stages["correction"] - 0.05
        windows["correction"] = (t_corr, t_built)
        windows["pose graph"] = (t_corr - stages.get("pose graph", 0.0) - 0.05, t_corr + 0.05)
    windows["build"] = (t_start, t_built)
    windows["diagnose"] = (t_diag, t_end)
    peaks = {name: rss.peak(*w) for name, w in windows.items()}
    diag_seconds = {f"diagnose: {k}": float(v) for k, v in diag.result.seconds.items()}
    record = {
        "sensor": sensor, "frames": result.n_frames, "keyframes": result.n_keyframes,
        "loops_tried": result.loops_tried, "loops_accepted": result.loops_accepted,
        "seconds": {**stages, "build total": t_built - t_start, **diag_seconds, "diagnose total": t_end - t_diag},
        "peak_rss_bytes": peaks, "baseline_rss_bytes": baseline,
        "peak_rss_total_bytes": max(r for _, r in rss.samples),
        "stored_bytes_after_build": stored_after_build, "stored_bytes": stored_after_diagnose,
    }
    result_json.write_text(json.dumps(record, indent=1) + "\n")


# --------------------------------------------------------------------------------------------- parent


def slope(sizes: list[int], values: list[float]) -> float | None:
    """Least-squares slope of log(value) over log(size); None when a value is not positive."""
    if len(sizes) < 2 or any(v <= 0 for v in values):
        return None
    return float(np.polyfit(np.log(sizes), np.log(values), 1)[0])


def nlogn(n: int) -> float:
    return n * math.log(n)


def measure(sizes: list[int], sensors: list[str], work: Path, echo=lambda *a: print(*a, flush=True)) -> dict:
    """Generate each log (in a subprocess), then build + diagnose it per sensor in its own subprocess."""
    runs: dict[str, dict[int, dict]] = {s: {} for s in sensors}
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(HERE), os.environ.get("PYTHONPATH")]))}
    for n in sizes:
        log = work / f"log-{n}"
        if all((work / f"result-{sensor}-{n}.json").exists() for sensor in sensors):
            for sensor in sensors:  # measured before in this --work folder
                runs[sensor][n] = json.loads((work / f"result-{sensor}-{n}.json").read_text())
                echo(f"  {sensor} {n} frames: reusing {work / f'result-{sensor}-{n}.json'}")
            continue
        t0 = time.perf_counter()
        shutil.rmtree(log, ignore_errors=True)
        subprocess.run([sys.executable, __file__, "--generate", str(n), "--log", str(log)], check=True, env=env)
        echo(f"  generated {n} frames in {time.perf_counter() - t0:.0f} s")
        for sensor in sensors:
            out, res = work / f"store-{sensor}-{n}", work / f"result-{sensor}-{n}.json"
            if res.exists():
                runs[sensor][n] = json.loads(res.read_text())
                echo(f"  {sensor} {n} frames: reusing {res}")
                continue
            shutil.rmtree(out, ignore_errors=True)
            t0 = time.perf_counter()
            subprocess.run([sys.executable, __file__, "--worker", sensor, "--log", str(log), "--out", str(out),
                            "--result", str(res)], check=True, env=env)
            runs[sensor][n] = json.loads(res.read_text())
            r = runs[sensor][n]
            echo(f"  {sensor} {n} frames: build {r['seconds']['build total']:.1f} s, diagnose "
                 f"{r['seconds']['diagnose total']:.1f} s, {r['loops_accepted']}/{r['loops_tried']} loops, peak RSS "
                 f"{r['peak_rss_total_bytes'] / 2**20:.0f} MiB, stored {r['stored_bytes'] / 2**20:.1f} MiB "
                 f"(wall {time.perf_counter() - t0:.0f} s)")
            shutil.rmtree(out, ignore_errors=True)
        shutil.rmtree(log, ignore_errors=True)
    return runs


BUILD_STAGES = ("read+validate", "odometry", "poses", "store", "keyframes", "loop candidates", "odometry edges",
                "pose graph", "correction")


def analyse(runs: dict[str, dict[int, dict]]) -> dict:
    out = {}
    for by_n in runs.values():  # build's time outside its named stages (loop config, flagged rows, graph verdicts)
        for r in by_n.values():
            sec = r["seconds"]
            sec["build: outside the stages"] = sec["build total"] - sum(sec.get(s, 0.0) for s in BUILD_STAGES)
    for sensor, by_n in runs.items():
        sizes = sorted(by_n)
        n0 = sizes[0]
        stages = [s for s in STAGE_ORDER if any(s in by_n[n]["seconds"] for n in sizes)]
        stages += sorted({s for n in sizes for s in by_n[n]["seconds"]} - set(stages))
        rows = {}
        for stage in stages:
            t = [by_n[n]["seconds"].get(stage, 0.0) for n in sizes]
            exp = slope(sizes, t)
            rows[stage] = {"seconds": dict(zip(sizes, t)), "exponent": exp,
                           "ratio_vs_anchor": t[-1] / t[0] if t[0] > 0 else None,
                           "flag": exp is not None and exp > EXPONENT_LIMIT}
        stored = [by_n[n]["stored_bytes"] for n in sizes]
        stored_exp = slope(sizes, stored)
        mem = {}
        for window in by_n[sizes[-1]]["peak_rss_bytes"]:
            peak = [by_n[n]["peak_rss_bytes"].get(window, 0) for n in sizes]
            above = [p - by_n[n]["baseline_rss_bytes"] for p, n in zip(peak, sizes)]
            exp = slope(sizes, above)
            mem[window] = {"peak_bytes": dict(zip(sizes, peak)), "above_baseline_bytes": dict(zip(sizes, above)),
                           "exponent": exp,
                           "flag": exp is not None and stored_exp is not None and exp > stored_exp + 0.05}
        out[sensor] = {"sizes": sizes, "anchor_frames": n0, "stages": rows, "memory": mem,
                       "stored_bytes": dict(zip(sizes, stored)), "stored_exponent": stored_exp,
                       "linear_ratio": sizes[-1] / n0, "nlogn_ratio": nlogn(sizes[-1]) / nlogn(n0),
                       "loops": {n: (by_n[n]["loops_accepted"], by_n[n]["loops_tried"], by_n[n]["keyframes"])
                                 for n in sizes}}
    return out


def fmt_exp(e: float | None) -> str:
    return "-" if e is None else f"{e:.2f}"


def table(analysis: dict) -> str:
    lines = []
    for sensor, a in analysis.items():
        sizes = a["sizes"]
        lines.append(f"## {sensor}: sizes {', '.join(map(str, sizes))} frames; anchor = the {a['anchor_frames']}-frame "
                     f"run; n/n0 = {a['linear_ratio']:.2f}, n log n/(n0 log n0) = {a['nlogn_ratio']:.2f}")
        lines.append("loops accepted/tried (keyframes): " + ", ".join(f"{n}: {acc}/{tr} ({kf})" for n, (acc, tr, kf) in a["loops"].items()))
        head = "| stage | " + " | ".join(f"{n} s" for n in sizes) + " | t(n)/t(n0) | exponent | > 1.15 |"
        lines += [head, "|" + "---|" * (len(sizes) + 4)]
        for stage, r in a["stages"].items():
            ratio = "-" if r["ratio_vs_anchor"] is None else f"{r['ratio_vs_anchor']:.2f}"
            lines.append(f"| {stage} | " + " | ".join(f"{r['seconds'][n]:.2f}" for n in sizes)
                         + f" | {ratio} | {fmt_exp(r['exponent'])} | {'FLAG' if r['flag'] else ''} |")
        lines.append("")
        head = "| peak RSS (MiB) during | " + " | ".join(f"{n}" for n in sizes) + " | exponent above baseline | faster than stored |"
        lines += [head, "|" + "---|" * (len(sizes) + 3)]
        for window, m in a["memory"].items():
            lines.append(f"| {window} | " + " | ".join(f"{m['peak_bytes'][n] / 2**20:.0f} (+{m['above_baseline_bytes'][n] / 2**20:.0f})"
                                                   for n in sizes) + f" | {fmt_exp(m['exponent'])} | {'FLAG' if m['flag'] else ''} |")
        lines.append(f"| stored bytes (MiB) | " + " | ".join(f"{a['stored_bytes'][n] / 2**20:.1f}" for n in sizes)
                     + f" | {fmt_exp(a['stored_exponent'])} | |")
        lines.append("")
    return "\n".join(lines)


def sizes_for(quick: bool) -> list[int]:
    env = os.environ.get("DRIFTMAP_LONG_LOG_SIZES")
    if env:
        return sorted(int(s) for s in env.split(","))
    return list(QUICK_SIZES if quick else FULL_SIZES)


def rows_of(analysis: dict, runs: dict) -> list[dict]:
    """One harness row per sensor and stage: ours = the stage at the largest size, anchor = at the smallest,
    target = the n log n ratio."""
    rows = []
    for sensor, a in analysis.items():
        n0, n1 = a["sizes"][0], a["sizes"][-1]
        for stage, r in a["stages"].items():
            if r["seconds"][n0] <= 0:
                continue
            rows.append({
                "name": f"long_log_{sensor}_{stage.replace(' ', '_').replace(':', '').replace('+', '_')}",
                "description": f"{stage} on a {n1}-frame synthetic {sensor} log vs the same on {n0} frames (target: "
                               f"n log n growth; exponent {fmt_exp(r['exponent'])} over {a['sizes']})",
                "unit": "log",
                "ours": {"median_s": r["seconds"][n1]},
                "anchors": {f"same_pipeline_{n0}_frames": {"median_s": r["seconds"][n0]}},
                "target_ratio": a["nlogn_ratio"],
                "check": f"{n1} frames built and diagnosed; loops accepted/tried {a['loops'][n1][0]}/{a['loops'][n1][1]}",
                "details": {"seconds": r["seconds"], "exponent": r["exponent"], "linear_ratio": a["linear_ratio"],
                            "flag_exponent_above_1_15": r["flag"], "memory": a["memory"],
                            "stored_bytes": a["stored_bytes"], "stored_exponent": a["stored_exponent"]},
            })
    return rows


def run(quick: bool = False, sizes: list[int] | None = None, sensors: list[str] | None = None,
        echo=lambda *a: print(*a, flush=True), work: Path | None = None) -> list[dict]:
    sizes = sizes or sizes_for(quick)
    env_sensors = os.environ.get("DRIFTMAP_LONG_LOG_SENSORS")
    sensors = sensors or (env_sensors.split(",") if env_sensors else ["lidar"] if quick else list(SENSORS))
    if work is not None:  # kept: a later run with the same --work reuses the sizes measured already
        work.mkdir(parents=True, exist_ok=True)
        runs = measure(sizes, sensors, work, echo)
    else:
        with tempfile.TemporaryDirectory(prefix="driftmap-longlog-") as tmp:
            runs = measure(sizes, sensors, Path(tmp), echo)
    analysis = analyse(runs)
    echo(table(analysis))
    from _harness import check

    for sensor in sensors:
        for n, r in runs[sensor].items():
            check(r["frames"] == n, f"{sensor}: {r['frames']} of {n} frames stored")
    return rows_of(analysis, runs)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--sizes", help="comma-separated frame counts (default 1000,2000,5000,10000; --quick 50,100,200)")
    p.add_argument("--sensors", help="comma-separated: lidar,depth (default both; --quick: lidar)")
    p.add_argument("--json", type=Path, help="write the rows and the raw runs here")
    p.add_argument("--work", type=Path, help="keep logs' results here; sizes measured there before are reused")
    p.add_argument("--generate", type=int, help=argparse.SUPPRESS)
    p.add_argument("--worker", help=argparse.SUPPRESS)
    p.add_argument("--log", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.generate:
        from driftmap.sources.synthetic import generate_synthetic_log

        generate_synthetic_log(args.log, log_config(args.generate))
        return
    if args.worker:
        worker(args.log, args.worker, args.out, args.result)
        return
    sys.path.insert(0, str(HERE))
    sizes = sorted(int(s) for s in args.sizes.split(",")) if args.sizes else None
    rows = run(args.quick, sizes, args.sensors.split(",") if args.sensors else None, work=args.work)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
