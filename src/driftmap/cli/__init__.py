"""The ``driftmap`` command line (typer + rich).

Only this package prints and exits: library errors (:class:`DriftmapError`) become one red line and exit code 1;
``--debug`` shows the traceback and debug logs. Each command parses its flags, calls one library function and
renders what it returns; the commands live by group in :mod:`~driftmap.cli.build_cmds` (demo, config, synth,
convert, build), :mod:`~driftmap.cli.store_cmds` (correct, revisions, rollback, export, info, recover) and
:mod:`~driftmap.cli.diagnose_cmds` (diagnose, view, perturb), :mod:`~driftmap.cli.batch_cmds` (batch),
:mod:`~driftmap.cli.decide_cmds` (decide) and :mod:`~driftmap.cli.merge_cmds` (merge); :mod:`~driftmap.cli.common`
holds what they share.
"""

from __future__ import annotations

import signal
import sys
import threading

_interrupt = {"seen": False}
"""Set by Ctrl-C (SIGINT): whatever a library turns the interrupt into while it loads (open3d, gtsam and numpy's
extensions raise ImportError or their own errors when interrupted mid-initialisation), the command ends as
interrupted (exit 130), not with a traceback."""


def _on_sigint(signum: int, frame: object) -> None:
    _interrupt["seen"] = True
    raise KeyboardInterrupt


def _exit_interrupted() -> None:
    sys.stderr.write("interrupted\n")  # rich may not be loaded yet
    sys.stderr.flush()
    import os

    os._exit(130)


if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
    signal.signal(signal.SIGINT, _on_sigint)

try:
    from rich.text import Text

    # the command modules register their commands on import, in the order --help lists them
    # isort: off
    from driftmap.cli import build_cmds  # noqa: F401
    from driftmap.cli import store_cmds  # noqa: F401
    from driftmap.cli import diagnose_cmds  # noqa: F401
    from driftmap.cli import batch_cmds  # noqa: F401
    from driftmap.cli import decide_cmds  # noqa: F401
    from driftmap.cli import merge_cmds  # noqa: F401
    # isort: on
    from driftmap.cli.common import app, err_console, state
    from driftmap.errors import DriftmapError
except BaseException as exc:  # noqa: BLE001 - only an interrupt is handled here; everything else is re-raised
    if _interrupt["seen"] or isinstance(exc, KeyboardInterrupt):
        _exit_interrupted()
    raise

__all__ = ["app", "main"]


def main() -> None:
    """Console-script entry point: maps driftmap errors to one line and a non-zero exit, Ctrl-C to exit 130."""
    try:
        app()
    except KeyboardInterrupt:
        _interrupted()
    except SystemExit as exc:  # typer turns a Ctrl-C inside a command into Exit(130): end it the same way
        if _interrupt["seen"] and exc.code == 130:
            _interrupted()
        raise
    except Exception as exc:
        if _interrupt["seen"]:  # an interrupt while a library loads or works can surface as its own error
            _interrupted()
        if state["debug"] or not isinstance(exc, (DriftmapError, UnicodeDecodeError, OSError)):
            raise
        _error(_message(exc))


def _message(exc: Exception) -> str:
    if isinstance(exc, UnicodeDecodeError):
        return f"a file is not UTF-8 text ({exc.reason} at byte {exc.start}); run with --debug to see which"
    if isinstance(exc, DriftmapError):  # its own message says it all (OutputWriteError is an OSError too)
        return str(exc)
    if isinstance(exc, OSError):  # unwritable output, a directory where a file was expected, a full disk ...
        from driftmap.cli.common import os_error_hint

        hint = os_error_hint(exc)
        return ((f"{exc.filename}: {exc.strerror}" if exc.filename and exc.strerror else str(exc))
                + (f"; {hint}" if hint else ""))
    return str(exc)


def _interrupted() -> None:
    err_console.print(Text("interrupted", style="red"))
    _exit_now(130)


def _exit_now(code: int) -> None:
    """Exit with ``code`` without the interpreter's shutdown (the logs and output are flushed first): an Open3D or
    GTSAM interrupted mid-initialisation prints its memory statistics from its C++ destructors and turns the exit
    code into 1, and Ray's C++ exit handler can crash (SIGSEGV in its core worker's destructor) after a Ray whose
    start was interrupted. ``batch`` has stopped its embedded Ray, and every process Ray left running, before this
    (driftmap.fleet.reaper)."""
    import logging
    import os

    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _error(message: str) -> None:
    err_console.print(Text.assemble(("error:", "red"), f" {message}"), highlight=False, soft_wrap=True)
    sys.exit(1)
