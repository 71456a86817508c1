"""Running the command line as a user does, for the tests of the hostile-input trials."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def run_cli(*args: object, cwd: Path | None = None, env: dict | None = None,
            timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -m driftmap.cli ARGS`` in a subprocess (a wide terminal, so messages are not wrapped)."""
    return subprocess.run([sys.executable, "-m", "driftmap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env={**os.environ, "COLUMNS": "200", **(env or {})})


def one_error(out: subprocess.CompletedProcess) -> str:
    """The one-line error of a refused command (exit 1 or 2, no traceback), whitespace joined."""
    assert out.returncode in (1, 2), (out.returncode, out.stdout[-1500:], out.stderr[-1500:])
    assert "Traceback" not in out.stderr and "Traceback" not in out.stdout
    return " ".join(out.stderr.split())


def small_sevenscenes_log(sevenscenes_dir: Path, log: Path, n_frames: int) -> Path:
    """A 7-Scenes folder of the first ``n_frames`` frames (depth images, poses, the intrinsics file) at ``log``."""
    import shutil

    log.mkdir(parents=True)
    for i in range(n_frames):
        for kind in ("depth.png", "pose.txt"):
            shutil.copy(sevenscenes_dir / f"frame-{i:06d}.{kind}", log)
    shutil.copy(sevenscenes_dir / "camera-intrinsics.txt", log)
    return log
