"""Running a batch on Ray: one task per log (:func:`driftmap.fleet.task.run_log`), an embedded local Ray by default,
an existing cluster by address.

* **Embedded** (no address): ``ray.init(num_cpus=workers x threads)`` in this process (no server to install or
  start); ``workers`` logs run at once, each with ``threads`` registration threads, so the machine's CPUs are used
  and not oversubscribed (default: one worker per CPU, one thread each). A Ray this process had started already is
  used as it is (and left running).
* **Cluster** (``ray_address``, e.g. ``ray://head:10001`` or ``auto``): ``ray.init(address=...)``; each task asks
  for ``threads`` CPUs (default 1), so Ray places as many at once as the cluster has CPUs; ``workers`` limits it.

Faults: a log whose task fails is a ``failed`` row (its typed error) and the others go on; a task whose worker dies
(killed, out of memory, a lost node) is retried up to :data:`MAX_RETRIES` times, then its row says so. ``resume``
keeps each log whose ``DIR/<name>/`` is complete and was made with the same config (a ``skipped`` row with the
recorded figures) and runs the others. A ``KeyboardInterrupt`` (Ctrl-C) cancels the running tasks (each removes its
partial folder), writes ``fleet.json`` with the logs that finished and the names of those that did not
(``interrupted``), and is raised again: only complete log folders are left.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from driftmap.errors import ConfigError, DriftmapError
from driftmap.fleet.config import BatchConfig, config_hash
from driftmap.fleet.folders import (
    clean_temp,
    completed_result,
    input_fingerprint,
    prepare_out_dir,
    release_batch_lock,
)
from driftmap.fleet.inputs import LogSpec
from driftmap.fleet.reaper import (
    adopt_orphans,
    descendants,
    interrupts_deferred,
    is_subreaper,
    start_watchdog,
    stop_descendants,
)
from driftmap.fleet.report import write_fleet_json, write_fleet_report
from driftmap.fleet.task import LogHook, empty_row, failed_row, run_log

__all__ = ["MAX_RETRIES", "FleetProgress", "FleetResult", "plan_workers", "require_ray", "run_batch"]

MAX_RETRIES = 2
"""A log whose worker process dies is run again at most this many times."""
CANCEL_WAIT_S = 20.0
"""After Ctrl-C, how long the running tasks get to stop and remove their partial folders before they are killed."""
INSTALL_HINT = "pip install 'driftmap[fleet]'"
AUTH_MODE_VAR = "RAY_AUTH_MODE"
DEFAULT_TOKEN = Path.home() / ".ray" / "auth_token"
"""Where ``ray start`` keeps the token of a cluster with token authentication (Ray's default)."""

logger = logging.getLogger(__name__)


@dataclass
class FleetProgress:
    """Where a batch is: logs done (ok or skipped), failed, running, of ``total``; ``last`` the row just finished."""

    total: int
    done: int = 0
    failed: int = 0
    skipped: int = 0
    running: int = 0
    last: dict[str, Any] | None = None


ProgressCallback = Callable[[FleetProgress], None]


@dataclass
class FleetResult:
    """What a batch did: its rows (input order), the workers and threads it ran with, the files it wrote."""

    rows: list[dict[str, Any]]
    workers: int
    threads: int
    ray_address: str | None
    out_dir: Path
    files: dict[str, Path] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def failed(self) -> list[dict[str, Any]]:
        return [r for r in self.rows if r["status"] == "failed"]


def require_ray(ray_address: str | None = None) -> Any:
    """The ``ray`` module, or a :class:`ConfigError` that says how to install it. With ``ray_address``, Ray's token
    mode is switched on first where a token is at hand (:func:`_token_mode`)."""
    if ray_address is not None:
        _token_mode()
    try:
        import ray
    except ImportError:
        raise ConfigError(f"driftmap batch runs on Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def _token_mode() -> None:
    """A cluster started by ``ray start`` (Ray >= 2.5x) asks for its token, which a driver that joins it sends only in
    token mode; Ray switches that on by itself for the clusters it starts, not for those it joins. So where a token is
    at hand (``RAY_AUTH_TOKEN``, ``~/.ray/auth_token``) and ``RAY_AUTH_MODE`` is not set, it is set to ``token``
    (before Ray reads its configuration, or re-read as Ray itself does)."""
    if AUTH_MODE_VAR in os.environ or not (os.environ.get("RAY_AUTH_TOKEN") or DEFAULT_TOKEN.is_file()):
        return
    os.environ[AUTH_MODE_VAR] = "token"
    if "ray" in sys.modules:
        with contextlib.suppress(Exception):
            from ray._raylet import Config

            Config.initialize("")


MAX_WORKERS_PER_CPU = 4
"""Embedded Ray: at most this many logs at once per CPU of this machine (``--workers`` beyond is refused)."""


def plan_workers(workers: int | None, threads: int | None, ray_address: str | None,
                 cpus: int | None = None) -> tuple[int, int]:
    """``(workers, threads per log)``: on this machine, ``workers`` (default: one per CPU) x ``threads`` (default:
    the CPUs shared by the workers) stays within its CPUs; on a cluster, threads default to 1 and workers to the
    cluster's CPUs (``cpus``)."""
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers: must be >= 1, got {workers}")
    cpus = cpus or os.cpu_count() or 1
    if ray_address is None:
        if workers is not None and workers > MAX_WORKERS_PER_CPU * cpus:
            raise ConfigError(f"--workers {workers}: this machine has {cpus} CPU{'s' if cpus > 1 else ''}; an embedded "
                              f"Ray runs at most {MAX_WORKERS_PER_CPU} logs per CPU at once "
                              f"({MAX_WORKERS_PER_CPU * cpus}: each log holds its frames in memory); give fewer "
                              f"--workers, or --ray-address for a cluster")
        w = workers or cpus
        return w, threads or max(1, cpus // w)
    t = threads or 1
    return workers or max(1, cpus // t), t


def _start_ray(ray: Any, ray_address: str | None, workers: int, threads: int) -> bool:
    """Start (or join) Ray; True if this call started it (and so stops it at the end)."""
    if ray.is_initialized():
        return False
    quiet = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR}
    if ray_address is None:
        try:
            ray.init(address="local", num_cpus=workers * threads, **quiet)  # a new Ray, even with a cluster here
        except KeyboardInterrupt:  # Ctrl-C while Ray starts: stop what it started (its agents outlive us otherwise)
            with contextlib.suppress(Exception):
                ray.shutdown()
            raise
        except Exception as exc:  # Ray raises a bare Exception ("timed out during startup"), among others
            _shutdown_quietly(ray)
            raise DriftmapError(f"Ray could not start here ({workers} workers x {threads} threads): "
                                f"{_first_line(exc)}; no log was run (a loaded or small machine: try fewer --workers, "
                                f"and check /tmp/ray/session_latest/logs)") from exc
        return True
    _probe_address(ray_address)
    try:
        ray.init(address=ray_address, **quiet)
    except (ConnectionError, ValueError, RuntimeError) as exc:
        _shutdown_quietly(ray)
        raise ConfigError(f"--ray-address {ray_address}: cannot join the Ray cluster ({_first_line(exc)}); is 'ray "
                          f"start --head' running there, and is its token in {DEFAULT_TOKEN} or RAY_AUTH_TOKEN "
                          f"here?") from exc
    except Exception as exc:  # as above
        _shutdown_quietly(ray)
        raise DriftmapError(f"--ray-address {ray_address}: Ray could not start: {_first_line(exc)}; no log was "
                            f"run") from exc
    return True


def _first_line(exc: BaseException) -> str:
    """An exception's message on one line (Ray's run to many lines): its first line, or its type."""
    lines = [line.strip() for line in str(exc).strip().splitlines() if line.strip()]
    return lines[0].rstrip(".") if lines else type(exc).__name__


PROBE_TIMEOUT_S = 5.0
"""``--ray-address HOST:PORT``: how long the cluster's port may take to accept a connection before the batch gives
up (Ray itself waits for its GCS and then keeps the batch waiting for ever)."""


def _probe_address(ray_address: str) -> None:
    """:class:`ConfigError` when nothing accepts a TCP connection at ``HOST:PORT`` (also ``ray://HOST:PORT``) within
    :data:`PROBE_TIMEOUT_S`; ``auto`` and addresses without a port are left to Ray."""
    import socket
    from urllib.parse import urlsplit

    text = ray_address if "://" in ray_address else f"tcp://{ray_address}"
    try:
        parts = urlsplit(text)
        host, port = parts.hostname, parts.port
    except ValueError:
        return
    if not host or port is None:
        return
    try:
        with socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S) as conn:
            speaks_grpc = os.environ.get("RAY_USE_TLS", "0") not in ("0", "") or _answers_http2(conn)
    except OSError as exc:
        raise ConfigError(f"--ray-address {ray_address}: nothing answers at {host}:{port} ({exc.strerror or exc}); is "
                          f"'ray start --head' running there (its GCS port, 6379 by default, or the client port "
                          f"10001 for ray://)?") from None
    if not speaks_grpc:
        raise ConfigError(f"--ray-address {ray_address}: something answers at {host}:{port}, but not Ray (its GCS and "
                          f"client ports speak gRPC); is it the dashboard (8265) or another service? Give the GCS "
                          f"port (6379 by default) or ray://HOST:10001")


HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00"
"""The HTTP/2 connection preface and an empty SETTINGS frame: a gRPC server (Ray's GCS, its client server) answers
with a SETTINGS frame of its own; an HTTP/1 server, a dashboard or anything else does not."""


def _answers_http2(conn: Any) -> bool:
    """True when the server on ``conn`` answers the HTTP/2 preface with a SETTINGS frame (frame type 4) within
    :data:`PROBE_TIMEOUT_S`."""
    import socket

    conn.settimeout(PROBE_TIMEOUT_S)
    data = b""
    try:
        conn.sendall(HTTP2_PREFACE)
        while len(data) < 9:
            chunk = conn.recv(9 - len(data))
            if not chunk:
                break
            data += chunk
    except (socket.timeout, OSError):
        return False
    return len(data) == 9 and data[3] == 0x04


def _shutdown_quietly(ray: Any) -> None:
    """Stop what a failed ``ray.init`` may have started."""
    with contextlib.suppress(Exception):
        if ray.is_initialized():
            ray.shutdown()


class _Batch:
    """The tasks of one batch in flight: submitted at most ``workers`` at a time, their rows as they finish."""

    def __init__(self, ray: Any, specs: list[LogSpec], submit: Callable[[LogSpec], Any], workers: int,
                 progress: FleetProgress, tick: ProgressCallback, rows: dict[str, dict[str, Any]]):
        self.ray, self.queue, self.submit, self.workers = ray, list(specs), submit, workers
        self.progress, self.tick, self.rows = progress, tick, rows
        self.pending: dict[Any, tuple[LogSpec, float]] = {}

    def _fill(self) -> None:
        while self.queue and len(self.pending) < self.workers:
            spec = self.queue.pop(0)
            self.pending[self.submit(spec)] = (spec, time.perf_counter())
        self.progress.running = len(self.pending)

    def _finish(self, ref: Any) -> None:
        spec, started = self.pending.pop(ref)
        try:
            row = self.ray.get(ref)
        except self.ray.exceptions.RayError as exc:  # the worker died more than MAX_RETRIES times, or Ray failed
            first = (str(exc).strip().splitlines() or [""])[0]
            row = failed_row(spec, f"{spec.input}: its Ray task failed after {MAX_RETRIES} retries: {first}",
                             type(exc).__name__, time.perf_counter() - started)
        self.rows[spec.name] = row
        self.progress.failed += row["status"] == "failed"
        self.progress.done += row["status"] != "failed"
        self.progress.last = row

    def run(self) -> None:
        self._fill()
        self.tick(self.progress)
        while self.pending:
            ready, _ = self.ray.wait(list(self.pending), num_returns=1, timeout=0.25)
            for ref in ready:
                self._finish(ref)
            self._fill()
            self.tick(self.progress)

    def cancel(self) -> list[str]:
        """Stop the tasks in flight: each gets a ``KeyboardInterrupt`` (and removes its partial folder), those still
        running after :data:`CANCEL_WAIT_S` are killed. Returns the logs that did not finish."""
        for ref in self.pending:
            self.ray.cancel(ref, force=False)
        deadline = time.monotonic() + CANCEL_WAIT_S
        while self.pending and time.monotonic() < deadline:
            ready, _ = self.ray.wait(list(self.pending), num_returns=1, timeout=0.25)
            for ref in ready:
                spec, _ = self.pending.pop(ref)
                try:
                    self.rows[spec.name] = self.ray.get(ref)  # it finished before the cancel reached it
                except (self.ray.exceptions.RayError, KeyboardInterrupt):
                    self.queue.insert(0, spec)
        for ref, (spec, _) in self.pending.items():
            self.ray.cancel(ref, force=True)
            self.queue.insert(0, spec)
        self.pending.clear()
        return [s.name for s in self.queue]


def _skipped_rows(specs: Sequence[LogSpec], config: BatchConfig, out_dir: Path) -> dict[str, dict[str, Any]]:
    """``--resume``: the logs whose folder is complete and made with this config, as ``skipped`` rows."""
    rows = {}
    for spec in specs:
        result = completed_result(out_dir / spec.name, config_hash(config, spec),
                                  expected_input=input_fingerprint(spec.input_paths()))
        if result is not None:
            rows[spec.name] = {**empty_row(spec, "skipped"), **result["row"], "status": "skipped"}
    return rows


def run_batch(specs: Sequence[LogSpec], out_dir: str | Path, config: BatchConfig | None = None, *,
              workers: int | None = None, ray_address: str | None = None, resume: bool = False,
              progress: ProgressCallback | None = None, hook: LogHook | None = None) -> FleetResult:
    """Run every log of ``specs`` on Ray into ``out_dir`` (see the module docstring); write ``fleet.json`` and the
    fleet report. Raises :class:`ConfigError` (before any log runs) for an unusable ``out_dir``, a missing Ray or
    a cluster that cannot be joined; ``KeyboardInterrupt`` after cleaning up."""
    ray = require_ray(ray_address)
    config = config or BatchConfig()
    out_dir = Path(out_dir).absolute()
    t0 = time.perf_counter()
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ConfigError("two logs of the batch have one name; give each its own (--name in a list file)")
    fresh = not out_dir.exists()
    lock = prepare_out_dir(out_dir, resume)
    try:
        return _run_locked(specs, out_dir, config, workers, ray_address, resume, progress, hook, ray, names, fresh, t0)
    finally:
        release_batch_lock(lock)


def _run_locked(specs: Sequence[LogSpec], out_dir: Path, config: BatchConfig, workers: int | None,
                ray_address: str | None, resume: bool, progress: ProgressCallback | None, hook: LogHook | None,
                ray: Any, names: list[str], fresh: bool, t0: float) -> FleetResult:
    """:func:`run_batch` with ``out_dir`` prepared and its batch lock held."""
    config_file = config.write_tables(out_dir)
    rows = _skipped_rows(specs, config, out_dir) if resume else {}
    todo = [s for s in specs if s.name not in rows]
    state = FleetProgress(total=len(specs), done=len(rows), skipped=len(rows))
    tick = progress or (lambda p: None)
    started = False
    w, t = plan_workers(workers, config.fleet.threads_per_log, ray_address)
    embedded = bool(todo) and ray_address is None and not ray.is_initialized()
    earlier = set(descendants()) if embedded else set()
    was_subreaper = is_subreaper()
    if embedded:
        adopt_orphans()  # an agent whose raylet dies first stays ours to stop (see driftmap.fleet.reaper)
    watchdog = start_watchdog(keep=earlier) if embedded else None  # ... and if this process is killed outright
    try:
        if todo:
            try:
                started = _start_ray(ray, ray_address, w, t)
            except (DriftmapError, KeyboardInterrupt):
                if fresh:  # nothing ran: leave no batch folder behind (a rerun needs no --resume)
                    shutil.rmtree(out_dir, ignore_errors=True)
                raise
            if ray_address is not None and workers is None:
                w = plan_workers(None, t, ray_address, int(ray.cluster_resources().get("CPU", 1)))[0]
            shared = ray.put(config)
            task = ray.remote(run_log).options(num_cpus=t, max_retries=MAX_RETRIES, retry_exceptions=False)
            batch = _Batch(ray, todo, lambda s: task.remote(s, shared, str(out_dir), threads=t,
                                                            config_file=config_file and str(config_file), hook=hook),
                           w, state, tick, rows)
            try:
                batch.run()
            except KeyboardInterrupt:
                unfinished = batch.cancel()
                write_fleet_json(out_dir, [rows[n] for n in names if n in rows], w, ray_address,
                                 interrupted=unfinished, threads=t)
                raise
        else:
            tick(state)
    finally:
        with interrupts_deferred():  # a second Ctrl-C does not cut the clean-up short
            if watchdog is not None:
                watchdog.stop()
            if started:
                ray.shutdown()
            if embedded:  # also after Ctrl-C inside ray.init, before `started` was set
                stop_descendants(keep=earlier)
                if not was_subreaper:
                    adopt_orphans(False)  # a library caller's process is left as it was
            if out_dir.is_dir():
                clean_temp(out_dir)
    ordered = [rows[n] for n in names]
    files = {"fleet_json": write_fleet_json(out_dir, ordered, w, ray_address, threads=t)}
    files.update(write_fleet_report(out_dir, ordered))
    return FleetResult(ordered, w, t, ray_address, out_dir, files, time.perf_counter() - t0)
