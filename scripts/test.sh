#!/usr/bin/env bash
# Installs everything (Chromium from apt, Python packages in .venv) and runs the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --with-browser
exec .venv/bin/python -m pytest "$@"
