#!/usr/bin/env bash
# Set up (if needed) and run the driftmap demo on the embedded synthetic log. Extra arguments go to
# `driftmap demo` (e.g. --out DIR).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/driftmap demo "$@"
