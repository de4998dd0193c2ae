#!/usr/bin/env bash
# Sets up cellctl on a fresh Debian 12 machine: Debian packages (deploy/install-system-deps.sh),
# a virtual environment in .venv/ and the package with its test tools and the PostgreSQL driver
# (the store tests run a real PostgreSQL), and numba's disk cache of the compiled loops (renderer,
# matcher, calibration solver: about a minute of CPU the first time, seconds later), so the first
# frame, search and calibration do not compile. Idempotent; safe to re-run.
set -euo pipefail
cd "$(dirname "$0")/.."

bash deploy/install-system-deps.sh

PY=${PYTHON:-python3}
if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
  echo "setup: cellctl needs Python >= 3.11; $PY is $("$PY" --version 2>&1)" >&2
  exit 1
fi
if [ ! -x .venv/bin/python ]; then
  if ! "$PY" -m venv .venv 2>/dev/null; then
    rm -rf .venv
    if [ "$(id -u)" -eq 0 ]; then
      DEBIAN_FRONTEND=noninteractive apt-get install -y -q python3-venv >&2
    else
      echo "setup: run 'sudo apt-get install -y python3-venv' and re-run" >&2
      exit 1
    fi
    "$PY" -m venv .venv
  fi
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test,aravis,postgres,ethernet-ip]'
# pytest rewrites the asserts of its plugins' modules (schemathesis, hypothesis, anyio, xdist: ~250 of
# them) in every pytest process, about 2 s of CPU each, unless their rewritten caches exist; it writes
# none while PYTHONDONTWRITEBYTECODE is set (the variable is read before the suite's conftest turns
# writing back on). Write them once here (a package upgraded later is rewritten per run until set-up runs again).
env -u PYTHONDONTWRITEBYTECODE .venv/bin/python -m pytest --collect-only -q -p no:cacheprovider -o addopts= \
  tests/test_layers.py >/dev/null || echo "setup: pytest's plugin caches were not written (each run rewrites them)" >&2
# node-opcua for the OPC UA Machine Vision tests (the npm registry's client, pinned by its lock file)
bash deploy/install-opcua-client.sh
# Into __pycache__ beside the modules, or NUMBA_CACHE_DIR when set (the service must see the same).
echo "setup: compiling the renderer's, matcher's and solver's loops into numba's cache" >&2
.venv/bin/cellctl warm-up >/dev/null
echo "setup: ready (.venv/bin/cellctl)" >&2
