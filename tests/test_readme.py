"""The README's Python quick start runs as written (on a real 7-Scenes frame)."""

from __future__ import annotations

import os
import re
from pathlib import Path

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
    assert re.search(r"\(\d+, 3\)", out)
