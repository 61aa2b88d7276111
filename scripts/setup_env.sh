#!/usr/bin/env bash
# Creates .venv when missing and installs fruxel with every extra at the pinned versions (constraints.txt).
# Re-running is cheap: the install is skipped while pyproject.toml and constraints.txt are unchanged.
# Also checks for Mesa's EGL (headless OpenGL for pyrender) and Debian's PoCL (OpenCL on the CPU): installs them
# when running as root with apt (waiting up to FRUXEL_APT_WAIT seconds, default 300, for another apt or dpkg to
# release its lock), else prints the command to run.
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
  # setuptools says "Editable installation. Please be careful with folders in your working directory with the same
  # name as your package" for every editable install of a package laid out over several folders (package-dir);
  # here the folder fruxel/ is the package itself, so the notice is filtered out, by its message alone.
  PYTHONWARNINGS="ignore:Editable installation" .venv/bin/python -m pip install -q -c constraints.txt -e ".[all]"
  echo "$want" > "$stamp"
fi

# System packages, installed when running as root with apt, else named with the command to run:
# - Mesa's EGL vendor library and DRI drivers give pyrender a headless OpenGL context (llvmpipe on a CPU);
#   required.
# - Debian's PoCL (pocl-opencl-icd: PoCL 3.1 on LLVM 15, its kernel library tied to known target CPUs) is the
#   OpenCL CPU driver that compiles on current x86-64 CPUs. The PyPI pocl-binary-distribution that pyopencl brings
#   (LLVM 14) fails to build any kernel on CPUs newer than its LLVM (AMD Zen 5: "unknown target CPU 'generic'").
#   pyopencl's bundled ICD loader also reads /etc/OpenCL/vendors, so both are visible; fruxel's OpenCL runtime
#   probes each device and prefers the newer PoCL (kernels/cl/runtime.py). Without it OpenCL may still work, or
#   fruxel falls back to Warp with a warning: recommended, not required.
have_egl() {
  # No pipes into grep -q here: with pipefail, the early exit of grep would count as a failure.
  local libs
  libs=$(ldconfig -p 2>/dev/null || true)
  [[ $libs == *libEGL_mesa.so.0* && $libs == *libEGL.so.1* ]] && compgen -G '/usr/lib/*/dri/swrast_dri.so' >/dev/null
}
have_pocl() {
  [ -f /etc/OpenCL/vendors/pocl.icd ]
}
egl_pkgs="libegl-mesa0 libgl1-mesa-dri libegl1"
pocl_pkgs="pocl-opencl-icd"
# Another apt or dpkg (an unattended upgrade, a second set-up) may hold their locks: apt-get then waits up to
# FRUXEL_APT_WAIT seconds (default 300) for them, and says in one line when it gave up.
APT_WAIT=${FRUXEL_APT_WAIT:-300}
apt_get() {
  # DPkg::Lock::Timeout makes apt-get wait for dpkg's lock itself; the lock of `apt-get update` (on the package
  # lists) has no timeout in apt 2.x, so a refusal for a lock is retried here until the same deadline. apt's own
  # messages are shown as they are unless they are about a lock.
  # The deadline in milliseconds: bash's SECONDS counts whole seconds from an arbitrary fraction of one, so a wait
  # measured with it could end up to a second early.
  local log rc holder deadline=$(( $(date +%s%3N) + APT_WAIT * 1000 )) waiting=
  log=$(mktemp)
  while :; do
    rc=0
    apt-get -o DPkg::Lock::Timeout="$APT_WAIT" "$@" 2>"$log" || rc=$?
    if [ "$rc" = 0 ] || ! grep -qE 'Could not get lock|Unable to (acquire|lock)' "$log"; then
      cat "$log" >&2
      rm -f "$log"
      [ "$rc" = 0 ] || exit "$rc"
      return 0
    fi
    # "It is held by process N (name)" when apt could see the holder, else the lock's file.
    holder=$(grep -oE 'held by process [0-9]+( \([^)]*\))?' "$log" | head -n 1 || true)
    [ -n "$holder" ] || holder=$(grep -oE '/[^ ,()]*lock[^ ,()]*' "$log" | head -n 1 || true)
    if [ "$(date +%s%3N)" -ge "$deadline" ]; then
      rm -f "$log"
      echo "setup_env.sh: another apt or dpkg still holds its lock${holder:+ ($holder)} after ${APT_WAIT} s; run" \
        "make env again once it has finished (FRUXEL_APT_WAIT=SECONDS waits longer)" >&2
      exit "$rc"
    fi
    if [ -z "$waiting" ]; then
      echo "waiting up to ${APT_WAIT} s for another apt or dpkg to finish${holder:+ ($holder)}"
      waiting=1
    fi
    sleep 2
  done
}

if ! have_egl || ! have_pocl; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    export DEBIAN_FRONTEND=noninteractive
    apt_get update -qq
    if ! have_egl; then
      echo "installing Mesa EGL for headless rendering: $egl_pkgs"
      apt_get install -y -qq $egl_pkgs
    fi
    if ! have_pocl; then
      # Without recommends: PoCL needs clang-15 and LLVM 15, not the 32-bit libraries that clang recommends.
      echo "installing Debian's PoCL (OpenCL on the CPU): $pocl_pkgs"
      apt_get install -y -qq --no-install-recommends $pocl_pkgs
    fi
  else
    if ! have_pocl; then
      echo "Debian's PoCL (OpenCL on current CPUs) is missing; without it OpenCL may fall back to Warp. Install it with:" >&2
      echo "  sudo apt-get install -y --no-install-recommends $pocl_pkgs" >&2
    fi
    if ! have_egl; then
      echo "Mesa EGL (headless OpenGL) is missing. Install it with:" >&2
      echo "  sudo apt-get install -y $egl_pkgs" >&2
      exit 1
    fi
  fi
fi
