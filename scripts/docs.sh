#!/usr/bin/env bash
# Build the documentation site into docs/_build/html, warnings as errors (the docs tools come with
# the `dev` extra: bash scripts/setup.sh installs them).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
rm -rf docs/_build/html docs/_build/doctrees
"$PY" -m sphinx -W --keep-going -q -j auto -b html docs docs/_build/html "$@"
echo "docs: docs/_build/html/index.html"
