#!/usr/bin/env bash
# The whole test suite: lint, then pytest (real Mosquitto, real GPy fits, real statsmodels).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/bootstrap.sh
.venv/bin/ruff check daemon tests scripts
exec .venv/bin/pytest -q "$@"
