"""Run the driftmap benchmarks and compare each against its anchor measured in the same run.

Every ``benchmarks/bench_*.py`` module exposes ``run(quick: bool) -> list[dict]``; each dict is one
benchmark with ``name``, ``description``, ``unit``, ``ours`` and ``anchors`` (timings from
``_harness.time_per_item``), ``target_ratio`` (ours / fastest anchor must be at most this), ``check``
(the correctness check that passed) and free-form ``details``. A module raises on a failed check.

Usage: python benchmarks/run.py [--only NAME] [--quick] [--json PATH]

Exit code: 0 when everything ran (missed targets are reported, not fatal); 1 when a benchmark crashed or
its correctness check failed.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import json
import os
import platform
import subprocess
import sys
import traceback
from pathlib import Path

from rich.console import Console
from rich.table import Table

HERE = Path(__file__).resolve().parent
DEFAULT_JSON = HERE / "results" / "latest.json"


def discover() -> list[str]:
    """Module names of all ``bench_*.py`` files next to this script."""
    return sorted(p.stem for p in HERE.glob("bench_*.py"))


def value(measure: dict) -> float:
    """A measurement's median: seconds (``median_s``) or bytes (``median_bytes``, memory benchmarks)."""
    return measure["median_s"] if "median_s" in measure else measure["median_bytes"]


def score(bench: dict) -> dict:
    """Add the anchor (smallest one), ratio ours/anchor and PASS/MISS against the target."""
    anchor = min(bench["anchors"], key=lambda name: value(bench["anchors"][name]))
    ratio = value(bench["ours"]) / value(bench["anchors"][anchor])
    return {**bench, "anchor": anchor, "ratio": ratio, "passed": ratio <= bench["target_ratio"]}


def environment() -> dict:
    def version(module: str) -> str | None:
        try:
            return importlib.import_module(module).__version__
        except Exception:
            return None

    def git(*args: str) -> str | None:
        try:
            return subprocess.run(["git", *args], cwd=HERE, capture_output=True, text=True, check=True).stdout.strip()
        except Exception:
            return None

    return {
        "timestamp_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "git_commit": git("rev-parse", "HEAD"),
        "git_dirty": bool(git("status", "--porcelain")),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "versions": {m: version(m) for m in ("driftmap", "numpy", "open3d")},
    }


def fmt_time(seconds: float) -> str:
    return f"{seconds * 1e3:.3f} ms" if seconds >= 1e-3 else f"{seconds * 1e6:.1f} µs"


def fmt(measure: dict) -> str:
    return fmt_time(measure["median_s"]) if "median_s" in measure else f"{measure['median_bytes'] / 2**20:.1f} MiB"


def print_report(console: Console, results: list[dict], errors: list[dict]) -> None:
    table = Table(title="driftmap benchmarks (median per item, or memory; ratio = ours / anchor, lower is better)")
    for column in ("benchmark", "ours", "anchor", "anchor time", "ratio", "target", "result"):
        justify = "right" if column in ("ours", "anchor time", "ratio") else "left"
        table.add_column(column, justify=justify, no_wrap=True)
    for bench in results:
        for k, (name, timing) in enumerate(sorted(bench["anchors"].items(), key=lambda kv: value(kv[1]))):
            ratio = value(bench["ours"]) / value(timing)
            is_target = name == bench["anchor"]
            result = ("[green]PASS" if bench["passed"] else "[yellow]MISS") if is_target else ""
            table.add_row(
                bench["name"] if k == 0 else "",
                fmt(bench["ours"]) if k == 0 else "",
                name + (" (target)" if is_target else ""),
                fmt(timing),
                f"{ratio:.2f}x",
                f"<= {bench['target_ratio']:g}x" if is_target else "",
                result,
            )
    for err in errors:
        table.add_row(err["module"], "", "", "", "", "", "[red]ERROR")
    console.print(table)
    for bench in results:
        console.print(f"[bold]{bench['name']}[/]: {bench['description']}")
        console.print(f"  check OK: {bench['check']}")
        faults = {"ours": bench["ours"].get("page_faults_per_item", 0)}
        faults |= {name: t.get("page_faults_per_item", 0) for name, t in bench["anchors"].items()}
        if any(v >= 1 for v in faults.values()):
            listed = ", ".join(f"{k} {v:.0f}" for k, v in faults.items())
            console.print(f"  [yellow]page faults per item while timing (allocator churn is in the times): {listed}")
    for err in errors:
        console.print(f"[red]{err['module']} failed:[/] {err['error']}")


def main(argv: list[str] | None = None) -> int:
    modules = discover()
    names = [m.removeprefix("bench_") for m in modules]
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", choices=names, help="run only this benchmark module")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (a smoke run, noisier numbers)")
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON, help=f"results file (default {DEFAULT_JSON})")
    args = parser.parse_args(argv)

    sys.path.insert(0, str(HERE))
    console = Console()
    if not console.is_terminal:  # rich assumes 80 columns when piped; keep table rows on one line
        console = Console(width=120)
    results, errors = [], []
    for module_name, name in zip(modules, names):
        if args.only and name != args.only:
            continue
        console.print(f"running {module_name} ...")
        try:
            module = importlib.import_module(module_name)
            results += [score(bench) for bench in module.run(quick=args.quick)]
        except Exception as exc:
            console.print(traceback.format_exc(), markup=False, highlight=False)
            errors.append({"module": module_name, "error": f"{type(exc).__name__}: {exc}"})

    print_report(console, results, errors)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    report = {"environment": environment(), "quick": args.quick, "results": results, "errors": errors}
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    console.print(f"results written to {args.json}")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
