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

# System libraries: Open3D links libusb-1.0, EGL and GL (needed to import it); its headless rendering (the
# viewer's PNG views, docs/open3d-choice.md) also needs Mesa's EGL and, for OffscreenRenderer, Vulkan with
# Mesa's software driver (without them the viewer falls back to its software renderer, and one test fails).
required=()
optional=()
libs=$(ldconfig -p 2>/dev/null || true)  # once: "ldconfig -p | grep -q" fails under pipefail when grep exits early
have_lib() { grep -qF "$1" <<< "$libs"; }
have_lib 'libusb-1.0.so.0' || required+=(libusb-1.0-0)
have_lib 'libEGL.so.1 ' || required+=(libegl1)
have_lib 'libGL.so.1 ' || required+=(libgl1)
have_lib 'libEGL_mesa.so.0' || optional+=(libegl-mesa0 libgl1-mesa-dri)
have_lib 'libvulkan.so.1' || optional+=(libvulkan1)
ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 || optional+=(mesa-vulkan-drivers)
if [ $((${#required[@]} + ${#optional[@]})) -gt 0 ]; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing system libraries for Open3D with apt-get: ${required[*]} ${optional[*]}" >&2
  if ! { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq \
         --no-install-recommends "${required[@]}" "${optional[@]}" >/dev/null; }; then
    if [ ${#required[@]} -gt 0 ]; then
      echo "could not install ${required[*]}: Open3D cannot be imported without them" >&2
      exit 1
    fi
    echo "warning: could not install ${optional[*]}: headless Open3D rendering is not available (the viewer" \
         "falls back to its software renderer)" >&2
  fi
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
