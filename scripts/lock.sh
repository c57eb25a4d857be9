#!/usr/bin/env bash
# Regenerates requirements.lock: the exact versions of every Python package that scripts/setup.sh
# installs (the project's dependencies with the test, lint, camera and yard extras), resolved by
# pip-tools from pyproject.toml. Run it after changing a dependency in pyproject.toml, commit both.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/pip-compile ] || .venv/bin/python -m pip install -q pip-tools
.venv/bin/pip-compile -q --strip-extras --no-emit-index-url --extra test \
  --output-file requirements.lock pyproject.toml
# The project itself is installed by setup.sh from its checkout (pip install -e .), wherever that is:
# drop the self-reference pip-compile writes for the extras (a file:// URL of this machine's path).
sed -i '/^plate-inspect @ file:/,+1d' requirements.lock
