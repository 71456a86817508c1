"""The ``driftmap`` command line (typer + rich).

Only this package prints and exits: library errors (:class:`DriftmapError`) become one red line and exit code 1;
``--debug`` shows the traceback and debug logs. Each command parses its flags, calls one library function and
renders what it returns; the commands live by group in :mod:`~driftmap.cli.build_cmds` (demo, config, synth,
convert, build), :mod:`~driftmap.cli.store_cmds` (correct, revisions, rollback, export, info, recover) and
:mod:`~driftmap.cli.diagnose_cmds` (diagnose, view, perturb); :mod:`~driftmap.cli.common` holds what they share.
"""

from __future__ import annotations

import sys

from rich.text import Text

# the command modules register their commands on import, in the order --help lists them
# isort: off
from driftmap.cli import build_cmds  # noqa: F401
from driftmap.cli import store_cmds  # noqa: F401
from driftmap.cli import diagnose_cmds  # noqa: F401
from driftmap.cli import batch_cmds  # noqa: F401
from driftmap.cli import decide_cmds  # noqa: F401
# isort: on
from driftmap.cli.common import app, err_console, state
from driftmap.errors import DriftmapError

__all__ = ["app", "main"]


def main() -> None:
    """Console-script entry point: maps driftmap errors to one line and a non-zero exit."""
    try:
        app()
    except DriftmapError as exc:
        if state["debug"]:
            raise
        _error(str(exc))
    except UnicodeDecodeError as exc:
        if state["debug"]:
            raise
        _error(f"a file is not UTF-8 text ({exc.reason} at byte {exc.start}); run with --debug to see which")
    except OSError as exc:  # unwritable output, a directory where a file was expected, a full disk ...
        if state["debug"]:
            raise
        from driftmap.cli.common import os_error_hint

        hint = os_error_hint(exc)
        _error((f"{exc.filename}: {exc.strerror}" if exc.filename and exc.strerror else str(exc))
               + (f"; {hint}" if hint else ""))
    except KeyboardInterrupt:
        err_console.print(Text("interrupted", style="red"))
        sys.exit(130)


def _error(message: str) -> None:
    err_console.print(Text.assemble(("error:", "red"), f" {message}"), highlight=False, soft_wrap=True)
    sys.exit(1)
