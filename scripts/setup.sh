#!/usr/bin/env bash
# One-time, idempotent set-up of a fresh machine for mems-stereo:
#   1. the system libraries Open3D needs (libusb for `import open3d`,
#      Mesa EGL/GL for headless rendering) and libdeflate (gzip'd recordings
#      read twice as fast; mems_stereo/io/deflate_chunks.py), installed with
#      apt when missing;
#   2. Debian's chromium and chromium-driver (the browser viewer's test drives
#      the page of `mems-stereo live --view browser` in headless chromium),
#      without their recommended packages;
#   3. a virtual environment in .venv with the package and its test tools;
#   4. numba's disk cache of the package's kernels (scripts/warm_kernels.py).
# Re-running it is cheap: each step is skipped when already done.
set -euo pipefail
cd "$(dirname "$0")/.."

need_pkgs=()
for p in libusb-1.0-0 libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libgomp1 libdeflate0; do
  dpkg -s "$p" >/dev/null 2>&1 || need_pkgs+=("$p")
done
if [ ${#need_pkgs[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  echo "[setup] installing system packages: ${need_pkgs[*]}" >&2
  $SUDO apt-get update -qq >&2
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_pkgs[@]}" >&2
fi
browser_pkgs=()
for p in chromium chromium-driver; do
  dpkg -s "$p" >/dev/null 2>&1 || browser_pkgs+=("$p")
done
if [ ${#browser_pkgs[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  echo "[setup] installing ${browser_pkgs[*]} (about 40 s)" >&2
  [ ${#need_pkgs[@]} -gt 0 ] || $SUDO apt-get update -qq >&2
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
    "${browser_pkgs[@]}" >&2
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv" >&2
  "$PY" -m venv .venv
fi
stamp=.venv/.mems-stereo-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "[setup] installing mems-stereo and its dependencies into .venv (about 2 minutes)" >&2
  .venv/bin/python -m pip install -q --upgrade pip >&2
  .venv/bin/python -m pip install -q -e ".[dev]" >&2
  touch "$stamp"
fi
# 4. numba's disk cache of the package's kernels (scripts/warm_kernels.py): compiled once
#    here (about 60 CPU s) instead of in each test process that meets them; redone when a
#    package source is newer than the stamp
kstamp=.venv/.mems-stereo-kernels
if [ ! -f "$kstamp" ] || [ -n "$(find mems_stereo -name '*.py' -newer "$kstamp" -print -quit)" ]; then
  echo "[setup] compiling the numba kernels into their disk cache (about 1 minute)" >&2
  .venv/bin/python scripts/warm_kernels.py >&2
  touch "$kstamp"
fi
