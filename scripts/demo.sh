#!/usr/bin/env bash
# The main job: the daemon end to end on a real day of SML2010 (see scripts/demo.py).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/bootstrap.sh
exec .venv/bin/python scripts/demo.py "$@"
