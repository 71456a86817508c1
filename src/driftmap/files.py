"""Writing an output file so that it appears complete or not at all (a bottom layer: every writer uses it).

:func:`atomic_write` writes under a temporary name in the same folder and renames into place only when the file is
complete and flushed: a failed export leaves no partial file, and an existing file survives a failed overwrite.
Outputs that must not land inside a store folder are refused above this layer
(:func:`driftmap.store.refuse_inside_store`, which :func:`driftmap.store.guards.atomic_output` adds).
"""

from __future__ import annotations

import contextlib
import contextvars
import errno as errno_codes
import fcntl
import logging
import os
import secrets
import stat
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


_NO_CLOBBER: contextvars.ContextVar[bool] = contextvars.ContextVar("driftmap_no_clobber", default=False)


@contextlib.contextmanager
def no_clobber(active: bool = True) -> Iterator[None]:
    """Within it, :func:`atomic_write` puts its file in place only where no file is: a command that refused an
    existing output before its work (no ``--overwrite``) must not replace one that appeared meanwhile -- another
    process writing the same name (hostile trial 25 W9: two exports to one new file both said they wrote it)."""
    token = _NO_CLOBBER.set(active)
    try:
        yield
    finally:
        _NO_CLOBBER.reset(token)


def _put_in_place(tmp: Path, path: Path) -> None:
    """``os.replace``, or under :func:`no_clobber` a hard link that fails when ``path`` exists (a file system
    without hard links: replaced only if nothing is there, which is not atomic against another writer)."""
    if not _NO_CLOBBER.get():
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(errno_codes.EEXIST, "another process wrote a file of that name while this one was being "
                                                  "made; it was not replaced (give --overwrite to replace it)") from None
    except OSError as exc:
        if exc.errno not in (errno_codes.EPERM, errno_codes.ENOTSUP, errno_codes.EOPNOTSUPP, errno_codes.EXDEV):
            raise
        if path.exists():
            raise FileExistsError(errno_codes.EEXIST, "another process wrote a file of that name while this one was "
                                                      "being made; it was not replaced (give --overwrite to replace "
                                                      "it)") from None
        os.replace(tmp, path)


def special_file_kind(path: str | Path) -> str | None:
    """What ``path`` (a link followed) is when it exists and is neither a regular file nor a folder -- "a FIFO", "a
    character device" (``/dev/stdout``, ``/dev/null``), "a block device", "a socket" -- else None."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    for test, kind in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return None


def refuse_special_file(path: str | Path, what: str) -> None:
    """An output that exists as a FIFO, a device or a socket (or a link to one) is refused: an atomic write renames a
    regular file over the name, which replaces it (hostile trial 25 B6: ``--trajectory /dev/stdout`` replaced the
    machine's ``/dev/stdout`` link)."""
    kind = special_file_kind(path)
    if kind is not None:
        raise OutputWriteError(f"{path}: is {kind}, not a file ({what}): driftmap writes its outputs as regular files "
                               f"(a temporary file renamed into place), which would replace it; give a file path",
                               path=Path(path), errno=None)


@contextlib.contextmanager
def atomic_write(path: str | Path, what: str) -> Iterator[Path]:
    """Yield a temporary path (same folder, same suffix, so format detection by extension still works) for the body
    to write; when it returns, the file is flushed and renamed over ``path``. If the body raises, the temporary file
    is removed and ``path`` is untouched. ``what`` names the output in errors (a CLI flag or the function); an
    ``OSError`` becomes :class:`~driftmap.errors.OutputWriteError` naming ``path``."""
    path = Path(path)
    refuse_special_file(path, what)
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
        _put_in_place(tmp, path)
        fsync_dir(path.parent)
    except OSError as exc:
        raise OutputWriteError(
            f"{path}: could not be written ({what}): {exc.strerror or exc}"
            + (" (no space left on the device)" if exc.errno == errno_codes.ENOSPC else "")
            + ("" if exc.errno == errno_codes.EEXIST else "; nothing was written under that name (an existing file "
               "is unchanged)"),
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
