#!/usr/bin/env bash
# Installs what pseudotwin needs on a fresh machine: a virtualenv with the package and its
# test tools, the Mosquitto broker (the demo and the tests run a real one) and the
# PostgreSQL server binaries (the store tests initdb a throwaway cluster), and Chromium (the
# commissioning report's test renders it headless).
# Idempotent and quiet when everything is already there.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    echo "bootstrap: creating .venv" >&2
    "$PY" -m venv .venv
fi
stamp=.venv/.pseudotwin-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ deploy/constraints.txt -nt "$stamp" ]; then
    echo "bootstrap: installing pseudotwin and its dependencies into .venv" >&2
    .venv/bin/python -m pip install -q --upgrade pip >/dev/null
    # The dependencies at the versions the daemon image is built with (test tools float).
    .venv/bin/python -m pip install -q -e '.[test]' -c deploy/constraints.txt
    touch "$stamp"
fi

# apt_install PACKAGE WHY: Debian's package, when the machine lacks it.
apt_install() {
    echo "bootstrap: installing $1 (apt; $2)" >&2
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "$1" >/dev/null
}

# The Debian package starts a system broker on 1883; the demo and tests start their own.
if ! command -v mosquitto >/dev/null 2>&1 && [ ! -x /usr/sbin/mosquitto ]; then
    apt_install mosquitto "the demo and the tests run a real broker"
fi
# Debian may start a system cluster on 5432; the tests initdb their own on a free port.
if ! command -v initdb >/dev/null 2>&1 && ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then
    apt_install postgresql "the store tests start their own PostgreSQL server"
fi
if ! command -v chromium >/dev/null 2>&1 && [ ! -x /usr/bin/chromium ]; then
    apt_install chromium "tests/test_commissioning.py renders the report in a headless browser"
fi
if ! command -v promtool >/dev/null 2>&1; then
    apt_install prometheus "its promtool checks deploy/prometheus.yml in tests/test_deploy.py"
fi
