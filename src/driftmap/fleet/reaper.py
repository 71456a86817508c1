"""Leaving no process behind: the processes an embedded Ray starts (GCS, raylet, its agents and workers) are all
descendants of this one; an interrupted ``ray.init`` or a shutdown racing with the raylet can leave the agents the
raylet started re-parented to PID 1, running for good.

:func:`adopt_orphans` makes this process a *child subreaper* (Linux ``prctl(PR_SET_CHILD_SUBREAPER)``): a
descendant whose parent dies is re-parented to this process instead of PID 1, so it stays a descendant.
:func:`stop_descendants` then terminates (SIGTERM, then SIGKILL after a grace period) and reaps every descendant
still running. Elsewhere than Linux both do nothing (the embedded Ray's own shutdown is all there is).

Neither runs when this process is killed outright (SIGKILL, the OOM killer): then Ray's processes outlived it (hostile
trial 17 W11). :func:`start_watchdog` starts a small process that keeps a list of this process's descendants and, when
this process is gone, stops them (and their own descendants), as :func:`stop_descendants` would have.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

__all__ = ["Watchdog", "adopt_orphans", "descendants", "interrupts_deferred", "is_subreaper", "start_watchdog",
           "stop_descendants"]

logger = logging.getLogger(__name__)

PR_SET_CHILD_SUBREAPER = 36
PR_GET_CHILD_SUBREAPER = 37
GRACE_S = 2.0
"""How long descendants get to stop after SIGTERM before SIGKILL."""
WATCH_PERIOD_S = 0.5
"""How often the watchdog lists the watched process's descendants and checks that it is still there."""


def adopt_orphans(adopt: bool = True) -> bool:
    """Make this process the child subreaper of its descendants (``adopt=False``: no longer); True if the call
    succeeded (Linux only)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_CHILD_SUBREAPER, int(adopt), 0, 0, 0) == 0
    except (OSError, AttributeError):  # no prctl here
        return False


def is_subreaper() -> bool:
    """True when this process is already a child subreaper (set by whoever runs it, e.g. a container's init)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        flag = ctypes.c_int(0)
        return ctypes.CDLL(None, use_errno=True).prctl(PR_GET_CHILD_SUBREAPER, ctypes.byref(flag), 0, 0, 0) == 0 \
            and flag.value != 0
    except (OSError, AttributeError):
        return False


def _parents() -> dict[int, int]:
    """pid -> parent pid of every process readable in /proc."""
    parents = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        fields = _stat_fields(int(entry))
        if fields is not None and len(fields) > 1:  # None: gone meanwhile
            parents[int(entry)] = int(fields[1])
    return parents


def descendants(pid: int | None = None, prune: frozenset[int] | set[int] = frozenset()) -> list[int]:
    """The pids of every descendant of ``pid`` (this process by default), leaving out those in ``prune`` and their
    own descendants; [] where /proc is missing."""
    root = os.getpid() if pid is None else pid
    if not os.path.isdir("/proc"):
        return []
    children: dict[int, list[int]] = {}
    for child, parent in _parents().items():
        children.setdefault(parent, []).append(child)
    found, stack = [], [root]
    while stack:
        for child in children.get(stack.pop(), []):
            if child in prune:
                continue
            found.append(child)
            stack.append(child)
    return found


def _reap(pids: list[int]) -> None:
    """Collect the exit status of those of ``pids`` that are children of this process and have ended (orphans
    adopted as a subreaper become zombies); never ``waitpid(-1)``, which would take a child another part of the
    program waits for."""
    for pid in pids:
        with contextlib.suppress(ChildProcessError, OSError):
            os.waitpid(pid, os.WNOHANG)


def _signal_all(pids: list[int], sig: int) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, sig)


def stop_descendants(keep: frozenset[int] | set[int] = frozenset(), grace_s: float = GRACE_S) -> int:
    """Terminate every descendant of this process still running except those in ``keep`` and their own descendants
    (pass the descendants it had before the embedded Ray started: a cluster or a helper started earlier is not
    this Ray's) -- SIGTERM, then SIGKILL after ``grace_s`` -- and reap them; the number that had to be stopped."""
    if not sys.platform.startswith("linux"):
        return 0

    def running() -> list[int]:
        found = descendants(prune=keep)
        _reap(found)
        return [p for p in found if _alive(p)]

    left = running()
    if not left:
        return 0
    logger.info("stopping %d process(es) the embedded Ray left running: %s", len(left), left)
    _signal_all(left, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while (stubborn := running()) and time.monotonic() < deadline:
        time.sleep(0.05)
    if stubborn:
        _signal_all(stubborn, signal.SIGKILL)
        for _ in range(40):
            if not running():
                break
            time.sleep(0.05)
    return len(left)


def _stat_fields(pid: int) -> list[bytes] | None:
    """The fields of ``/proc/PID/stat`` after the name (field 3 on: the state first), None when gone. The name
    (field 2) is in parentheses and may hold spaces or ')': the fields after its last ')'."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return None
    return stat[stat.rfind(b")") + 2:].split()


def _alive(pid: int) -> bool:
    """True unless ``pid`` has ended (a zombie has ended: it only waits to be reaped)."""
    fields = _stat_fields(pid)
    return bool(fields) and fields[0] != b"Z"


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold back Ctrl-C (SIGINT) while the block runs -- the clean-up after a first Ctrl-C, which a second one must
    not cut short -- and raise ``KeyboardInterrupt`` after it if one came. Outside the main thread, nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    seen = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: seen.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if seen:
        raise KeyboardInterrupt


def _start_time(pid: int) -> int | None:
    """A process's start time (clock ticks after boot, /proc field 22): a pid and it name one process, even after
    the pid is reused. None: gone."""
    fields = _stat_fields(pid)
    return int(fields[19]) if fields is not None and len(fields) > 19 else None


def _stop(pids: Iterable[tuple[int, int | None]], grace_s: float = GRACE_S) -> int:
    """SIGTERM, then SIGKILL after ``grace_s``, the processes of ``(pid, start time)`` that are still those
    processes, with their own descendants; the number signalled."""
    own = [pid for pid, started in pids if started is not None and _start_time(pid) == started]
    targets = sorted({*own, *(d for pid in own for d in descendants(pid))})
    if not targets:
        return 0
    _signal_all(targets, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while [p for p in targets if _alive(p)] and time.monotonic() < deadline:
        time.sleep(0.05)
    _signal_all([p for p in targets if _alive(p)], signal.SIGKILL)
    return len(targets)


def watch(pid: int, keep: frozenset[int] = frozenset(), period_s: float = WATCH_PERIOD_S) -> int:
    """The watchdog's loop (:func:`start_watchdog`): list ``pid``'s descendants (less ``keep``, this watchdog, and
    their own descendants) every ``period_s``; when ``pid`` is gone, stop the last ones listed. Returns how many it
    stopped (0 when ``pid`` ends with none left running)."""
    me = os.getpid()
    started = _start_time(pid)
    known: dict[int, int | None] = {}
    while started is not None and _start_time(pid) == started and os.getppid() == pid:
        known = {d: _start_time(d) for d in descendants(pid, prune={*keep, me})}
        time.sleep(period_s)
    return _stop(known.items())


@dataclass
class Watchdog:
    """A running :func:`watch` process (:func:`start_watchdog`); :meth:`stop` ends it without it stopping anything."""

    process: subprocess.Popen | None

    @property
    def pid(self) -> int | None:
        return None if self.process is None else self.process.pid

    def stop(self) -> None:
        if self.process is None:
            return
        with contextlib.suppress(ProcessLookupError, PermissionError):
            self.process.kill()  # SIGKILL: it stops nothing then
        with contextlib.suppress(subprocess.TimeoutExpired, OSError):
            self.process.wait(timeout=5)
        self.process = None


def start_watchdog(keep: Iterable[int] = ()) -> Watchdog:
    """Start a process that stops this process's descendants (except ``keep`` and theirs) once this process is
    gone without stopping them itself (killed outright). Outside Linux, or when it cannot start, a watchdog that
    does nothing."""
    if not sys.platform.startswith("linux") or not os.path.isdir("/proc"):
        return Watchdog(None)
    try:
        # this file run as a script (isolated: the standard library only, no driftmap import, ~30 ms)
        process = subprocess.Popen([sys.executable, "-I", os.path.abspath(__file__), str(os.getpid()),
                                    *map(str, sorted(keep))], stdin=subprocess.DEVNULL,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   start_new_session=True)  # a terminal's Ctrl-C is the batch's to handle
    except OSError as exc:
        logger.warning("no watchdog for the embedded Ray (%s): if this process is killed outright, its Ray "
                       "processes keep running", exc)
        return Watchdog(None)
    return Watchdog(process)


if __name__ == "__main__":  # the watchdog process: python -I reaper.py PID [KEEP...]
    watch(int(sys.argv[1]), frozenset(int(a) for a in sys.argv[2:]))
