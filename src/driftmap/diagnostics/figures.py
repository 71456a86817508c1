"""The figures of a diagnosis (matplotlib, headless ``Agg`` backend): the map's top view with the flagged double
walls, the per-frame disagreement over time with the change points, and a before/after comparison of the
smearing scores; :func:`write_report` writes them as PNG files."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from driftmap.diagnostics.diagnosis import Diagnosis  # noqa: E402
from driftmap.diagnostics.samples import PlacedCloud  # noqa: E402
from driftmap.frame import SensorKind  # noqa: E402


def _up_axis(placed: PlacedCloud) -> NDArray[np.float64]:
    """World 'up' from how the sensors were held: minus the mean camera y axis (image down) for depth cameras,
    the mean sensor z axis for LiDAR."""
    kinds = placed.samples.sensor_kinds
    lidar = sum(k is SensorKind.LIDAR for k in kinds) > len(kinds) / 2
    R = placed.poses[:, :3, :3]
    up = R[:, :, 2].mean(axis=0) if lidar else -R[:, :, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])


def _plane_axes(up: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - up * (helper @ up)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def plot_double_walls(path: str | Path, diagnosis: Diagnosis, *, max_points: int = 150_000, title: str | None = None) -> Path:
    """Top view of the map (grey) with every flagged surface group coloured by its separation (cm)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    placed, walls = diagnosis.placed, diagnosis.double_walls
    up = _up_axis(placed)
    e1, e2 = _plane_axes(up)
    P = placed.points_world
    if len(P) > max_points:
        P = P[np.random.default_rng(0).choice(len(P), max_points, replace=False)]
    fig, ax = plt.subplots(figsize=(8.0, 7.0))
    ax.scatter(P @ e1, P @ e2, s=0.2, c="0.75", linewidths=0, rasterized=True)
    centers, seps, sizes = [], [], []
    for s in walls.scales:
        sel = s.flagged
        centers.append(s.centers_m[sel])
        seps.append(np.abs(s.separation_m[sel]) * 100)
        sizes.append(np.full(int(sel.sum()), s.voxel_size_m))
    if centers and sum(len(c) for c in centers):
        C, S, Z = np.concatenate(centers), np.concatenate(seps), np.concatenate(sizes)
        order = np.argsort(-Z)  # large voxels first, small ones on top
        sc = ax.scatter(C[order] @ e1, C[order] @ e2, c=S[order], s=8 + 120 * Z[order] / Z.max(), cmap="inferno_r",
                        vmin=0, vmax=max(float(np.percentile(S, 95)), 1.0), edgecolors="k", linewidths=0.3)
        fig.colorbar(sc, ax=ax, label="double-wall separation (cm)", shrink=0.8)
        for k, region in enumerate(walls.regions[:8]):
            ax.annotate(f"{k + 1}", (region.center_m @ e1, region.center_m @ e2), fontsize=8, color="navy",
                        xytext=(4, 4), textcoords="offset points")
    traj = placed.origins_world
    ax.plot(traj @ e1, traj @ e2, "-", color="tab:blue", lw=0.8, alpha=0.7, label="sensor path")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    ax.grid(alpha=0.3)
    ax.set_title(title or (f"revision {diagnosis.revision}: {walls.voxels_flagged} of {walls.voxels_evaluated} surface "
                           f"voxels doubled ({100 * walls.fraction_flagged:.1f} %), smearing "
                           f"{1000 * walls.smearing_score_m:.1f} mm"), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_frame_disagreement(path: str | Path, diagnosis: Diagnosis, *, title: str | None = None) -> Path:
    """Per-frame disagreement with the map and jump against the frames before, over time, with change points."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    at = diagnosis.attribution
    cfg = at.config
    x = at.frame_ids
    est = at.disagreement.estimated(cfg.min_correspondences)
    obs = at.disagreement.observable(cfg.min_correspondences)
    fig, axes = plt.subplots(2, 1, figsize=(10.0, 6.0), sharex=True)
    step = at.split.step_norm_m
    step_label = f"step: {cfg.split_window} frames from here vs the {cfg.split_window} before"
    for ax, d, j, unit, scale, label in (
            (axes[0], at.disagreement.translation_norm_m, step, "mm", 1000.0, step_label),
            (axes[1], at.disagreement.rotation_norm_deg, at.jumps.rotation_norm_deg, "deg", 1.0, f"jump vs the {cfg.window} frames before")):
        ax.plot(x[est], d[est] * scale, ".-", ms=3, lw=0.8, color="tab:blue", label="disagreement with the map")
        ax.plot(x[est & ~obs], d[est & ~obs] * scale, "x", ms=4, color="0.5", label="(a direction unobservable)")
        ax.plot(x, j * scale, "-", lw=0.8, color="tab:orange", label=label)
        for cp in at.change_points:
            ax.axvline(cp.frame_id, color="crimson", lw=1.0, alpha=0.8)
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
    if at.change_points:
        axes[0].plot([], [], color="crimson", label="change point")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[1].legend(loc="upper right", fontsize=8)
    axes[1].set_xlabel("frame id")
    drift = at.drift
    rate = ("no revisit: drift invisible" if drift.percent_per_m is None
            else f"drift ~{drift.percent_per_m:.2f} %/m, {drift.deg_per_m:.3f} deg/m")
    axes[0].set_title(title or f"revision {diagnosis.revision}: per-frame disagreement; {len(at.change_points)} change "
                               f"points; {rate}; revisited {100 * at.revisit_fraction:.0f} %", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_score_comparison(path: str | Path, diagnoses: dict[str, Diagnosis], *, title: str | None = None) -> Path:
    """Smearing score per voxel scale and overall, and the share of doubled voxels, for several revisions
    (e.g. before / after a correction)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = list(diagnoses)
    scales = sorted({s for d in diagnoses.values() for s in d.double_walls.score_per_scale_m})
    groups = [f"{s:g} m" for s in scales] + ["overall"]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11.0, 4.2), gridspec_kw={"width_ratios": [3, 1]})
    width = 0.8 / max(len(labels), 1)
    for k, label in enumerate(labels):
        d = diagnoses[label].double_walls
        vals = [d.score_per_scale_m.get(s, float("nan")) * 1000 for s in scales] + [d.smearing_score_m * 1000]
        ax.bar(np.arange(len(groups)) + k * width, vals, width, label=label)
        bar = ax2.bar(k, 100 * d.fraction_flagged, 0.6, label=label, color=f"C{k}")
        ax2.bar_label(bar, fmt="%.2f %%", fontsize=8)
    ax.set_xticks(np.arange(len(groups)) + width * (len(labels) - 1) / 2, groups)
    ax.set_ylabel("smearing score (mm)")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    ax2.set_xticks(range(len(labels)), [label.replace(" (", "\n(") for label in labels], fontsize=7)
    ax2.set_ylabel("surface voxels doubled (%)")
    ax2.grid(axis="y", alpha=0.3)
    fig.suptitle(title or "smearing before / after", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_report(out_dir: str | Path, diagnosis: Diagnosis, *, compare: dict[str, Diagnosis] | None = None) -> dict[str, Path]:
    """The PNG figures of a diagnosis (and, with ``compare``, the before/after score figure)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "double_walls": plot_double_walls(out / f"double_walls_rev{diagnosis.revision}.png", diagnosis),
        "frame_disagreement": plot_frame_disagreement(out / f"frame_disagreement_rev{diagnosis.revision}.png", diagnosis),
    }
    if compare:
        files["score_comparison"] = plot_score_comparison(out / "smearing_before_after.png", compare)
    return files
