"""What a batch reports: ``DIR/fleet.json`` (the contract: one row per log) and ``DIR/fleet.html`` with its figures
(``fleet_ranking.png``: the logs ranked worst first; ``fleet_drift.png``: drift rate against double-wall fraction
across the fleet), and the failures with their reasons.

"Worst" is first a log whose diagnosis says it cannot judge its map (``valid`` false: its figures are no measure of
it), then the larger fraction of surface voxels doubled (``fraction_flagged``), then the larger drift rate, then the
larger smearing score; a log without a figure ranks after those with one. The table shows "cannot judge" in place of
the figures of such a diagnosis (they stay in ``fleet.json``, beside ``valid``); the figures draw them grey (hatched
bars labelled "(cannot judge)", crosses in the scatter).
"""

from __future__ import annotations

import datetime
import html
import json
import math
from pathlib import Path
from typing import Any

from driftmap._version import __version__
from driftmap.files import atomic_write
from driftmap.fleet.folders import FLEET_JSON

__all__ = ["CONTRACT_KEYS", "JUDGED_KEYS", "cannot_judge", "rank_worst_first", "ranking_labels", "write_fleet_json",
           "write_fleet_report"]

CONTRACT_KEYS = ("name", "input", "status", "error", "frames", "time_s", "ate_rmse_m", "drift_percent_per_m",
                 "fraction_flagged", "smearing_score_m")
"""The keys every row of ``fleet.json`` has (issue 27's contract: extended, never renamed)."""
JUDGED_KEYS = frozenset({"drift_percent_per_m", "drift_deg_per_m", "revisit_fraction", "fraction_flagged",
                         "fraction_flagged_before", "smearing_score_m", "smearing_score_before_m"})
"""The figures of a log's diagnosis that mean nothing when it says it cannot judge the map (ATE, from ground truth,
and the counts do not depend on it)."""
FLEET_HTML = "fleet.html"


def cannot_judge(row: dict[str, Any]) -> bool:
    """The log's diagnosis says it cannot judge its map (``valid`` false; None: no diagnosis)."""
    return row.get("valid") is False
RANKING_PNG = "fleet_ranking.png"
DRIFT_PNG = "fleet_drift.png"


def write_fleet_json(out_dir: Path, rows: list[dict[str, Any]], workers: int, ray_address: str | None, *,
                     threads: int | None = None, interrupted: list[str] | None = None) -> Path:
    """``DIR/fleet.json``: ``{"logs": rows, "workers", "ray_address"}`` and extra keys (threads per log, counts by
    status, driftmap's version, when; ``interrupted``: the logs a Ctrl-C stopped). Written atomically."""
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "failed", "skipped")}
    data: dict[str, Any] = {"logs": rows, "workers": int(workers), "ray_address": ray_address,
                            "threads_per_log": threads, "counts": counts, "driftmap": __version__,
                            "written": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}
    if interrupted is not None:
        data["interrupted"] = interrupted
    path = out_dir / FLEET_JSON
    with atomic_write(path, "fleet.json") as tmp:
        tmp.write_text(json.dumps(data, indent=1) + "\n")
    return path


def _number(row: dict[str, Any], key: str) -> float:
    value = row.get(key)
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else -math.inf


def rank_worst_first(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The logs with results (ok or skipped), worst first (see the module docstring)."""
    measured = [r for r in rows if r["status"] != "failed"]
    return sorted(measured, key=lambda r: (cannot_judge(r), _number(r, "fraction_flagged"),
                                           _number(r, "drift_percent_per_m"), _number(r, "smearing_score_m")),
                  reverse=True)


def ranking_labels(ranked: list[dict[str, Any]]) -> list[str]:
    """The ranking figure's row labels: each log's name, with "(cannot judge)" where its diagnosis cannot judge its
    map -- such logs rank first, and their bars (grey, hatched) are no measure of the map."""
    return [r["name"] + (" (cannot judge)" if cannot_judge(r) else "") for r in ranked]


def _plot_ranking(path: Path, ranked: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ranking_labels(ranked)[::-1]
    judged = [not cannot_judge(r) for r in ranked][::-1]
    flagged = [100 * max(_number(r, "fraction_flagged"), 0.0) for r in ranked][::-1]
    drift = [max(_number(r, "drift_percent_per_m"), 0.0) for r in ranked][::-1]
    fig, axes = plt.subplots(1, 2, figsize=(10, 1.2 + 0.35 * len(names)), sharey=True)
    for ax, values, colour in ((axes[0], flagged, "tab:red"), (axes[1], drift, "tab:blue")):
        # a log whose diagnosis cannot judge its map: grey and hatched (its figures are no measure of it)
        ax.barh(names, values, color=[colour if j else "0.75" for j in judged],
                hatch=[None if j else "//" for j in judged], edgecolor="0.4", linewidth=0.5)
    axes[0].set_xlabel("surface voxels doubled (%)")
    axes[1].set_xlabel("drift rate (% of path)")
    fig.suptitle("logs ranked worst first (top)")
    fig.tight_layout()
    with atomic_write(path, "fleet report") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def _plot_drift(path: Path, ranked: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    labelled = grey_labelled = False
    for r in ranked:
        x, y = _number(r, "drift_percent_per_m"), _number(r, "fraction_flagged")
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        if cannot_judge(r):  # its figures are no measure of the map: a grey cross, named as such
            ax.scatter(x, 100 * y, marker="x", color="0.5", zorder=3,
                       label=None if grey_labelled else "diagnosis cannot judge the map")
            grey_labelled = True
            ax.annotate(r["name"], (x, 100 * y), fontsize=7, color="0.4", xytext=(3, 3), textcoords="offset points")
            continue
        before = _number(r, "fraction_flagged_before")
        if math.isfinite(before):  # the same log before loop closure: a hollow marker joined to the filled one
            ax.plot([x, x], [100 * before, 100 * y], color="0.7", lw=1, zorder=1)
            ax.scatter(x, 100 * before, facecolors="none", edgecolors="tab:purple", zorder=2,
                       label=None if labelled else "before loop closure")
            labelled = True
        ax.scatter(x, 100 * y, color="tab:purple", zorder=3)
        ax.annotate(r["name"], (x, 100 * y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    if labelled or grey_labelled:
        ax.legend(loc="best", fontsize=8)
    ax.set_xlabel("drift rate (% of path travelled)")
    ax.set_ylabel("surface voxels doubled (%)")
    ax.set_title("drift rate and double-wall fraction across the fleet")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_write(path, "fleet report") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def _cell(value: Any, scale: float = 1.0, digits: int = 2) -> str:
    if isinstance(value, bool) or value is None:
        return "-" if value is None else str(value).lower()
    if isinstance(value, (int, float)):
        return f"{scale * value:.{digits}f}" if math.isfinite(value) else "-"
    return html.escape(str(value))


RESULT_COLUMNS = (("log", "name", 1, 0), ("status", "status", 1, 0), ("diagnosis", "valid", 1, 0), ("frames", "frames", 1, 0),
                  ("duration (s)", "duration_s", 1, 1), ("time (s)", "time_s", 1, 1), ("ATE (cm)", "ate_rmse_m", 100, 2),
                  ("drift (%/m)", "drift_percent_per_m", 1, 3), ("drift (deg/m)", "drift_deg_per_m", 1, 3),
                  ("revisited (%)", "revisit_fraction", 100, 0), ("doubled (%)", "fraction_flagged", 100, 2),
                  ("doubled before LC (%)", "fraction_flagged_before", 100, 2),
                  ("smearing (mm)", "smearing_score_m", 1000, 2),
                  ("smearing before LC (mm)", "smearing_score_before_m", 1000, 2))


def _results_table(ranked: list[dict[str, Any]]) -> str:
    head = "".join(f"<th>{html.escape(title)}</th>" for title, *_ in RESULT_COLUMNS)
    body = []
    for r in ranked:
        cells = []
        for _, key, scale, digits in RESULT_COLUMNS:
            if key == "valid":
                text = {True: "valid", False: "cannot judge"}.get(r.get("valid"), "-")
            elif key in JUDGED_KEYS and cannot_judge(r):
                text = "cannot judge"
            else:
                text = _cell(r.get(key), scale, digits) if key not in ("name", "status") else html.escape(str(r[key]))
            if key == "name" and r.get("folder"):
                text = f'<a href="{html.escape(r["folder"])}/diagnosis.json">{text}</a>'
            cells.append(f"<td>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _failures_table(rows: list[dict[str, Any]]) -> str:
    failed = [r for r in rows if r["status"] == "failed"]
    if not failed:
        return "<p>No log failed.</p>"
    body = "".join(f"<tr><td>{html.escape(r['name'])}</td><td>{html.escape(r['input'])}</td>"
                   f"<td>{html.escape(str(r.get('error_type') or ''))}</td><td>{html.escape(str(r['error']))}</td></tr>"
                   for r in failed)
    return f"<table><tr><th>log</th><th>input</th><th>error</th><th>reason</th></tr>{body}</table>"


def _ground_truth_notes(rows: list[dict[str, Any]]) -> str:
    """The logs diagnosed without the ground truth ``ground_truth = "auto"`` found, because it failed (no ATE)."""
    left_out = [r for r in rows if r.get("ground_truth_error")]
    if not left_out:
        return ""
    body = "".join(f"<tr><td>{html.escape(r['name'])}</td><td>{html.escape(str(r['ground_truth_error']))}</td></tr>"
                   for r in left_out)
    return (f"<h2>Ground truth left out</h2><table><tr><th>log</th><th>why (diagnosed without it, no ATE)</th></tr>"
            f"{body}</table>")


STYLE = ("body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
         "td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}td:first-child,th:first-child{text-align:left}"
         "img{max-width:100%}")


def write_fleet_report(out_dir: Path, rows: list[dict[str, Any]]) -> dict[str, Path]:
    """``DIR/fleet.html`` and its PNGs (none without a log that has results); returns the files by name."""
    ranked = rank_worst_first(rows)
    files: dict[str, Path] = {}
    figures = ""
    if ranked:
        _plot_ranking(out_dir / RANKING_PNG, ranked)
        _plot_drift(out_dir / DRIFT_PNG, ranked)
        files.update(ranking_png=out_dir / RANKING_PNG, drift_png=out_dir / DRIFT_PNG)
        figures = f'<img src="{RANKING_PNG}" alt="logs ranked worst first"><img src="{DRIFT_PNG}" alt="drift">'
    counts = ", ".join(f"{sum(r['status'] == s for r in rows)} {s}" for s in ("ok", "skipped", "failed"))
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>driftmap fleet report</title>"
            f"<style>{STYLE}</style></head><body><h1>driftmap fleet report</h1>"
            f"<p>{len(rows)} logs: {counts}. Ranked worst first: the fraction of surface voxels doubled, then the "
            f"drift rate (LC: loop closure).</p>{figures}<h2>Logs, worst first</h2>{_results_table(ranked)}"
            f"{_ground_truth_notes(rows)}<h2>Failures</h2>{_failures_table(rows)}</body></html>\n")
    with atomic_write(out_dir / FLEET_HTML, "fleet.html") as tmp:
        tmp.write_text(page)
    files["html"] = out_dir / FLEET_HTML
    return files
