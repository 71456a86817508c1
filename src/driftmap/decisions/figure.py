"""The report figure: the decisions on the map's top view (free / occupied / unknown of the layers in a height
band), coloured by outcome, with the decisions a comparison flipped ringed and named."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from driftmap.decisions.query_file import CollisionQuery, ExploreQuery, GraspQuery
from driftmap.decisions.records import OK_DECISIONS, UNKNOWN_DECISIONS, DecisionSet

if TYPE_CHECKING:
    from driftmap.decisions.compare import Comparison
    from driftmap.volume.layers import VolumeLayers

BAND_M = (0.05, 1.8)
"""Heights (world z, m) the top view summarises: occupied where any voxel of a column in the band is."""
COLOURS = {"ok": "#2ca02c", "unknown": "#ff9f1c", "fail": "#d62728"}


def top_view(layers: VolumeLayers, band_m: tuple[float, float] = BAND_M) -> tuple[np.ndarray, list[float]]:
    """An RGB image (y up) of the layers' columns in the band: occupied dark, free light, unknown grey."""
    g = layers.grid
    k0 = int(np.clip(np.floor(band_m[0] / g.voxel_size_m) - g.origin_index[2], 0, g.shape[2] - 1))
    k1 = int(np.clip(np.floor(band_m[1] / g.voxel_size_m) - g.origin_index[2], k0, g.shape[2] - 1))
    states = layers.state_grid()[:, :, k0:k1 + 1]
    occupied, free = (states == 1).any(axis=2), (states == 0).any(axis=2)
    img = np.full((*occupied.shape, 3), 0.72)
    img[free] = 0.97
    img[occupied] = 0.15
    extent = [float(g.min_m[0]), float(g.max_m[0]), float(g.min_m[1]), float(g.max_m[1])]
    return np.transpose(img, (1, 0, 2)), extent


def _colour(decision: str) -> str:
    return COLOURS["ok" if decision in OK_DECISIONS else "unknown" if decision in UNKNOWN_DECISIONS else "fail"]


def write_figure(path: str | Path, decisions: DecisionSet, layers: VolumeLayers | None = None,
                 comparison: Comparison | None = None, title: str | None = None) -> Path:
    """Draw every decision at its query's place (paths as lines, regions as squares, points as dots) on the top
    view; with ``comparison`` the flipped ones ringed in black with their ids. Writes a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fig, ax = plt.subplots(figsize=(10, 9))
    if layers is not None:
        img, extent = top_view(layers)
        ax.imshow(img, origin="lower", extent=extent, interpolation="nearest")
    queries = decisions.queries.by_id()
    for d in decisions.decisions:
        q, c = queries[d.id], _colour(d.decision)
        if isinstance(q, CollisionQuery):
            ax.plot(q.path_m[:, 0], q.path_m[:, 1], "-", color=c, lw=1.2, alpha=0.8)
        elif isinstance(q, (GraspQuery, ExploreQuery)):
            lo, hi = q.extent_m()
            ax.add_patch(plt.Rectangle(lo[:2], *(hi - lo)[:2], fill=False, ec=c, lw=1.0))
        a = q.anchor_m()
        ax.plot(a[0], a[1], "o", ms=3.5, color=c)
    if comparison is not None:
        for f in comparison.flipped:
            ax.plot(f.anchor_m[0], f.anchor_m[1], "o", ms=13, mfc="none", mec="black", mew=1.6)
            ax.annotate(f"{f.id}: {f.before}->{f.after}", f.anchor_m[:2], fontsize=6, xytext=(6, 6),
                        textcoords="offset points")
        for w in comparison.a.double_walls + comparison.b.double_walls:
            ax.plot(w.center_m[0], w.center_m[1], "x", ms=9, color="purple", mew=2)
    else:
        for w in decisions.double_walls:
            ax.plot(w.center_m[0], w.center_m[1], "x", ms=9, color="purple", mew=2)
    handles = [Line2D([], [], marker="o", ls="", color=COLOURS[k], label=lab) for k, lab in
               (("ok", "free / graspable / stable / known"), ("unknown", "unknown / go_look / too_few_points"),
                ("fail", "blocked / unstable_normal / too_steep / uneven"))]
    handles.append(Line2D([], [], marker="x", ls="", color="purple", label="double wall (diagnose)"))
    if comparison is not None:
        handles.append(Line2D([], [], marker="o", ls="", mfc="none", mec="black", label="flipped"))
    ax.legend(handles=handles, loc="upper right", fontsize=7)
    rep = decisions.representation
    ax.set_title(title or f"{len(decisions)} decisions, revision {rep.revision} of {Path(rep.store).name}"
                 + ("" if comparison is None else f"; {len(comparison.flipped)} flipped since "
                    f"revision {comparison.a.representation.revision}"), fontsize=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
