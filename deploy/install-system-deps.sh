#!/usr/bin/env bash
# Installs the Debian 12 packages cellctl needs (drivers' peers, test tools). Idempotent: packages
# already installed are skipped and nothing is fetched when all are present.
# Needs root (apt-get); as another user it says which command to run with sudo.
set -euo pipefail

PACKAGES=(
  # GigE Vision cameras (Aravis 0.8 + the fake GigE camera for tests) and the PyGObject build deps
  libaravis-0.8-0 gir1.2-aravis-0.8 aravis-tools-cli aravis-tools
  libgirepository1.0-dev libcairo2-dev pkg-config
  # serial tests: pseudo-terminal pairs
  socat
  # README tour commands
  curl
  # network namespaces for loopback-only camera tests (unshare, ip)
  util-linux iproute2
  # store tests: a throwaway PostgreSQL cluster on loopback (plant-scale store backend)
  postgresql
  # deployment tests: systemd-analyze verify/security of deploy/cellctl.service; openssl for TLS test certs
  systemd openssl
  # operator web page tests: headless Chromium driven by Playwright (executable_path=/usr/bin/chromium)
  chromium chromium-driver
)

missing=()
for p in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

# node and npm: the OPC UA Machine Vision tests' client (node-opcua, deploy/install-opcua-client.sh).
# A machine that already has both (e.g. NodeSource's nodejs, which carries npm) keeps them.
if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
  missing+=(nodejs npm)
fi

if [ "${#missing[@]}" -eq 0 ]; then
  echo "install-system-deps: all ${#PACKAGES[@]} Debian packages present" >&2
  exit 0
fi

if [ "$(id -u)" -ne 0 ]; then
  echo "install-system-deps: missing Debian packages: ${missing[*]}" >&2
  echo "install-system-deps: run as root:  sudo apt-get update && sudo apt-get install -y ${missing[*]}" >&2
  exit 1
fi

echo "install-system-deps: installing ${missing[*]}" >&2
export DEBIAN_FRONTEND=noninteractive
apt-get update -q >&2
apt-get install -y -q --no-install-recommends "${missing[@]}" >&2
