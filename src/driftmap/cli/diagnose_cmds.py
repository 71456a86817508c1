"""Commands that judge and show a store: ``diagnose``, ``view``, ``perturb``."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import numpy as np
import typer
from rich.table import Table
from rich.text import Text

from driftmap.cli.common import (
    CALIB_HELP,
    KITTI_FRAME_HELP,
    app,
    bold,
    check_output,
    choice,
    console,
    err_console,
    finite,
    finite_within,
    open_store,
    progress_bar,
    refuse_existing,
    refuse_output_on_input,
    refuse_same_output,
    refuse_store_inputs,
    stage_ticker,
    warn_unmerged,
    writing_output,
)

if TYPE_CHECKING:
    from driftmap.diagnostics.diagnosis import Diagnosis
    from driftmap.diagnostics.revisits import RevisitCheck
    from driftmap.diagnostics.verify import RegionCheck
    from driftmap.pipeline.diagnose import DiagnoseRun


def _verification_note(check: RegionCheck) -> str:
    if check.offset_b_minus_a_m is None:
        return f"; unverifiable ({check.note})"
    cause = {True: ", a pose error", False: ", local (its surroundings agree: not a pose error)", None: ""}[check.pose_explained]
    return f"; measured {100 * check.offset_b_minus_a_m:+.1f} cm: {'confirmed' + cause if check.confirmed else 'NOT confirmed'}"


@app.command()
def diagnose(
    store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")],
    json_path: Annotated[Path, typer.Option("--json", help="Write the diagnosis here (JSON).")],
    revision: Annotated[Optional[int], typer.Option("--revision", help="Revision (default: the latest).")] = None,
    gt: Annotated[Optional[Path], typer.Option("--gt", help="Ground-truth poses (T_world_sensor) for ATE/RPE.")] = None,
    gt_format: Annotated[Optional[str], typer.Option("--gt-format", help="tum (matched by stamp; the default) | kitti (row i = frame_id i) | redwood (.log: by the frame ids it names) | 4x4 (one 4x4 matrix per frame: by stamp when the last rows hold stamps, else block i = frame_id i) | euroc (EuRoC / ASL CSV, stamps in ns: by stamp)")] = None,
    report: Annotated[Optional[Path], typer.Option("--report", help="Write PNG figures to this folder.")] = None,
    compare_revision: Annotated[Optional[int], typer.Option("--compare-revision", help="Also diagnose this revision; the report shows the score before/after.")] = None,
    points_per_frame: Annotated[Optional[int], typer.Option("--points-per-frame", min=50, help="Points sampled per frame (default: a budget of 600k RGB-D / 1M LiDAR points shared by the frames).")] = None,
    kitti_frame: Annotated[str, typer.Option("--kitti-frame", help=KITTI_FRAME_HELP)] = "auto",
    calib: Annotated[Optional[Path], typer.Option("--calib", help=CALIB_HELP)] = None,
    verify: Annotated[bool, typer.Option("--verify", help="Re-measure every double-wall region from the stored full-resolution frames with Open3D (adds \"verification\" per region and double_wall.verified).")] = False,
    config: Annotated[Optional[Path], typer.Option("--config", help="Config file (JSON or TOML): its [diagnose] table (or the whole file without one) sets diagnose's own lengths over the scene's defaults: [diagnose.double_wall] voxel_sizes_m, visit_gap_m, ..., [diagnose.attribution], [diagnose.sampling], [diagnose.entropy] (the JSON's \"config\" lists every field); its [volume] table sets the report's volumetric layers (as for export); the other tables are left to the commands that read them, and a file holding none of these is refused.")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --json file that is not an earlier diagnosis (an earlier diagnosis is replaced without it).")] = False,
) -> None:
    """Find double walls (where, how far apart, which frames), the smearing score, MME/MPV, per-frame
    disagreement and change points; with --gt also ATE/RPE."""
    from driftmap.pipeline.diagnose import GT_FORMATS, is_diagnosis_file, run_diagnose

    gt_format = None if gt_format is None else choice(gt_format, GT_FORMATS, "--gt-format")
    refuse_same_output([(p, f) for p, f in ((json_path, "--json"), (report, "--report"), (gt, "--gt"),
                                            (config, "--config"), (calib, "--calib"))
                        if p is not None], folders=("--report",))  # an output never replaces an input, nor another output
    refuse_store_inputs(store_path, [(p, f) for p, f in ((json_path, "--json"), (report, "--report")) if p is not None])
    from driftmap.config import DriftmapConfig, refuse_unread_tables

    volume_config = DriftmapConfig.load(config).volume  # the report's volumetric layers, as export builds them
    if config is not None:
        refuse_unread_tables(config, "diagnose")
    if json_path.is_file() and not is_diagnosis_file(json_path):
        refuse_existing(json_path, "--json (not an earlier diagnosis)", overwrite)
    check_output(json_path, "--json")  # before the diagnosis, not after it
    check_output(report, "--report", folder=True)
    with open_store(store_path, reads_map=True) as store, progress_bar() as progress:
        from driftmap.errors import ConfigError

        for rev, flag in ((revision, "--revision"), (compare_revision, "--compare-revision")):
            if rev is not None and not 0 <= rev <= store.head:  # before the first diagnosis, not after it
                raise ConfigError(f"{flag} {rev}: {store_path} has revisions 0..{store.head}")
        warn_unmerged(store, [store.head if revision is None else revision]
                      + ([] if compare_revision is None else [compare_revision]))
        tick = stage_ticker(progress)

        run = run_diagnose(store, json_path, revision=revision, gt=gt, gt_format=gt_format, report_dir=report,
                           compare_revision=compare_revision, points_per_frame=points_per_frame,
                           kitti_frame=kitti_frame, calib=calib, verify=verify, config_file=config, progress=tick,
                           volume_config=volume_config)
    _render_diagnosis(run, store_path)
    console.print(bold("diagnosis: ", json_path))


def _diagnosis_rows(run: DiagnoseRun) -> list[tuple[str, str]]:
    """The rows of the diagnose table: the headline figures, each marked "cannot judge" where coverage says so."""
    result, other, data = run.result, run.other, run.data
    dw = result.double_walls
    rows = [
        ("smearing score", f"{1000 * dw.smearing_score_m:.2f} mm ("
                           + ", ".join(f"{k:.3g} m: {1000 * v:.2f}" for k, v in dw.score_per_scale_m.items()) + "; between visits)"
         if dw.voxels_revisited else
         f"{1000 * dw.smearing_score_m:.2f} mm: no surface was seen on two visits "
         f"({dw.config.visit_gap_m:g} m of travel apart), so drift cannot show"),
        ("smearing score, frame to frame", f"{1000 * dw.frame_smearing_score_m:.2f} mm"),
        ("surface voxels doubled", f"{dw.voxels_flagged} / {dw.voxels_evaluated} ({100 * dw.fraction_flagged:.2f} %)"),
        ("median separation", "-" if dw.median_separation_m is None else f"{100 * dw.median_separation_m:.1f} cm"),
        ("double-wall regions", str(len(dw.regions))),
        ("change points (frame: jump)", ", ".join(
            f"{c.frame_id}: {100 * c.jump_m:.1f} cm" + (f" / {np.linalg.norm(c.step_deg):.1f} deg" if c.step_deg and np.any(c.step_deg) else "")
            for c in result.attribution.change_points) or "-"),
        ("revisited", f"{100 * result.attribution.revisit_fraction:.0f} %"),
        ("drift rate", "-" if result.attribution.drift.percent_per_m is None else
         f"{result.attribution.drift.percent_per_m:.2f} %/m, {result.attribution.drift.deg_per_m:.3f} deg/m"
         + ("" if result.attribution.drift.noise_floor_m is None else
            f" (above a per-frame floor of {100 * result.attribution.drift.noise_floor_m:.1f} cm, "
            f"{result.attribution.drift.noise_floor_deg:.2f} deg)")),
        ("MME / MPV", f"{result.entropy.mme:.3f} / {result.entropy.mpv_m2:.2e} m^2 (r = {result.entropy.radius_m:g} m)"),
    ]
    if result.revisits is not None and result.revisits.config.enabled:
        rows.append(("revisit check", _revisit_row(result.revisits)))
    if result.trajectory is not None:
        tr = result.trajectory
        n_gt, n_all = int(tr.get("n_poses", 0)), int(data.get("n_frames", 0))
        over = f" (over {n_gt} of the {n_all} frames: the others have no ground truth)" if 0 < n_gt < n_all else ""
        rows.append(("ATE / RPE", f"{100 * tr['ate_rmse_m']:.2f} cm / {100 * tr['rpe_trans_rmse_m']:.2f} cm, "
                                  f"{tr['rpe_rot_rmse_deg']:.3f} deg{over}"))  # trial 27 W6: say when it is a part
    if other is not None:  # with its own coverage verdict, and the frames it is over when they differ (trial 21 W5)
        cmp = data["comparison"]
        value = f"{1000 * other.smearing_score_m:.2f} mm"
        if cmp["smearing_score_valid"] is False:
            value = f"cannot judge ({value})"
        if not cmp["same_frames"]:
            value += (f"; over the {cmp['n_frames']} frames revision {other.revision} places, revision "
                      f"{result.revision}'s over its {data['n_frames']}: not a before / after of one map")
        rows.append((f"smearing score, revision {other.revision}", value))
    if result.verification is not None:
        ver = data["double_wall"]["verified"]
        rows.append(("regions confirmed (Open3D)", f"{ver['regions_confirmed']} / {ver['regions_checked']}; "
                                                   f"{ver['voxels_unconfirmed']} flagged voxels unconfirmed, "
                                                   f"{ver['regions_local']} regions local"))
        rows.append(("flagged, confirmed pose errors", f"{100 * ver['fraction_pose']:.2f} % of evaluated voxels"))
    ch = result.session_changes
    if result.session_changes_skipped is not None:
        rows.append(("session changes", f"not judged: {result.session_changes_skipped}"))
    if ch is not None:
        kinds = ch.to_json()["kinds"]
        verdicts = [v for v, _ in result.double_wall_verdicts()]
        rows.append(("session changes", f"{len(ch.regions)} regions ({kinds['added']} added, {kinds['removed']} "
                                        f"removed) between sessions {', '.join(map(str, ch.sessions))}; "
                                        f"{ch.changed_voxels} / {ch.evaluated_voxels} judged voxels changed "
                                        f"({100 * ch.changed_fraction:.2f} %)"))
        rows.append(("double-wall regions: misaligned / changed", f"{verdicts.count('double_wall')} / "
                                                                  f"{verdicts.count('changed')}"))
    cov = result.coverage
    if cov is not None:
        why = ", ".join(f"{k.replace('_', ' ')} {100 * v:.0f} %" for k, v in cov.not_evaluated_fractions().items() if v >= 0.005)
        rows.insert(3, ("surface voxels inconsistent", f"{100 * cov.fraction_inconsistent:.2f} % (doubled or smeared)"))
        rows.insert(0, ("coverage", f"{100 * cov.fraction_evaluated:.0f} % of the samples in evaluated voxels"
                                    + (f" (not: {why})" if why else "")))
        labels = {"smearing score": "smearing_score", "surface voxels doubled": "fraction_flagged",
                  "surface voxels inconsistent": "fraction_inconsistent", "drift rate": "drift_rate"}
        rows = [(k, v if k not in labels or cov.measures[labels[k]]["valid"] else f"cannot judge ({v})") for k, v in rows]
    return rows


def _session_note(result: Diagnosis, k: int) -> str:
    """A merged store's double-wall region ``k``: the sessions on each side, and ``changed`` where a change explains it."""
    if result.session_changes is None:
        return ""
    region = result.double_walls.regions[k]
    verdict, ck = result.double_wall_verdicts()[k]
    a, b = result.region_sessions(region.frames_a), result.region_sessions(region.frames_b)
    sides = ("; frames per session " + ", ".join(f"{s}: {n}" for s, n in a.items()) + " vs "
             + ", ".join(f"{s}: {n}" for s, n in b.items()))
    return sides + ("" if ck is None else f"; CHANGED (change region {ck + 1}), not a misalignment")


def _revisit_row(check: RevisitCheck) -> str:
    """The revisit check in one cell: the disagreement and the detector's range, or why there is none."""
    cfg = check.config
    if not check.judged:
        group = check.deciding_group()  # the group the verdict rests on (step and floor probes are no revisits)
        return (f"{'NOT FIT' if check.unfit else '-'} ({sum(p.counted for p in group)} of {len(group)} revisiting "
                f"frames fit the earlier map; {cfg.min_probes} needed)")
    verdict = "BEYOND the detector's range" if check.beyond_detector else "within the detector's range"
    return (f"{100 * check.disagreement_m:.1f} cm / {check.disagreement_deg:.2f} deg over {len(check.counted)} "
            f"revisiting frames ({verdict}: {100 * cfg.max_detectable_m:.0f} cm / {cfg.max_detectable_deg:g} deg)")


def _render_diagnosis(run: DiagnoseRun, store_path: Path) -> None:
    """Print the diagnose table, the "cannot judge" reasons, the first regions and the report files."""
    result = run.result
    dw, cov = result.double_walls, result.coverage
    table = Table(title=f"driftmap diagnose: {store_path} revision {result.revision}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for k, v in _diagnosis_rows(run):
        table.add_row(k, v)
    console.print(table)
    if cov is not None and not cov.valid:
        for reason in cov.reasons:
            console.print(Text(f"cannot judge: {reason}", style="yellow"))
    for k, region in enumerate(dw.regions[:5]):
        console.print(f"  region {k + 1}: {100 * region.separation_m:.1f} +- {100 * region.separation_sigma_m:.1f} cm at "
                      f"{np.round(region.center_m, 2).tolist()}, frames {region.frames_a.min()}-{region.frames_a.max()} vs "
                      f"{region.frames_b.min()}-{region.frames_b.max()}"
                      + ("" if result.verification is None else _verification_note(result.verification[k]))
                      + ("" if result.causes is None else f"; cause: {result.causes[k].cause} ({result.causes[k].explanation})")
                      + _session_note(result, k),
                      highlight=False)
    if len(dw.regions) > 5:
        console.print(f"  ... and {len(dw.regions) - 5} more double-wall regions (all in the JSON: double_wall.regions)",
                      highlight=False)
    if result.session_changes is not None:
        for k, c in enumerate(result.session_changes.regions[:5]):
            console.print(f"  changed {k + 1}: {c.kind} in session {max(c.sessions)} "
                          f"at {np.round(c.center_m, 2).tolist()}, {np.round(c.max_m - c.min_m, 2).tolist()} m, "
                          f"{c.n_voxels} voxels (surface of session {c.session_surface}, free in session "
                          f"{c.session_free})", highlight=False)
        if len(result.session_changes.regions) > 5:
            console.print(f"  ... and {len(result.session_changes.regions) - 5} more changed regions (all in the JSON: "
                          f"session_changes.regions)", highlight=False)
    if result.attribution.revisit_note:
        console.print(Text(result.attribution.revisit_note, style="yellow"))
    for name, file in run.files.items():
        console.print(f"  {name:20s} {file}")


@app.command()
def view(
    store_path: Annotated[Path, typer.Argument(metavar="STORE", help="Frame store directory.")],
    revision: Annotated[Optional[int], typer.Option("--revision", help="Revision (default: the latest).")] = None,
    color: Annotated[str, typer.Option("--color", help="frame (frame id) | revision (how far the correction moved each point) | double-wall (flagged surfaces by separation) | state (the occupied voxels of the volumetric layers by height; with --out also a free / occupied / unknown top view) | session (each session of a merged store in its own colour, tab10, listed with its colour; a store no merge made is one session, one colour)")] = "frame",
    out: Annotated[Path, typer.Option("--out", help="Folder for the PNG views when there is no display (created).")] = Path("results/view"),
    voxel_size_m: Annotated[Optional[float], typer.Option("--voxel-size-m", callback=finite, help="Display voxel size (default: 0.02 m RGB-D, 0.2 m LiDAR).")] = None,
    backend: Annotated[str, typer.Option("--backend", help="auto | window | open3d | software | rerun (auto: a window with a display, else Open3D offscreen PNGs, else software PNGs)")] = "auto",
    headless: Annotated[Optional[bool], typer.Option("--headless/--no-headless", help="Force PNG output / a window (default: detected from DISPLAY / WAYLAND_DISPLAY).")] = None,
    reference: Annotated[Optional[int], typer.Option("--reference", help="--color revision: displacement from this revision (default: the viewed revision's parent).")] = None,
    latest_state: Annotated[bool, typer.Option("--latest-state", help="--color state on a merged store (driftmap merge): the latest state of the world -- each voxel as the newest session that observed it saw it (a chair moved between sessions stands only at its new place) -- instead of every session's rays at once.")] = False,
) -> None:
    """Show the map of a revision coloured by frame, by correction displacement, by double-wall separation, by
    volumetric state or by session: an Open3D window with a display, PNG views (top + two oblique) without one."""
    from driftmap.viewer import BACKENDS, COLOR_MODES, view_store

    color = choice(color, tuple(COLOR_MODES), "--color")
    backend = choice(backend, tuple(BACKENDS), "--backend")
    if latest_state and color != "state":
        raise typer.BadParameter(f"--latest-state applies to --color state (the volumetric layers), not --color {color}",
                                 param_hint="--latest-state")
    if reference is not None and color != "revision":
        raise typer.BadParameter(f"--reference applies to --color revision (the displacement from that revision), "
                                 f"not --color {color}", param_hint="--reference")
    if voxel_size_m is not None and voxel_size_m > 1000.0:  # after 'finite', so inf says it is not finite
        raise typer.BadParameter(f"must be at most 1000 m, got {voxel_size_m}", param_hint="--voxel-size-m")
    check_output(out, "--out", folder=True)

    with open_store(store_path, reads_map=True) as store:
        warn_unmerged(store, [store.head if revision is None else revision])
        with console.status(f"preparing the {color} view of {store_path}"), writing_output(out, "--out"):
            result = view_store(store, revision=revision, color=color, out_dir=out, voxel_size_m=voxel_size_m,
                                headless=headless, backend=backend, reference_revision=reference,
                                latest_state=latest_state)
    if result.fallback_reason:
        err_console.print(Text(f"{result.fallback_reason}; used the software renderer", style="yellow"), highlight=False)
    lo, hi = result.value_range
    console.print(f"revision {result.revision}{', latest state' if latest_state else ''}, colour {result.color} "
                  f"({result.value_label}: {lo:.4g} .. {hi:.4g}), "
                  f"{result.n_points_shown:,} of {result.n_points_map:,} points (voxel {result.voxel_size_m:g} m), "
                  f"backend {result.backend}")
    if result.n_double_wall_voxels is not None:
        console.print(f"  double-wall voxels flagged: {result.n_double_wall_voxels}")
        caveats = result.colored.double_wall_caveats if result.colored is not None else ()
        if caveats:  # hostile trial 27 W7: "flagged: 0" on a map diagnose cannot judge, without a word
            console.print(Text(f"  the detector cannot judge this map, the count is no verdict: {'; '.join(caveats)} "
                               f"(driftmap diagnose also checks revisits beyond its range)", style="yellow"))
    if result.sessions is not None:
        _print_session_colours(result.sessions)
    for name, path in result.files.items():
        console.print(f"  {name:10s} {path}", highlight=False)


def _print_session_colours(sessions) -> None:  # noqa: ANN001 - tuple[SessionColor, ...]
    """``view --color session``: one line per session (its colour, frames, points shown, source store)."""
    if len(sessions) == 1 and sessions[0].source_store is None:
        s = sessions[0]
        console.print(f"  one session (not a merged store: driftmap merge makes one), one colour: session 0 "
                      f"{s.color_text}, {s.n_frames} frames", highlight=False)
        return
    console.print(f"  {len(sessions)} sessions:", highlight=False)
    for s in sessions:
        console.print(f"  session {s.session}  {s.color_text}  {s.n_frames} frames, {s.n_points_shown:,} points shown"
                      f"  from {s.source_store}", highlight=False)
    if len(sessions) > 10:
        console.print(f"  (10 colours for {len(sessions)} sessions: session k has the colour of session k % 10)",
                      highlight=False)


MAX_STEP_M = 1e8
"""``perturb --step-m``: at most this long (poses beyond ``geometry.MAX_TRANSLATION_M`` are refused by every reader)."""
MIN_DIRECTION_NORM = 1e-9
"""``perturb --drift-direction`` / ``--drift-axis``: shorter vectors are no direction."""


@app.command()
def perturb(
    poses_in: Annotated[Path, typer.Argument(metavar="POSES_IN", help="Pose file to perturb.")],
    poses_out: Annotated[Path, typer.Argument(metavar="POSES_OUT", help="Perturbed pose file (same format; of an EuRoC CSV the stamp, position and quaternion columns: the velocity and bias columns would be the unperturbed ones, so they are left out).")],
    format: Annotated[str, typer.Option("--format", help="tum | kitti | euroc")] = "tum",
    step_frame: Annotated[Optional[int], typer.Option("--step-frame", min=0, help="Row index of the first frame after the step (KITTI: = frame_id).")] = None,
    step_m: Annotated[Optional[str], typer.Option("--step-m", help="Translation step 'x,y,z' (m, world frame).")] = None,
    step_deg: Annotated[Optional[str], typer.Option("--step-deg", help="Rotation step 'rx,ry,rz' (deg, world-frame rotation vector about the step frame's sensor origin; at most 360 deg long).")] = None,
    drift_percent_per_m: Annotated[float, typer.Option("--drift-percent-per-m", callback=finite_within(-100.0, 100.0, "% of the path"), help="Translation drift (% of the path travelled).")] = 0.0,
    drift_direction: Annotated[str, typer.Option("--drift-direction", help="World direction of the translation drift 'x,y,z'.")] = "1,0,0",
    drift_deg_per_m: Annotated[float, typer.Option("--drift-deg-per-m", callback=finite_within(-360.0, 360.0, "deg per m"), help="Rotation drift (deg per m travelled).")] = 0.0,
    drift_axis: Annotated[str, typer.Option("--drift-axis", help="World axis of the rotation drift 'x,y,z' (through the first position).")] = "0,0,1",
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing POSES_OUT; without it an existing file is refused.")] = False,
) -> None:
    """Write a perturbed copy of a trajectory: a translation/rotation step at a frame and/or a linear drift."""
    from driftmap.diagnostics.perturb import MAX_STEP_DEG, PosePerturbation, parse_vector, perturb_pose_file
    from driftmap.errors import ConfigError

    check_output(poses_out, "POSES_OUT")
    refuse_output_on_input(poses_out, "POSES_OUT", [(poses_in, "POSES_IN")])
    refuse_existing(poses_out, "POSES_OUT", overwrite)
    if (step_m is not None or step_deg is not None) and step_frame is None:
        raise ConfigError("--step-m / --step-deg need --step-frame")
    if step_frame is not None and step_m is None and step_deg is None:
        raise ConfigError("--step-frame needs --step-m and/or --step-deg")
    if step_m is None and step_deg is None and not drift_percent_per_m and not drift_deg_per_m:
        raise ConfigError("nothing to perturb: give a step (--step-frame with --step-m/--step-deg) or a drift")
    for text, flag, used in ((drift_direction, "--drift-direction", drift_percent_per_m),
                             (drift_axis, "--drift-axis", drift_deg_per_m)):
        if used and not float(np.hypot.reduce(parse_vector(text, flag))) >= MIN_DIRECTION_NORM:  # no overflow at 1e300
            raise ConfigError(f"{flag}: a drift needs a non-zero direction (length >= {MIN_DIRECTION_NORM:g}), got "
                              f"{text!r}")
    step_vec = None if step_m is None else parse_vector(step_m, "--step-m")
    if step_vec is not None and float(np.linalg.norm(step_vec)) > MAX_STEP_M:
        raise ConfigError(f"--step-m: a step of {float(np.linalg.norm(step_vec)):g} m would put poses where no pose "
                          f"file reader takes them (at most {MAX_STEP_M:g} m)")
    rot_vec = None if step_deg is None else parse_vector(step_deg, "--step-deg")
    if rot_vec is not None and float(np.hypot.reduce(rot_vec)) > MAX_STEP_DEG:  # no overflow at 1e300
        raise ConfigError(f"--step-deg: a rotation step must be within {MAX_STEP_DEG:g} deg (the length of the "
                          f"rotation vector 'rx,ry,rz'), got {step_deg!r} ({float(np.hypot.reduce(rot_vec)):g} deg; a "
                          f"unit mistake? no pose estimate jumps by more than a full turn)")
    if step_frame is not None:
        moved = step_vec is not None and any(step_vec)
        turn = 0.0 if rot_vec is None else float(np.linalg.norm(rot_vec))
        turned = turn > 0 and abs(turn - 360.0 * round(turn / 360.0)) > 1e-9
        if not moved and not turned and not drift_percent_per_m and not drift_deg_per_m:
            raise ConfigError("nothing to perturb: the step is zero" + (f" (a rotation of {turn:g} deg is none)"
                                                                       if turn else ""))
    perturbation = PosePerturbation(
        step_index=step_frame, step_m=step_vec, step_deg=rot_vec,
        drift_percent_per_m=drift_percent_per_m, drift_direction=parse_vector(drift_direction, "--drift-direction"),
        drift_deg_per_m=drift_deg_per_m, drift_axis=parse_vector(drift_axis, "--drift-axis"),
    )
    result = perturb_pose_file(poses_in, poses_out, perturbation, format=choice(format, ("tum", "kitti", "euroc"), "--format"))
    console.print(f"wrote {len(result)} perturbed poses to {poses_out}")
