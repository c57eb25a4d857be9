#!/usr/bin/env bash
# Installs everything (Chromium from apt, Python packages in .venv) and runs the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --with-browser
# One worker process per core (pytest-xdist), each test file in one worker (its module-scoped
# fixtures, e.g. the browser's live server and the simulated captures, built once).
exec .venv/bin/python -m pytest -n auto --dist loadfile "$@"
