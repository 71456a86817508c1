"""Writing an output file so that it appears complete or not at all (a bottom layer: every writer uses it).

:func:`atomic_write` writes under a temporary name in the same folder and renames into place only when the file is
complete and flushed: a failed export leaves no partial file, and an existing file survives a failed overwrite.
Outputs that must not land inside a store folder are refused above this layer
(:func:`driftmap.store.refuse_inside_store`, which :func:`driftmap.store.guards.atomic_output` adds).
"""

from __future__ import annotations

import contextlib
import errno as errno_codes
import fcntl
import logging
import os
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from driftmap.errors import DuplicateKeyError, OutputWriteError


logger = logging.getLogger(__name__)

MAX_NAME_IN_TEMP = 200
"""The temporary file's name repeats at most this much of the output's name (names are limited to 255 bytes)."""


def fsync_dir(folder: Path) -> None:
    """Flush a folder's entries (a rename into it) to disk, where the OS allows it."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def flock_held(lock: Path) -> bool:
    """True if some process holds an exclusive ``flock`` on the file ``lock`` (a store's writer lock, a batch's
    lock). Needs no write access: the file is opened read-only, and one that is missing or cannot be opened means
    no holder is known."""
    try:
        fd = os.open(lock, os.O_RDONLY)
    except FileNotFoundError:
        return False
    except OSError as exc:
        logger.debug("%s: cannot open the lock to see whether it is held (%s)", lock, exc)
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as exc:
        return exc.errno in (errno_codes.EAGAIN, errno_codes.EACCES)
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


def flock_release(fh: IO[str]) -> None:
    """Release a lock file held open with ``flock`` (errors are ignored: the lock goes with the file)."""
    with contextlib.suppress(OSError):
        fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
    with contextlib.suppress(OSError):
        fh.close()


@contextlib.contextmanager
def atomic_write(path: str | Path, what: str) -> Iterator[Path]:
    """Yield a temporary path (same folder, same suffix, so format detection by extension still works) for the body
    to write; when it returns, the file is flushed and renamed over ``path``. If the body raises, the temporary file
    is removed and ``path`` is untouched. ``what`` names the output in errors (a CLI flag or the function); an
    ``OSError`` becomes :class:`~driftmap.errors.OutputWriteError` naming ``path``."""
    path = Path(path)
    stem = path.name if len(path.name) <= MAX_NAME_IN_TEMP else path.name[:MAX_NAME_IN_TEMP]
    tmp = path.with_name(f".{stem}.{secrets.token_hex(4)}.tmp{path.suffix[:16]}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        if not tmp.exists():
            raise OutputWriteError(f"{path}: the writer produced no file ({what})", path=path, errno=None)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
        fsync_dir(path.parent)
    except OSError as exc:
        raise OutputWriteError(
            f"{path}: could not be written ({what}): {exc.strerror or exc}"
            + (" (no space left on the device)" if exc.errno == errno_codes.ENOSPC else "")
            + "; nothing was written under that name (an existing file is unchanged)",
            path=path, errno=exc.errno) from exc
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)


def _unique_object(pairs: list[tuple[str, object]]) -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in pairs:
        if key in out:
            raise DuplicateKeyError(f"the key {key!r} appears twice in one object (which one is meant?)")
        out[key] = value
    return out


def json_loads_unique(text: str) -> object:
    """``json.loads`` refusing an object that names a key twice (:class:`DuplicateKeyError`), as TOML does."""
    import json

    return json.loads(text, object_pairs_hook=_unique_object)
