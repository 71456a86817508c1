"""The README's Python quick start runs as written (on a real 7-Scenes frame)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
from PIL import Image

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_quick_start_runs(sevenscenes_dir: Path, capsys) -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python quick start"
    code = blocks[0]
    assert len(code.strip().splitlines()) <= 25
    cwd = os.getcwd()
    os.chdir(sevenscenes_dir)
    try:
        exec(compile(code, str(README), "exec"), {"__name__": "readme"})
    finally:
        os.chdir(cwd)
    out = capsys.readouterr().out
    # the back-projected cloud: every pixel with 0.2 m <= depth < 4 m (the README's range), counted here from the PNG
    # (frame 0: 273943 of 307200; the other 33257 read 0)
    depth_mm = np.asarray(Image.open(sevenscenes_dir / "frame-000000.depth.png")).astype(np.int64)
    expected = int(np.count_nonzero((depth_mm >= 200) & (depth_mm < 4000)))
    first = re.search(r"^\((\d+), 3\) \{", out, re.M)
    assert first, out
    assert expected > 0 and int(first.group(1)) == expected, out
    # the downsampled frame: fewer points, none lost from the count (frame 0: 253324 removed, 20619 left)
    second = re.search(r"^(\d+) points removed; \((\d+), 3\)$", out, re.M)
    assert second, out
    removed, left = int(second.group(1)), int(second.group(2))
    assert 0 < left < expected and removed > 0
