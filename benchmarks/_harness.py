"""Helpers shared by the ``bench_*.py`` modules: interleaved timing and correctness checks."""

from __future__ import annotations

import cProfile
import gc
import io
import pstats
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

try:
    import resource
except ImportError:  # pragma: no cover - not available on Windows
    resource = None


class CheckFailed(AssertionError):
    """A benchmark's correctness check failed; ``run.py`` then exits non-zero."""


def check(condition: bool, message: str) -> None:
    """Raise :class:`CheckFailed` unless ``condition`` holds (works under ``python -O``, unlike ``assert``)."""
    if not condition:
        raise CheckFailed(message)


def _minor_page_faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt if resource else 0


def time_per_item(
    impls: dict[str, Callable[[Any], object]], items: Sequence, *, repeats: int, warmup: int = 1
) -> dict[str, dict]:
    """Time each implementation per item, all in the same run, taking turns.

    Every repetition times one pass over all ``items`` per implementation with ``time.perf_counter``; the
    implementations take turns (the order rotates every repetition) so slow drift of the machine hits them
    alike. ``warmup`` untimed passes of every implementation over every item come first. The garbage
    collector is off while timing (as in ``timeit``).

    Returns, per implementation: median / min / max seconds per item over the repetitions, the raw samples,
    and the minor page faults per item during the timed passes (non-zero means the allocator hands memory
    back to the OS between calls and the time includes faulting it back in).
    """
    names = list(impls)
    for _ in range(warmup):
        for name in names:
            for item in items:
                impls[name](item)
    samples: dict[str, list[float]] = {name: [] for name in names}
    faults = dict.fromkeys(names, 0)
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for rep in range(repeats):
            shift = rep % len(names)
            for name in names[shift:] + names[:shift]:
                fn = impls[name]
                faults_before = _minor_page_faults()
                start = time.perf_counter()
                for item in items:
                    fn(item)
                elapsed = time.perf_counter() - start
                faults[name] += _minor_page_faults() - faults_before
                samples[name].append(elapsed / len(items))
    finally:
        if gc_was_enabled:
            gc.enable()
    return {
        name: {
            "median_s": statistics.median(s),
            "min_s": min(s),
            "max_s": max(s),
            "repeats": repeats,
            "items": len(items),
            "page_faults_per_item": faults[name] / (repeats * len(items)),
            "samples_s": s,
        }
        for name, s in samples.items()
    }


def top_functions(profile: cProfile.Profile, n: int = 10) -> list[str]:
    """The ``n`` functions of a profile that took the most time of their own, one line each."""
    stats = pstats.Stats(profile, stream=io.StringIO())
    rows = sorted(stats.stats.items(), key=lambda kv: -kv[1][2])  # by tottime
    out = []
    for (file, line, func), (_, ncalls, tottime, cumtime, _) in rows[:n]:
        where = f"{Path(file).name}:{line}" if file != "~" else "builtin"
        out.append(f"{func} ({where}) calls {ncalls} tottime {tottime:.3f} s cumtime {cumtime:.3f} s")
    return out
