#!/usr/bin/env bash
# Idempotent set-up for a fresh Debian machine with Python 3.11: system library for Open3D, a virtual
# environment in .venv, and driftmap with its test dependencies. Re-running only redoes what changed.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON="${PYTHON:-python3.11}"
if ! command -v "$PYTHON" >/dev/null 2>&1; then
  PYTHON=python3
fi
if ! "$PYTHON" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' 2>/dev/null; then
  echo "driftmap needs Python >= 3.11 (tried '$PYTHON')" >&2
  exit 1
fi

# System libraries: Open3D needs libusb-1.0 at import time; its headless rendering (the viewer's PNG views,
# docs/open3d-choice.md) needs Mesa's EGL and, for OffscreenRenderer, Vulkan with Mesa's software driver.
missing=()
libs=$(ldconfig -p 2>/dev/null || true)  # once: "ldconfig -p | grep -q" fails under pipefail when grep exits early
have_lib() { grep -qF "$1" <<< "$libs"; }
have_lib 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
have_lib 'libEGL.so.1 ' || missing+=(libegl1)
have_lib 'libGL.so.1 ' || missing+=(libgl1)
have_lib 'libEGL_mesa.so.0' || missing+=(libegl-mesa0 libgl1-mesa-dri)
have_lib 'libvulkan.so.1' || missing+=(libvulkan1)
ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 || missing+=(mesa-vulkan-drivers)
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing system libraries for Open3D with apt-get: ${missing[*]}" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi

# Reinstall only when the dependency list changed (or the install never finished).
stamp=.venv/.driftmap-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet -e '.[test]'
  echo "$want" > "$stamp"
fi
