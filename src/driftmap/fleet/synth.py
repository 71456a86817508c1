"""A fleet of small synthetic logs for tests, benchmarks and the docs: ``driftmap synth --fleet N OUT``.

``OUT/room-00/`` ... are synthetic room logs (:mod:`driftmap.sources.synthetic`) that differ in seed, drift rates
(yaw 0.2-1.2 deg/m, scale 0.5-2 %), the odometry's translation step (0-5 cm, at a frame in the log's middle half) and
how far the robot goes round (1.02-1.06 turns: it revisits the start), drawn from one seed; small (``frames``,
default 40, at 200 x 150 pixels) so that a batch of them runs in seconds per log. Fewer frames turn the robot
farther between frames: below about 40 the odometry starts to lose track (the room's default log has 60). ``broken`` adds logs that are broken on purpose
(``OUT/broken-00-truncated-depth/``, ...), in turn:

* ``truncated-depth``: a depth PNG in the middle cut to half its bytes (the build fails at that frame, naming it);
* ``missing-metadata``: ``synthetic.json`` removed (no format can be detected);
* ``corrupt-metadata``: ``synthetic.json`` cut short (not JSON).

OUT holds nothing but the log folders, so ``driftmap batch OUT/*`` takes them as they are.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from driftmap.errors import ConfigError
from driftmap.sources.synthetic import METADATA_FILE, SyntheticLogConfig, generate_synthetic_log

__all__ = ["BREAKAGES", "FleetLog", "fleet_log_configs", "synth_fleet"]

BREAKAGES = ("truncated-depth", "missing-metadata", "corrupt-metadata")
DEFAULT_FRAMES = 40
DEFAULT_WIDTH = 200
MAX_FLEET = 1000


@dataclass(frozen=True)
class FleetLog:
    """One log of a synthetic fleet: its folder, config and how it is broken (None: it is not)."""

    path: Path
    config: SyntheticLogConfig
    broken: str | None = None


def _camera(width: int) -> dict[str, float | int]:
    """The synthetic depth camera scaled to ``width`` pixels (4:3, the default's field of view)."""
    s = width / 320
    height = max(2, round(240 * s))
    return {"width": width, "height": height, "fx": 262.5 * s, "fy": 262.5 * s, "cx": (width - 1) / 2,
            "cy": (height - 1) / 2}


def fleet_log_configs(n: int, *, frames: int = DEFAULT_FRAMES, seed: int = 7, width: int = DEFAULT_WIDTH,
                      lidar: bool = False) -> list[SyntheticLogConfig]:
    """``n`` configs that differ in seed, drift rates, step and loop length; the same ``seed`` gives the same."""
    rng = np.random.default_rng(seed)
    configs = []
    for k in range(n):
        step = float(rng.uniform(0.0, 0.05))
        heading = float(rng.uniform(0, 2 * np.pi))
        configs.append(SyntheticLogConfig(
            seed=seed + k, n_frames=frames, lidar=lidar, **_camera(width),
            yaw_drift_deg_per_m=round(float(rng.uniform(0.2, 1.2)), 3),
            scale_drift_percent=round(float(rng.uniform(0.5, 2.0)), 3),
            step_frame=int(rng.integers(frames // 4, max(frames // 4 + 1, 3 * frames // 4))),
            step_m=(round(step * np.cos(heading), 4), round(step * np.sin(heading), 4), 0.0),
            loop_turns=round(float(rng.uniform(1.02, 1.06)), 3)))
    return configs


def _break(log: Path, how: str) -> None:
    if how == "truncated-depth":
        pngs = sorted((log / "depth").glob("*.png"))
        victim = pngs[len(pngs) // 2]
        data = victim.read_bytes()
        victim.write_bytes(data[: len(data) // 2])
    elif how == "missing-metadata":
        (log / METADATA_FILE).unlink()
    elif how == "corrupt-metadata":
        meta = log / METADATA_FILE
        meta.write_bytes(meta.read_bytes()[:200])
    else:
        raise ConfigError(f"unknown breakage {how!r}; one of {', '.join(BREAKAGES)}")


def _names(n: int, broken: int) -> tuple[list[str], list[str]]:
    width = max(2, len(str(max(n, broken) - 1)))
    return ([f"room-{k:0{width}d}" for k in range(n)],
            [f"broken-{k:0{width}d}-{BREAKAGES[k % len(BREAKAGES)]}" for k in range(broken)])


def _clear(out: Path, names: list[str], overwrite: bool) -> None:
    """``out`` new or empty; with ``overwrite``, an earlier fleet's log folders (room-*, broken-*) are removed."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: is a file, not a folder for a fleet of logs")
    entries = sorted(out.iterdir()) if out.is_dir() else []
    if not entries:
        return
    ours = all(e.is_dir() and e.name.startswith(("room-", "broken-")) for e in entries)
    if not ours:
        raise ConfigError(f"{out}: holds other files than a synthetic fleet's logs; give a new or empty folder")
    if not overwrite:
        raise ConfigError(f"{out}: a synthetic fleet exists: pass --overwrite to replace it (or give a new folder)")
    for entry in entries:
        shutil.rmtree(entry)


def synth_fleet(out: str | Path, n: int, *, broken: int = 0, frames: int = DEFAULT_FRAMES, seed: int = 7,
                width: int = DEFAULT_WIDTH, lidar: bool = False, overwrite: bool = False,
                progress: Callable[[int, int], None] | None = None) -> list[FleetLog]:
    """Write ``n`` synthetic room logs and ``broken`` broken ones into ``out`` (see the module docstring); returns
    them in order. ``progress(done, total)`` is called after each log."""
    if not 0 <= n <= MAX_FLEET or not 0 <= broken <= MAX_FLEET or n + broken < 1:
        raise ConfigError(f"a synthetic fleet has 1 to {MAX_FLEET} logs and at most {MAX_FLEET} broken ones, "
                          f"got {n} and {broken}")
    out = Path(out)
    good_names, broken_names = _names(n, broken)
    _clear(out, good_names + broken_names, overwrite)
    configs = fleet_log_configs(n + broken, frames=frames, seed=seed, width=width, lidar=lidar)
    logs = []
    for k, name in enumerate(good_names + broken_names):
        how = None if k < n else BREAKAGES[(k - n) % len(BREAKAGES)]
        path = generate_synthetic_log(out / name, configs[k])
        if how is not None:
            _break(path, how)
        logs.append(FleetLog(path, configs[k], how))
        if progress is not None:
            progress(k + 1, n + broken)
    return logs
