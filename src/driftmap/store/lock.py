"""The writer lock (``writer.lock``, flock'ed): held by the one process that appends to a store; reading never
takes it."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from pathlib import Path
from typing import IO

from driftmap.errors import StoreError
from driftmap.files import flock_held, flock_release
from driftmap.store.guards import RESUME_HINT, store_io_error
from driftmap.store.layout import LOCK_FILE


def acquire_writer_lock(folder: Path) -> IO[str]:
    """Take the writer lock of the store in ``folder`` (appending needs write access); returns the open lock file,
    which holds it until :func:`release_writer_lock`."""
    lock = folder / LOCK_FILE
    hint = (f"appending needs write access to the store folder (reading does not: FrameStore.open(path) / "
            f"`driftmap info {folder}`)")
    try:
        fh = open(lock, "a+")  # noqa: SIM115  (held open until release_writer_lock)
    except OSError as exc:
        raise store_io_error(exc, lock, "taking the writer lock", folder, hint) from exc
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        fh.close()
        if exc.errno in (errno.EAGAIN, errno.EACCES):
            raise StoreError(f"{folder}: another process is appending to this store") from exc
        raise store_io_error(exc, lock, "taking the writer lock", folder, hint) from exc
    try:
        fh.seek(0)
        fh.truncate()
        fh.write(f"{os.getpid()}\n")
        fh.flush()
    except OSError as exc:  # the pid is informative only, but a full disk now fails every append later
        with contextlib.suppress(OSError):
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
            fh.close()
        raise store_io_error(exc, lock, "writing the writer lock", folder, RESUME_HINT) from exc
    return fh


def release_writer_lock(fh: IO[str]) -> None:
    """Release a lock taken by :func:`acquire_writer_lock` (errors are ignored: the lock goes with the file)."""
    flock_release(fh)


def writer_alive(folder: Path) -> bool:
    """True if some process holds the writer lock of the store in ``folder``. Needs no write access: the lock file
    is opened read-only, and one that is missing or cannot be opened means no writer is known."""
    return flock_held(folder / LOCK_FILE)
