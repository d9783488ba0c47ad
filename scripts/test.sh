#!/usr/bin/env bash
# The whole test suite: lint, types (mypy, settings in pyproject.toml), then pytest (real Mosquitto, real GPy fits, real statsmodels).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/bootstrap.sh
.venv/bin/ruff check daemon tests scripts
.venv/bin/mypy
exec .venv/bin/pytest -q "$@"
