"""``python -m driftmap.cli``: the command line."""

from driftmap.cli import main

main()
