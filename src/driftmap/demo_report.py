"""The demo's results (:class:`DemoResult`, ``summary.json``) and its Markdown / HTML reports; the CLI's summary
table shows the same rows (:func:`summary_rows`)."""

from __future__ import annotations

import html
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from driftmap.diagnostics.report import Diagnosis


@dataclass(frozen=True)
class DiagnosisSummary:
    """The numbers of one ``diagnose`` run the demo reports (the full JSON is written beside it)."""

    label: str
    revision: int | None
    smearing_score_m: float
    voxels_evaluated: int
    voxels_flagged: int
    fraction_flagged: float
    median_separation_m: float | None
    n_regions: int
    regions: list[dict[str, Any]]
    ate_rmse_m: float | None
    json_path: str | None
    valid: bool | None = None
    """the diagnosis can judge the map (False: its figures are not a verdict; None: no coverage check ran)"""
    reasons: list[str] = field(default_factory=list)
    """why it cannot judge (empty when valid)"""

    @classmethod
    def of(cls, label: str, d: Diagnosis, json_path: Path | None, *, revision: int | None, max_regions: int = 5) -> DiagnosisSummary:
        dw = d.double_walls
        regions = [{"center_m": np.round(r.center_m, 3).tolist(), "separation_m": round(float(r.separation_m), 4),
                    "separation_sigma_m": round(float(r.separation_sigma_m), 4),
                    "frames_a": [int(r.frames_a.min()), int(r.frames_a.max())],
                    "frames_b": [int(r.frames_b.min()), int(r.frames_b.max())]} for r in dw.regions[:max_regions]]
        return cls(label, revision, float(dw.smearing_score_m), int(dw.voxels_evaluated), int(dw.voxels_flagged),
                   float(dw.fraction_flagged), dw.median_separation_m, len(dw.regions), regions,
                   None if d.trajectory is None else float(d.trajectory["ate_rmse_m"]),
                   None if json_path is None else str(json_path),
                   None if d.coverage is None else bool(d.coverage.valid),
                   [] if d.coverage is None else list(d.coverage.reasons))

    @property
    def cannot_judge(self) -> bool:
        return self.valid is False


@dataclass(frozen=True)
class VolumeSummary:
    """The demo's volumetric layers: revision 0 built, then updated to the loop closure's revision (``*_after``:
    None without one). ``summary.json`` holds every field with a ``volume_`` prefix."""

    voxel_size_m: float
    revision_before: int
    occupied_before: int
    free_before: int
    unknown_before: int
    n_voxels: int
    """voxels of the grid (after the update: it may grow)"""
    unknown_fraction: float
    """never-observed share of the grid's voxels, of the last revision the layers hold"""
    build_s: float
    """building the layers of revision 0 from its frames"""
    top_view_band_m: tuple[float, float]
    """the height band (z, metres) the top views show"""
    top_view_extent_m: tuple[float, float, float, float]
    """x min, x max, y min, y max (metres) both top views show (:func:`~driftmap.diagnostics.figures.top_view_layout`)"""
    loop_wall_thickness_before_m: float | None
    """median extent across the loop wall of its occupied cells from above (a double wall is thicker)"""
    revision_after: int | None = None
    occupied_after: int | None = None
    free_after: int | None = None
    unknown_after: int | None = None
    update_s: float | None = None
    """:meth:`VolumeLayers.apply` to the loop closure's revision (every moved frame taken out and put back)"""
    update_rebuilt: bool | None = None
    frames_reintegrated: int | None = None
    state_changed: int | None = None
    """voxels whose state (occupied / free / unknown) the update changed"""
    loop_wall_thickness_after_m: float | None = None
    mesh_triangles: int | None = None
    """triangles of the TSDF mesh of the last revision (None: nothing to mesh)"""

    def to_json(self) -> dict[str, Any]:
        return {f"volume_{k}": (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


@dataclass(frozen=True)
class DemoResult:
    out_dir: Path
    n_frames: int
    n_points: int
    mean_invalid_fraction: float
    flagged_frames: list[int]
    wall_spread_odometry_m: float
    wall_spread_ground_truth_m: float
    wall_spread_odometry_max_m: float
    wall_spread_ground_truth_max_m: float
    files: dict[str, str]
    seconds: float
    loops_accepted: int = 0
    wall_spread_corrected_m: float | None = None
    wall_spread_corrected_max_m: float | None = None
    ate_odometry_m: float | None = None
    ate_corrected_m: float | None = None
    loop_revision: int | None = None
    loops_tried: int = 0
    max_correction_m: float | None = None
    frames_retransformed: int = 0
    diagnosis_before: DiagnosisSummary | None = None
    diagnosis_after: DiagnosisSummary | None = None
    diagnosis_ground_truth: DiagnosisSummary | None = None
    seconds_per_stage: dict[str, float] = field(default_factory=dict)
    volume: VolumeSummary | None = None

    @property
    def double_walls_before(self) -> int:
        return 0 if self.diagnosis_before is None else self.diagnosis_before.n_regions

    @property
    def double_walls_after(self) -> int | None:
        return None if self.diagnosis_after is None else self.diagnosis_after.n_regions

    def to_json(self) -> dict:
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        d.pop("volume")
        if self.volume is not None:
            d.update(self.volume.to_json())
        d["double_walls_before"] = self.double_walls_before
        d["double_walls_after"] = self.double_walls_after
        return d


def _cm(v: float | None) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{100 * v:.1f} cm"


def _mm(v: float | None) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{1000 * v:.2f} mm"


def summary_rows(r: DemoResult) -> list[tuple[str, str]]:
    """The demo's summary as (quantity, value) rows: the CLI table and the reports show the same."""
    before, after, ref = r.diagnosis_before, r.diagnosis_after, r.diagnosis_ground_truth
    rows = [
        ("frames / points (sensor frames)", f"{r.n_frames} / {r.n_points:,}"),
        ("mean invalid-pixel fraction", f"{r.mean_invalid_fraction:.3f}"),
        ("loops tried / accepted", f"{r.loops_tried} / {r.loops_accepted}"),
        ("frames re-transformed by the correction", f"{r.frames_retransformed} (max {_cm(r.max_correction_m)})"),
    ]
    if r.loop_revision is None:
        rows.append(("loop closure", f"no correction: {r.loops_tried} loops tried, {r.loops_accepted} accepted"))
    if before is not None:
        rows.append(("diagnosis: revision 0 -> corrected",
                     f"{_verdict(before)} -> {'-' if after is None else _verdict(after)}"))
        rows.append(("double-wall regions: revision 0 -> corrected",
                     f"{before.n_regions} -> {'-' if after is None else after.n_regions}"))
        rows.append(("surface voxels doubled: revision 0 -> corrected",
                     f"{100 * before.fraction_flagged:.2f} % -> " + ("-" if after is None else f"{100 * after.fraction_flagged:.2f} %")))
        rows.append(("median double-wall separation, revision 0", _cm(before.median_separation_m)))
        rows.append(("smearing score: revision 0 -> corrected (ground truth)",
                     f"{_mm(before.smearing_score_m)} -> {_mm(None if after is None else after.smearing_score_m)}"
                     f" ({_mm(None if ref is None else ref.smearing_score_m)})"))
    rows.append(("loop wall spread (median): odometry -> corrected (ground truth)",
                 f"{_cm(r.wall_spread_odometry_m)} -> {_cm(r.wall_spread_corrected_m)} ({_cm(r.wall_spread_ground_truth_m)})"))
    rows.append(("ATE vs ground truth: odometry -> corrected", f"{_cm(r.ate_odometry_m)} -> {_cm(r.ate_corrected_m)}"))
    if r.volume is not None:
        rows += volume_rows(r.volume)
    rows.append(("time", f"{r.seconds:.1f} s"))
    return rows


def _verdict(s: DiagnosisSummary) -> str:
    """``valid`` or ``cannot judge`` (the figures beside it are then no verdict on the map)."""
    return "cannot judge" if s.cannot_judge else "valid" if s.valid else "-"


def story(r: DemoResult) -> str:
    """The report's first sentence: what was done to the log (the loop closure only when it made a revision)."""
    text = ("The embedded synthetic log (a robot driving a loop in a furnished room, with drifting odometry) was built "
            "into a frame store and diagnosed")
    if r.loop_revision is None:
        text += (f"; loop closure made no correction ({r.loops_tried} loops tried, {r.loops_accepted} accepted), so "
                 "there is no corrected revision to compare with.")
    else:
        text += ", corrected by loop closure and diagnosed again."
    judged = [s for s in (r.diagnosis_before, r.diagnosis_after) if s is not None and s.cannot_judge]
    for s in judged:
        text += (f" The diagnosis of {s.label} cannot judge the map ({'; '.join(s.reasons) or 'see its JSON'}): its "
                 "double-wall figures are no verdict on it.")
    return text


def volume_rows(v: VolumeSummary) -> list[tuple[str, str]]:
    """The volumetric layers' rows of the summary table."""
    after = "-" if v.occupied_after is None else f"{v.occupied_after:,}"
    update = ("-" if v.update_s is None else
              f"{v.update_s:.1f} s ({v.frames_reintegrated} frames re-integrated, {v.state_changed:,} voxels changed "
              f"state{', fell back to a rebuild' if v.update_rebuilt else ''})")
    return [
        (f"volume ({100 * v.voxel_size_m:g} cm voxels): occupied voxels, revision 0 -> corrected",
         f"{v.occupied_before:,} -> {after} ({100 * v.unknown_fraction:.0f} % of the grid unknown)"),
        ("volume: loop wall thickness from above, revision 0 -> corrected",
         f"{_cm(v.loop_wall_thickness_before_m)} -> {_cm(v.loop_wall_thickness_after_m)}"),
        ("volume: update to the correction vs build of revision 0", f"{update} vs {v.build_s:.1f} s"),
    ]


def region_lines(s: DiagnosisSummary) -> list[str]:
    """One line per double-wall region: separation, where, and which frames disagree."""
    return [f"{100 * g['separation_m']:.1f} +- {100 * g['separation_sigma_m']:.1f} cm apart at {g['center_m']} m: frames "
            f"{g['frames_a'][0]}-{g['frames_a'][1]} vs {g['frames_b'][0]}-{g['frames_b'][1]}" for g in s.regions]


_UNCORRECTED = {
    "top_view_png": "Top view (0.9-2.4 m slice) coloured by frame: revision 0, the drifting odometry (no correction was made).",
    "volume_top_view_before_png": ("Volumetric layers of revision 0 from above (free white, occupied black, never "
                                   "observed grey, the sensor path blue)."),
}
"""captions of a run without a loop-closure revision (the others compare revision 0 with the correction)"""

_FIGURES = [
    ("top_view_png", "Top view (0.9-2.4 m slice) coloured by frame: the loop wall is doubled with the drifting odometry and single after the correction."),
    ("double_walls_rev0_png", "Revision 0: map coloured by double-wall separation."),
    ("frame_disagreement_rev0_png", "Revision 0: per-frame disagreement with the rest of the map, with change points."),
    ("smearing_before_after_png", "Smearing score per voxel scale before and after the correction, and for the ground-truth placement."),
    ("double_walls_rev1_png", "After loop closure: map coloured by double-wall separation."),
    ("frame_disagreement_rev1_png", "After loop closure: per-frame disagreement."),
    ("volume_top_view_before_png", ("Volumetric layers of revision 0 from above (free white, occupied black, never "
                                    "observed grey, the sensor path blue): the loop wall is doubled, a thick or "
                                    "stepped line.")),
    ("volume_top_view_after_png", ("The same layers updated to the loop closure's revision (the moved frames taken "
                                   "out and put back, not rebuilt): the loop wall is a single line.")),
]


def _figures(r: DemoResult) -> list[tuple[str, str]]:
    """(file key, caption) of the figures the run wrote."""
    out = []
    for key, caption in _FIGURES:
        if key in r.files:
            out.append((key, _UNCORRECTED.get(key, caption) if r.loop_revision is None else caption))
    return out


def _rel(path: str, root: Path) -> str:
    return Path(path).resolve().relative_to(root.resolve()).as_posix()


def write_markdown_report(path: Path, r: DemoResult) -> Path:
    lines = ["# driftmap demo report", "", story(r), "", "| quantity | value |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in summary_rows(r)]
    for s in (r.diagnosis_before, r.diagnosis_after):
        if s is None:
            continue
        lines += ["", f"## Double walls, {s.label}", ""]
        lines += [f"- {line}" for line in region_lines(s)] or ["- none flagged"]
    lines += ["", "## Figures", ""]
    for key, caption in _figures(r):
        lines += [f"![{caption}]({_rel(r.files[key], path.parent)})", "", f"*{caption}*", ""]
    lines += ["## Files", ""]
    lines += [f"- `{k}`: `{_rel(v, path.parent)}`" for k, v in r.files.items() if Path(v).exists()]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_html_report(path: Path, r: DemoResult) -> Path:
    esc = html.escape
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>driftmap demo report</title>",
             "<style>body{font-family:sans-serif;max-width:1200px;margin:2em auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #ccc;padding:4px 8px}td:last-child{text-align:right}img{max-width:100%}</style>",
             "</head><body><h1>driftmap demo report</h1>",
             f"<p>{esc(story(r))}</p><table><tr><th>quantity</th><th>value</th></tr>"]
    parts += [f"<tr><td>{esc(k)}</td><td>{esc(v)}</td></tr>" for k, v in summary_rows(r)]
    parts.append("</table>")
    for s in (r.diagnosis_before, r.diagnosis_after):
        if s is None:
            continue
        parts.append(f"<h2>Double walls, {esc(s.label)}</h2><ul>")
        parts += [f"<li>{esc(line)}</li>" for line in region_lines(s)] or ["<li>none flagged</li>"]
        parts.append("</ul>")
    parts.append("<h2>Figures</h2>")
    for key, caption in _figures(r):
        parts.append(f"<figure><img src='{esc(_rel(r.files[key], path.parent))}' alt='{esc(caption)}'>"
                     f"<figcaption>{esc(caption)}</figcaption></figure>")
    parts.append("</body></html>")
    path.write_text("\n".join(parts) + "\n")
    return path
