"""Where the map view reads sensor points from: a frame's own array, or a segment file read piece by piece with
``pread`` (one descriptor per reading thread)."""

from __future__ import annotations

import mmap
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import StoreError


@dataclass
class SensorBuffer:
    """Where sensor points come from: a flat float32 array (``_start``/``_stride`` in floats), or a segment
    file read with ``pread`` (``path`` set, ``flat`` None: ``_start`` is a byte offset, ``_stride`` in floats)."""

    flat: NDArray[np.float32] | None
    mm: mmap.mmap | None = None
    path: Path | None = None


class OpenFiles:
    """``n`` read-only descriptors of one file, one per reading thread (each its own read-ahead state, so a
    thread's sequential reads stay sequential for the kernel even while another thread reads elsewhere),
    closed on exit."""

    def __init__(self, path: Path, n: int):
        opened: list[int] = []
        try:
            for _ in range(n):
                opened.append(os.open(path, os.O_RDONLY))
                if hasattr(os, "posix_fadvise"):
                    os.posix_fadvise(opened[-1], 0, 0, os.POSIX_FADV_SEQUENTIAL)
        except OSError as exc:
            for fd in opened:
                os.close(fd)
            raise StoreError(f"{path}: cannot open the segment to read sensor points: {exc}") from exc
        self.fds = np.array(opened, np.int32)

    def __enter__(self) -> NDArray[np.int32]:
        return self.fds

    def __exit__(self, *exc: object) -> None:
        for fd in self.fds:
            os.close(int(fd))
