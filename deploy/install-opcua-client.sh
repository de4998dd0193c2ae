#!/usr/bin/env bash
# Installs node-opcua (the npm registry's OPC UA client, pinned by tests/opcua_client/package-lock.json)
# into tests/opcua_client/node_modules: the OPC UA client of another stack than the server's that the
# Machine Vision tests drive as a PLC would. Needs node >= 18 and npm (deploy/install-system-deps.sh).
# Idempotent: nothing is fetched when the pinned version is installed.
set -euo pipefail
cd "$(dirname "$0")/../tests/opcua_client"

if ! command -v npm >/dev/null 2>&1 || ! command -v node >/dev/null 2>&1; then
  echo "install-opcua-client: node and npm are missing; run deploy/install-system-deps.sh as root" >&2
  exit 1
fi
want=$(node -p "require('./package.json').dependencies['node-opcua-client']")
have=$(node -p "require('node-opcua-client/package.json').version" 2>/dev/null || true)
if [ "$have" = "$want" ]; then
  echo "install-opcua-client: node-opcua present" >&2
  exit 0
fi
npm ci --no-audit --no-fund --loglevel=error >&2
echo "install-opcua-client: node-opcua installed in tests/opcua_client/node_modules" >&2
