#!/usr/bin/env bash
# Creates .venv when missing and installs fruxel with every extra at the pinned versions (constraints.txt).
# Re-running is cheap: the install is skipped while pyproject.toml and constraints.txt are unchanged.
# Also checks for Mesa's EGL (headless OpenGL for pyrender): installs it when running as root, else prints
# the command to run.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 10))' \
    || { echo "fruxel needs Python >= 3.10 (found $($PYTHON --version 2>&1)); set PYTHON=..." >&2; exit 1; }
  echo "creating .venv with $($PYTHON --version 2>&1)"
  "$PYTHON" -m venv .venv
fi

stamp=.venv/.fruxel-installed
want=$(cat pyproject.toml constraints.txt | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "installing fruxel[all] with pinned dependencies (constraints.txt)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -c constraints.txt -e ".[all]"
  echo "$want" > "$stamp"
fi

# Mesa's EGL vendor library and DRI drivers give pyrender a headless OpenGL context (llvmpipe on a CPU).
have_egl() {
  # No pipes into grep -q here: with pipefail, the early exit of grep would count as a failure.
  local libs
  libs=$(ldconfig -p 2>/dev/null || true)
  [[ $libs == *libEGL_mesa.so.0* && $libs == *libEGL.so.1* ]] && compgen -G '/usr/lib/*/dri/swrast_dri.so' >/dev/null
}
if ! have_egl; then
  pkgs="libegl-mesa0 libgl1-mesa-dri libegl1"
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "installing Mesa EGL for headless rendering: $pkgs"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $pkgs
  else
    echo "Mesa EGL (headless OpenGL) is missing. Install it with:" >&2
    echo "  sudo apt-get install -y $pkgs" >&2
    exit 1
  fi
fi
