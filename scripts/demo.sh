#!/usr/bin/env bash
# Installs everything and starts the dashboard on a simulated cell with an embedded SQLite database.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/plate-inspect serve --demo "$@"
