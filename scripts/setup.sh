#!/usr/bin/env bash
# Installs what plate-inspect needs on a fresh Debian machine that has python3 (3.11) and apt:
# Aravis (GenICam cameras: gir1.2-aravis-0.8; its fake GigE Vision camera and arv-tool for the
# tests and for setting up a cell: aravis-tools, aravis-tools-cli), what building PyGObject in the
# virtual environment needs, Debian's Chromium, PostgreSQL, Redis and poppler-utils (the tests that
# drive them: pass --with-browser), and a
# virtual environment in .venv. Packages already installed are not asked for again.
set -euo pipefail
cd "$(dirname "$0")/.."
packages=(gir1.2-aravis-0.8 aravis-tools aravis-tools-cli libgirepository1.0-dev libcairo2-dev pkg-config gcc)
[ "${1:-}" = "--with-browser" ] && packages+=(chromium postgresql redis-server poppler-utils)
python3 -c 'import os, sys, sysconfig; sys.exit(not os.path.isfile(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
  || packages+=(python3-dev)
if command -v apt-get >/dev/null 2>&1; then
  missing=()
  for package in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" || missing+=("$package")
  done
  if [ "${#missing[@]}" -gt 0 ]; then
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
  fi
fi
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# Exact versions from the lock file (regenerate it with scripts/lock.sh), then the project itself.
.venv/bin/python -m pip install -q -r requirements.lock
.venv/bin/python -m pip install -q --no-deps -e .
# Compile the numba kernels into their on-disk cache now, not inside the first inspection or job (a
# cache older than the sources is dropped first: pipeline.parallel.drop_stale_kernels).
.venv/bin/python -c "from pipeline.run import warm_up; print(f'kernels compiled and cached ({warm_up(full=True):.0f} s)')"
