"""The fleet report's ranking and figures (issue 27) say which logs' diagnoses cannot judge their maps: those rank
first and are labelled, so a large bar of a log nobody can judge is not read as a measure of its map."""

from __future__ import annotations

from pathlib import Path

from driftmap.fleet.report import rank_worst_first, ranking_labels, write_fleet_report


def _row(name: str, valid: bool | None, flagged: float | None, drift: float | None, status: str = "ok") -> dict:
    return {"name": name, "input": f"logs/{name}", "status": status, "error": None if status == "ok" else "boom",
            "frames": 40, "time_s": 1.0, "ate_rmse_m": 0.05, "drift_percent_per_m": drift,
            "fraction_flagged": flagged, "smearing_score_m": 0.001, "valid": valid, "folder": name,
            "fraction_flagged_before": None if flagged is None else 2 * flagged}


ROWS = [_row("good-low", True, 0.001, 0.1), _row("unjudged", False, 0.009, 0.0), _row("good-high", True, 0.004, 0.5),
        _row("failed", None, None, None, status="failed")]


def test_unjudged_logs_rank_first_and_are_labelled_as_such() -> None:
    ranked = rank_worst_first(ROWS)
    assert [r["name"] for r in ranked] == ["unjudged", "good-high", "good-low"]  # failed logs are listed apart
    assert ranking_labels(ranked) == ["unjudged (cannot judge)", "good-high", "good-low"]


def test_the_report_writes_both_figures_and_says_cannot_judge(tmp_path: Path) -> None:
    files = write_fleet_report(tmp_path, ROWS)
    for key in ("ranking_png", "drift_png"):
        assert files[key].read_bytes()[:4] == b"\x89PNG"
    page = files["html"].read_text()
    assert "cannot judge" in page and "boom" in page.split("<h2>Failures</h2>")[1]
