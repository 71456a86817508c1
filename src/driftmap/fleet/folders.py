"""The output folder of a batch, and how a log's results appear in it whole or not at all.

::

    DIR/.driftmap-fleet      marks DIR as a batch's folder (``--resume`` continues it)
    DIR/fleet.json           one row per log (the contract in docs/fleet.md)
    DIR/fleet.html, *.png    the fleet report
    DIR/fleet_config.json    the config every log's build and diagnose read (without the [fleet] table)
    DIR/<name>/              one log: store/, diagnosis.json, result.json, log.txt and the exports
    DIR/.fleet-tmp/          logs being written (removed when a batch starts and ends)

A log is written into ``DIR/.fleet-tmp/<name>.<token>/`` and renamed to ``DIR/<name>/`` when it is complete
(:func:`publish`: a rename within one file system, so ``DIR/<name>/`` is never half-written). ``result.json``
records the log's row, the hash of the config it was made with and the fingerprint of its input files
(:func:`input_fingerprint`; :func:`completed_result`).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import secrets
import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from driftmap._version import __version__
from driftmap.errors import ConfigError
from driftmap.files import flock_held, flock_release, fsync_dir

__all__ = ["BATCH_LOCK", "FLEET_JSON", "MARKER", "RESULT_FILE", "TMP_DIR", "clean_temp", "completed_result", "damage",
           "input_fingerprint", "prepare_out_dir", "publish", "release_batch_lock", "temp_folder"]

logger = logging.getLogger(__name__)

MARKER = ".driftmap-fleet"
FLEET_JSON = "fleet.json"
RESULT_FILE = "result.json"
TMP_DIR = ".fleet-tmp"
LOG_FILES = ("store", "diagnosis.json", RESULT_FILE)
"""What a complete log folder holds at least."""
BATCH_LOCK = ".fleet-batch.lock"
"""flock'ed by the batch writing into the folder (its pid inside): a second batch is refused"""


def prepare_out_dir(out_dir: Path, resume: bool) -> IO[str]:
    """Make ``out_dir`` a batch's folder: new or empty, or an earlier batch's with ``resume``; partial logs of an
    interrupted batch are removed. Anything else is refused (:class:`ConfigError`) before it is touched, and so is a
    folder another batch is writing into (its partial logs would be taken for an interrupted batch's and removed).
    Returns the batch lock (``DIR/.fleet-batch.lock``, flock'ed), held until :func:`release_batch_lock`."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"--out {out_dir}: is a file, but a batch writes a folder")
    _refuse_a_running_batch(out_dir)
    earlier = (out_dir / MARKER).is_file()
    if out_dir.is_dir() and any(out_dir.iterdir()) and not earlier:
        raise ConfigError(f"--out {out_dir}: exists, is not empty and holds no batch ({MARKER}); choose another --out")
    if earlier and not resume:
        raise ConfigError(f"--out {out_dir}: holds an earlier batch; pass --resume to continue it (complete logs made "
                          f"with the same config are kept), or choose another --out")
    out_dir.mkdir(parents=True, exist_ok=True)
    lock = _take_batch_lock(out_dir)
    try:
        (out_dir / MARKER).write_text(json.dumps({"format": "driftmap-fleet", "driftmap": __version__}) + "\n")
        clean_temp(out_dir)
    except BaseException:
        release_batch_lock(lock)
        raise
    return lock


def _running_batch_message(out_dir: Path, lock: Path) -> str:
    try:
        pid = (lock.read_text().split() or ["?"])[-1]
    except OSError:
        pid = "?"
    return (f"--out {out_dir}: another driftmap batch (process {pid}) is writing into it; wait for it to finish (then "
            f"--resume continues it), or choose another --out")


def _refuse_a_running_batch(out_dir: Path) -> None:
    """:class:`ConfigError` when a live batch holds the lock of ``out_dir`` (checked without write access)."""
    if flock_held(out_dir / BATCH_LOCK):
        raise ConfigError(_running_batch_message(out_dir, out_dir / BATCH_LOCK))


def _take_batch_lock(out_dir: Path) -> IO[str]:
    lock = out_dir / BATCH_LOCK
    fh = open(lock, "a+")  # noqa: SIM115  (held open until release_batch_lock)
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        raise ConfigError(_running_batch_message(out_dir, lock)) from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"{os.getpid()}\n")
    fh.flush()
    return fh


def release_batch_lock(fh: IO[str]) -> None:
    """Release the lock :func:`prepare_out_dir` took (the file stays: a later batch takes it again)."""
    flock_release(fh)


def clean_temp(out_dir: Path) -> list[str]:
    """Remove the partial logs an interrupted batch left in ``DIR/.fleet-tmp``; returns their names."""
    tmp = out_dir / TMP_DIR
    removed = []
    if tmp.is_dir():
        for entry in sorted(tmp.iterdir()):
            removed.append(entry.name)
            shutil.rmtree(entry, ignore_errors=True) if entry.is_dir() else entry.unlink(missing_ok=True)
        with contextlib.suppress(OSError):  # not left behind empty
            tmp.rmdir()
    return removed


def temp_folder(out_dir: Path, name: str) -> Path:
    """A new folder to write log ``name`` into (in ``DIR/.fleet-tmp``, on the same file system as ``DIR``)."""
    folder = out_dir / TMP_DIR / f"{name}.{secrets.token_hex(4)}"
    folder.mkdir(parents=True)
    return folder


def publish(tmp: Path, final: Path) -> None:
    """Rename the complete log ``tmp`` to ``final``. An earlier ``final`` (a log redone) is moved aside first and
    removed after: at every moment ``final`` is either the old complete log, absent, or the new complete one."""
    fsync_dir(tmp)
    old = None
    if final.exists():
        old = tmp.parent / f"{tmp.name}.old"
        final.rename(old)
    tmp.rename(final)
    fsync_dir(final.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def input_fingerprint(paths: Iterable[str | Path | None]) -> str:
    """A fingerprint of a log's input files as they are now: every file under each path (a file, or a folder walked
    without following links to folders) by its path relative to it, size and modification time (ns); a missing
    path counts as missing. ``--resume`` redoes a log whose fingerprint changed (a log replaced in place)."""
    digest = hashlib.sha256()
    for path in paths:
        if path is None:
            continue
        digest.update(f"{path}\n".encode())
        for rel, size, mtime_ns in _file_stats(Path(path)):
            digest.update(f"{rel}\0{size}\0{mtime_ns}\n".encode())
    return digest.hexdigest()[:32]


def _file_stats(root: Path) -> Iterator[tuple[str, int, int]]:
    try:
        if not root.is_dir():
            st = root.stat()
            yield "", st.st_size, st.st_mtime_ns
            return
    except OSError:
        yield "<missing>", -1, -1
        return
    for here, dirs, files in os.walk(root):
        dirs.sort()
        for name in sorted(files):
            full = Path(here) / name
            try:
                st = full.stat()
                yield full.relative_to(root).as_posix(), st.st_size, st.st_mtime_ns
            except OSError:  # a broken link: counted as such
                yield full.relative_to(root).as_posix(), -1, -1


def completed_result(folder: Path, expected_hash: str | None = None, *, verify: bool = True,
                     expected_input: str | None = None) -> dict[str, Any] | None:
    """The ``result.json`` of a complete log folder (None if the folder is missing, incomplete, failed, or was
    made with another config than ``expected_hash``, or -- ``expected_input`` given -- from input files whose
    :func:`input_fingerprint` has changed since; a result that records none, from before fingerprints were kept, is
    taken as it is). With ``verify`` the folder's data is checked against its recorded row too (:func:`damage`): a
    log whose store was damaged or changed since is not complete."""
    if not all((folder / f).exists() for f in LOG_FILES):
        return None
    with contextlib.suppress(OSError, ValueError, RecursionError):
        result = json.loads((folder / RESULT_FILE).read_text())
        if (isinstance(result, dict) and isinstance(result.get("row"), dict) and result["row"].get("status") == "ok"
                and (expected_hash is None or result.get("config_hash") == expected_hash)):
            recorded = result.get("input_fingerprint")
            if expected_input is not None and recorded is not None and recorded != expected_input:
                logger.warning("%s: the log's input files changed since it was processed (names, sizes or times); the "
                               "log is run again", folder)
                return None
            if verify and (problem := damage(folder, result["row"])) is not None:
                logger.warning("%s: %s; the log is run again", folder, problem)
                return None
            return result
    return None


def damage(folder: Path, row: dict[str, Any]) -> str | None:
    """What is wrong with a log folder whose ``result.json`` says it is complete (None if nothing): its store does
    not open (a damaged or missing segment), holds another number of frames than the recorded row, its
    ``diagnosis.json`` does not parse, or an export the row names is missing."""
    from driftmap.store.frame_store import FrameStore

    try:
        with FrameStore.open(folder / "store") as store:
            frames = len(store)
    except Exception as exc:  # noqa: BLE001 - any failure to read the store means the log must be redone
        return f"its store does not open ({type(exc).__name__}: {exc})"
    if frames != row.get("frames"):
        return f"its store holds {frames} frames, but its result records {row.get('frames')}"
    try:
        json.loads((folder / "diagnosis.json").read_text())
    except (OSError, ValueError, RecursionError) as exc:
        return f"its diagnosis.json cannot be read ({exc})"
    exports = row.get("exports")
    missing = [f for f in exports.values() if not (folder / f).exists()] if isinstance(exports, dict) else []
    if missing:
        return f"its exports are missing ({', '.join(missing)})"
    return None
