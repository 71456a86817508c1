#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite. Extra arguments go to pytest.
# Real data is read from ../shared/datasets (or $DRIFTMAP_DATASETS); with CI=true missing data fails.
# Tests run on pytest-xdist workers (one per core, at most 4; DRIFTMAP_TEST_WORKERS overrides, 0 = in-process),
# grouped by module; every test that starts Ray is in one group, so Ray clusters never overlap.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
workers="${DRIFTMAP_TEST_WORKERS:-$(nproc)}"
if [ "$workers" -gt 4 ]; then workers=4; fi
if [ "$workers" -le 0 ]; then
    exec .venv/bin/python -m pytest "$@"
fi
exec .venv/bin/python -m pytest -n "$workers" --dist loadgroup "$@"
