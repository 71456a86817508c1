"""What protects a frame store from the outside: outputs that would land inside a store folder, exports written
atomically, and operating-system errors turned into errors that name the file and say how to continue.

- :func:`refuse_inside_store` refuses an output path inside *any* store folder (symlinks and ``..`` resolved; a
  store is recognised by its manifest, or by its segment files when the manifest is damaged or gone), so an
  export, a report or a figure can never replace a segment or ``store.json``.
- :func:`atomic_output` writes a file under a temporary name in the same folder and renames it into place only
  when it is complete: a failed export leaves no partial file, and an existing file survives a failed overwrite.
- :func:`store_io_error` turns an ``OSError`` met while reading or writing a store into a
  :class:`~driftmap.errors.StoreIOError` naming the file, what was being done and the way to continue.
"""

from __future__ import annotations

import contextlib
import errno as errno_codes
import json
import logging
import os
from collections.abc import Iterator
from pathlib import Path

from driftmap.errors import OutputInsideStoreError, StoreIOError
from driftmap.files import atomic_write
from driftmap.store.layout import FORMAT_NAME, LOCK_FILE, MANIFEST, SEGMENT_FILE

logger = logging.getLogger(__name__)

_MAX_MANIFEST_PROBE_BYTES = 64 << 20


def _manifest_says_store(file: Path) -> bool | None:
    """True / False: ``file`` is / is not a driftmap manifest; None: it cannot be read or parsed (damaged?)."""
    try:
        if file.stat().st_size > _MAX_MANIFEST_PROBE_BYTES:
            return None
        data = json.loads(file.read_bytes())
    except (OSError, ValueError, RecursionError):
        return None
    return isinstance(data, dict) and data.get("format") == FORMAT_NAME


def is_store_folder(folder: str | Path) -> bool:
    """Whether ``folder`` is a driftmap frame store: its ``store.json`` is a driftmap manifest, or it holds
    ``segment-NNNNNN.mcap`` files (a store whose manifest is damaged or missing), or its ``store.json`` is
    unreadable next to a ``writer.lock``."""
    folder = Path(folder)
    try:
        if not folder.is_dir():
            return False
        manifest = folder / MANIFEST
        verdict = _manifest_says_store(manifest) if manifest.is_file() else False
        if verdict:
            return True
        if verdict is None and (folder / LOCK_FILE).exists():
            return True
        with os.scandir(folder) as entries:
            return any(SEGMENT_FILE.fullmatch(entry.name) for entry in entries)
    except OSError:  # an unreadable folder: not known to be a store
        return False


def _resolved(path: str | Path) -> Path:
    """``path`` made absolute with every symlink and ``..`` resolved (as far as it exists)."""
    return Path(os.path.realpath(os.path.abspath(os.fspath(path))))


def store_folder_of(path: str | Path, *, include_self: bool = True) -> Path | None:
    """The store folder ``path`` lies in (resolved), or None. ``include_self``: ``path`` being a store folder
    itself counts too."""
    resolved = _resolved(path)
    candidates = ([resolved] if include_self else []) + list(resolved.parents)
    for folder in candidates:
        if is_store_folder(folder):
            return folder
    return None


def refuse_inside_store(path: str | Path | None, flag: str, *, output_is_store: bool = False) -> None:
    """Refuse an output ``path`` that lies inside a frame-store folder (any store, not only the one being read):
    writing there could replace a segment or the manifest. Symlinks and ``..`` are resolved first, so neither a
    link into a store nor ``STORE/sub/../segment-000000.mcap`` gets through. ``flag`` names the option in the
    error (e.g. ``"--mcap"``). ``output_is_store``: ``path`` is itself a store to create or continue (``build
    --out``): only a store folder *around* it is refused. ``None`` is accepted (an output that was not given).

    Raises :class:`~driftmap.errors.OutputInsideStoreError` (a ``ConfigError``) naming the flag, the path and the store.
    """
    if path is None:
        return
    store = store_folder_of(path, include_self=not output_is_store)
    if store is None:
        return
    resolved = _resolved(path)
    where = "is the frame store" if resolved == store else "is inside the frame store"
    shown = f"{path}" if Path(os.path.abspath(path)) == resolved else f"{path} (= {resolved})"
    raise OutputInsideStoreError(
        f"{flag} {shown}: {where} {store}; writing there could replace or corrupt the store's own files "
        f"(segments, {MANIFEST}): write it outside the store folder", path=path, flag=flag, store=store)


@contextlib.contextmanager
def atomic_output(path: str | Path, what: str, *, guard: bool = True) -> Iterator[Path]:
    """Write ``path`` atomically: the body writes the file at the yielded temporary path (same folder, same
    suffix, so format detection by extension still works); when it returns, the file is flushed to disk and
    renamed over ``path``. If the body raises, the temporary file is removed and ``path`` is untouched (a new
    file never appears half-written, an existing one survives a failed overwrite).

    ``what`` names the output in errors (a CLI flag or the function). ``guard``: refuse a path inside a store
    folder first (:func:`refuse_inside_store`). An ``OSError`` becomes :class:`~driftmap.errors.OutputWriteError`
    naming ``path``. The writing is :func:`driftmap.files.atomic_write`'s; this adds the store-folder guard.
    """
    path = Path(path)
    if guard:
        refuse_inside_store(path, what)
    with atomic_write(path, what) as tmp:
        yield tmp


#: how to continue after an I/O error, by what was being done
RESUME_HINT = ("the frames stored before it are intact; free space (or fix the device) and continue with "
               "`driftmap build ... --resume` for a build, or run `driftmap recover {store}`")
RECOVER_HINT = "free space (or fix the device) and run `driftmap recover {store}` again: it continues where it stopped"
READ_HINT = ("check the file's permissions and the device (reading a store needs read access only, no lock and no "
             "write access)")


def store_io_error(exc: OSError, file: str | Path, action: str, store: str | Path, hint: str = RESUME_HINT) -> StoreIOError:
    """A :class:`StoreIOError` for ``exc`` met while ``action`` (e.g. ``"appending frame 7"``) on ``file``; ``exc``
    itself when it is one already (its message names the file and the step that failed)."""
    if isinstance(exc, StoreIOError):
        return exc
    reason = exc.strerror or str(exc) or type(exc).__name__
    if exc.errno == errno_codes.ENOSPC:
        reason = "no space left on the device"
    elif exc.errno == errno_codes.EROFS:
        reason = "read-only file system"
    code = f" [{errno_codes.errorcode.get(exc.errno, exc.errno)}]" if exc.errno else ""
    if exc.errno in (errno_codes.EROFS, errno_codes.EACCES, errno_codes.EPERM) and hint in (RESUME_HINT, RECOVER_HINT):
        # no space to free: the store cannot be written where it is (reading it still works)
        hint = ("the store cannot be written there (it can still be read: info, export, diagnose); remount it "
                "writable or copy it to a writable place and run the command there")
    elif exc.errno in (errno_codes.ELOOP, errno_codes.EISDIR, errno_codes.ENOTDIR):
        # the store's own layout is damaged: running again meets the same file, freeing space does not help
        hint = (f"{Path(file).name} is not the regular file the store expects there (a symbolic-link loop, a folder "
                f"or a path through a file); move it aside (keep it: it may hold data) and run "
                f"`driftmap recover {{store}}` again")
    message = f"{file}: {action} failed: {reason}{code}; {hint.format(store=store)}"
    logger.debug("%s", message, exc_info=exc)
    return StoreIOError(message, path=Path(file), errno=exc.errno)


__all__ = ["FORMAT_NAME", "LOCK_FILE", "MANIFEST", "SEGMENT_FILE", "atomic_output", "is_store_folder",
           "refuse_inside_store", "store_folder_of", "store_io_error"]
