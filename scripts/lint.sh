#!/usr/bin/env bash
# The lint step CI runs before the tests (and the pre-commit hooks run on a commit): ruff's lint
# rules and formatter on the whole tree, mypy in strict mode on pipeline/, app/ and web/
# (configured in pyproject.toml). Needs the virtual environment of scripts/setup.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/mypy
