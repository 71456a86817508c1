"""Figures a person looks at (matplotlib, headless ``Agg`` backend)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from driftmap.map.fusion import FusedCloud  # noqa: E402


def top_view(
    path: str | Path,
    panels: Sequence[tuple[str, FusedCloud]],
    *,
    z_range_m: tuple[float, float] | None = None,
    trajectories: Sequence[NDArray[np.float64] | None] | None = None,
    max_points: int = 200_000,
    title: str | None = None,
) -> Path:
    """Side-by-side top views (x right, y up) of maps, coloured by the frame that observed each point.

    ``z_range_m`` keeps a horizontal slice (e.g. above the floor and below the ceiling) so walls show as
    lines; a doubled wall shows as two lines in different colours.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, len(panels), figsize=(6.0 * len(panels), 5.2), squeeze=False)
    for i, (ax, (label, cloud)) in enumerate(zip(axes[0], panels, strict=True)):
        p, ids = cloud.points_world, cloud.frame_ids
        if z_range_m is not None:
            keep = (p[:, 2] >= z_range_m[0]) & (p[:, 2] <= z_range_m[1])
            p, ids = p[keep], ids[keep]
        if len(p) > max_points:
            pick = np.random.default_rng(0).choice(len(p), max_points, replace=False)
            p, ids = p[pick], ids[pick]
        sc = ax.scatter(p[:, 0], p[:, 1], s=0.3, c=ids, cmap="viridis", linewidths=0, rasterized=True)
        if trajectories is not None and trajectories[i] is not None:
            traj = trajectories[i]
            ax.plot(traj[:, 0], traj[:, 1], "-", color="crimson", lw=1.0, label="camera path")
            ax.legend(loc="upper right", fontsize=8)
        ax.set_title(label)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        fig.colorbar(sc, ax=ax, label="frame id", shrink=0.8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
