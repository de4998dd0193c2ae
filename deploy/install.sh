#!/usr/bin/env bash
# Installs cellctl as a systemd service on Debian 12:
#   - system user and group `cellctl` (no login, home /var/lib/cellctl);
#   - the project copied to PREFIX (default /opt/cellctl) with a virtual environment PREFIX/.venv
#     holding cellctl and its dependencies (from the configured package index);
#   - /etc/cellctl/cell.yaml from the virtual-cell example when absent (an existing one is kept;
#     a real cell's example: PREFIX/deploy/examples/real-cell.yaml), /etc/cellctl/tls/ for the
#     HTTPS certificate (documented place: /etc/cellctl/tls/cert.pem and key.pem);
#   - /var/lib/cellctl (store, session token) owned by cellctl;
#   - /etc/systemd/system/cellctl.service (deploy/cellctl.service, ExecStart under PREFIX), then
#     `systemctl daemon-reload` and `systemctl enable cellctl` when systemd runs this system;
#   - the compiled loops (renderer, matcher, calibration solver) warmed into numba's cache, the
#     unit's NUMBA_CACHE_DIR (/var/lib/cellctl/numba-cache), as the service user: `cellctl warm-up`,
#     about a minute of CPU, so the service's first start, frame and calibration do not compile.
# Re-running upgrades the copy and the venv and keeps the config and the data.
#
# Usage: sudo deploy/install.sh [--prefix DIR] [--root DIR] [--python PY] [--no-deps] [--no-aravis] [--postgres] [--ethernet-ip]
#                               [--no-warm-up]
#   --root DIR   install into the tree DIR (a chroot, an image, a test tree) instead of /: every
#                path above lives under DIR, the user is created in DIR/etc/passwd when that file
#                exists, and systemctl is never called. The venv's scripts then name DIR in their
#                first line: such a tree is for inspection or for running install.sh inside it. The
#                warm-up is skipped (numba keys its cache by the modules' paths, which differ inside
#                DIR); the command to run on the target is printed.
#   --no-deps    install cellctl alone into the venv, without its dependencies (tests; systems
#                where the dependencies come another way)
#   --no-aravis  leave out the GigE Vision binding (PyGObject; needs deploy/install-system-deps.sh)
#   --postgres   add the PostgreSQL driver (psycopg) for a plant-wide store (store.url:
#                postgresql+psycopg://...); the default SQLite store needs nothing
#   --ethernet-ip add cpppo for the EtherNet/IP tag server (plc.ethernet_ip; cpppo is GPL-3.0 or a
#                paid licence: docs/licences.md)
#   --no-warm-up skip `cellctl warm-up` (the service then compiles on its first start: /health
#                says `starting` for a minute or more)
# Debian packages the cell needs (Aravis, socat, ...): deploy/install-system-deps.sh (run it first).
set -euo pipefail

PREFIX=/opt/cellctl
ROOT=""
PY=${PYTHON:-python3}
DEPS=1
ARAVIS=1
POSTGRES=0
ETHERNET_IP=0
WARM=1
SERVICE_USER=cellctl
SRC=$(cd "$(dirname "$0")/.." && pwd)
ARGS="$*"

die() { echo "install: $*" >&2; exit 2; }
say() { echo "install: $*" >&2; }

while [ $# -gt 0 ]; do
  case "$1" in
    --prefix) [ $# -ge 2 ] || die "--prefix needs a directory"; PREFIX=$2; shift 2 ;;
    --root) [ $# -ge 2 ] || die "--root needs a directory"; ROOT=$2; shift 2 ;;
    --python) [ $# -ge 2 ] || die "--python needs an interpreter"; PY=$2; shift 2 ;;
    --no-deps) DEPS=0; shift ;;
    --no-aravis) ARAVIS=0; shift ;;
    --postgres) POSTGRES=1; shift ;;
    --ethernet-ip) ETHERNET_IP=1; shift ;;
    --no-warm-up) WARM=0; shift ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) die "unknown option $1; see --help" ;;
  esac
done

EXTRAS=""
[ "$ARAVIS" -eq 1 ] && EXTRAS=aravis
[ "$POSTGRES" -eq 1 ] && EXTRAS=${EXTRAS:+$EXTRAS,}postgres
[ "$ETHERNET_IP" -eq 1 ] && EXTRAS=${EXTRAS:+$EXTRAS,}ethernet-ip
EXTRAS=${EXTRAS:+[$EXTRAS]}

case "$PREFIX" in /*) ;; *) die "--prefix must be an absolute path, got $PREFIX" ;; esac
PREFIX=${PREFIX%/}
if [ -n "$ROOT" ]; then
  [ -d "$ROOT" ] || die "--root $ROOT: no such directory; create it first"
  ROOT=$(cd "$ROOT" && pwd)
  [ "$ROOT" = / ] && ROOT=""
fi
if [ -z "$ROOT" ] && [ "$(id -u)" -ne 0 ]; then
  die "installing a system service needs root: run  sudo $0 $ARGS"
fi
"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null ||
  die "cellctl needs Python >= 3.11; $PY is $("$PY" --version 2>&1 || echo missing) (try --python python3.11)"
[ -f "$SRC/pyproject.toml" ] && [ -d "$SRC/cellctl" ] || die "run this script from a cellctl checkout ($SRC is not one)"
# numba's cache: the unit's own setting, so that the warm-up fills the folder the service reads
NUMBA_CACHE=$(sed -n 's/^Environment=NUMBA_CACHE_DIR=//p' "$SRC/deploy/cellctl.service")
case "$NUMBA_CACHE" in /var/lib/cellctl/*) ;; *) die "deploy/cellctl.service sets no NUMBA_CACHE_DIR under /var/lib/cellctl" ;; esac

at() { printf '%s%s' "$ROOT" "$1"; }  # a system path inside the install root
DEST=$(at "$PREFIX")
[ "$(cd "$SRC" && pwd -P)" != "$(mkdir -p "$DEST" && cd "$DEST" && pwd -P)" ] ||
  die "the checkout is the install prefix itself ($DEST); run install.sh from another checkout"

# -- the service user ---------------------------------------------------------------------------------
uid_gid() {  # "uid:gid" of the service user in the root's /etc/passwd, empty when absent
  awk -F: -v u="$SERVICE_USER" '$1 == u { print $3 ":" $4 }' "$(at /etc/passwd)" 2>/dev/null || true
}
if [ -z "$(uid_gid)" ]; then
  if [ -z "$ROOT" ]; then
    useradd --system --user-group --home-dir /var/lib/cellctl --no-create-home \
      --shell /usr/sbin/nologin --comment "cellctl service" "$SERVICE_USER"
    say "created system user $SERVICE_USER"
  elif [ -f "$(at /etc/passwd)" ] && [ "$(id -u)" -eq 0 ]; then
    useradd --root "$ROOT" --system --user-group --home-dir /var/lib/cellctl --no-create-home \
      --shell /usr/sbin/nologin --comment "cellctl service" "$SERVICE_USER"
    say "created system user $SERVICE_USER in $ROOT/etc/passwd"
  else
    say "skipped creating user $SERVICE_USER: $ROOT/etc/passwd is absent (or not root); files keep their installing owner"
  fi
fi
OWNER=$(uid_gid)
own() {  # own USER|ROOTGROUP PATH...: chown to the service user, or root:service-group
  local who=$1; shift
  [ -n "$OWNER" ] && [ "$(id -u)" -eq 0 ] || return 0
  if [ "$who" = user ]; then chown "$OWNER" "$@"; else chown "0:${OWNER#*:}" "$@"; fi
}

# -- the project and its venv -------------------------------------------------------------------------
say "copying $SRC to $DEST"
for item in cellctl drivers calibration vision deploy; do
  rm -rf "${DEST:?}/$item"
done
(cd "$SRC" && tar -cf - --exclude='__pycache__' --exclude='*.pyc' pyproject.toml README.md \
  cellctl drivers calibration vision deploy) | (cd "$DEST" && tar -xf - --no-same-owner)
if [ ! -x "$DEST/.venv/bin/python" ]; then
  "$PY" -m venv "$DEST/.venv" ||
    die "cannot create the venv: on Debian install python3-venv (apt-get install -y python3-venv) and re-run"
fi
# the copy just made replaces the installed cellctl even when its version number did not change
"$DEST/.venv/bin/python" -m pip uninstall -q -y cellctl >/dev/null 2>&1 || true
if [ "$DEPS" -eq 1 ]; then
  say "installing cellctl$EXTRAS and its dependencies into $DEST/.venv"
  "$DEST/.venv/bin/python" -m pip install -q --upgrade pip
  "$DEST/.venv/bin/python" -m pip install -q --upgrade "$DEST$EXTRAS"
else
  say "installing cellctl alone (--no-deps) into $DEST/.venv"
  "$DEST/.venv/bin/python" -m pip install -q --no-deps "$DEST"
fi
rm -rf "$DEST/build" "$DEST"/*.egg-info
[ -x "$DEST/.venv/bin/cellctl" ] || die "the venv has no cellctl command after pip install; see pip's output above"
chmod -R u=rwX,go=rX "$DEST"

# -- config, TLS directory, data ----------------------------------------------------------------------
install -d -m 0755 "$(at /etc/cellctl)"
install -d -m 0750 "$(at /etc/cellctl/tls)"
own rootgroup "$(at /etc/cellctl/tls)"
CONFIG=$(at /etc/cellctl/cell.yaml)
if [ -e "$CONFIG" ]; then
  say "keeping the existing $CONFIG"
else
  install -m 0640 "$SRC/deploy/examples/virtual-cell.yaml" "$CONFIG"
  own rootgroup "$CONFIG"
  say "wrote $CONFIG (the virtual cell; deploy/examples/real-cell.yaml shows a real one)"
fi
install -d -m 0750 "$(at /var/lib/cellctl)" "$(at "$NUMBA_CACHE")"
own user "$(at /var/lib/cellctl)" "$(at "$NUMBA_CACHE")"

# -- the unit -----------------------------------------------------------------------------------------
install -d -m 0755 "$(at /etc/systemd/system)"
sed "s#/opt/cellctl#$PREFIX#g" "$SRC/deploy/cellctl.service" > "$(at /etc/systemd/system/cellctl.service)"
chmod 0644 "$(at /etc/systemd/system/cellctl.service)"
say "installed $(at /etc/systemd/system/cellctl.service)"

if [ -z "$ROOT" ] && [ -d /run/systemd/system ]; then
  systemctl daemon-reload
  systemctl enable cellctl.service
  say "enabled cellctl.service; start it with: systemctl start cellctl; logs: journalctl -u cellctl"
else
  say "systemd does not run here${ROOT:+ (--root $ROOT)}: skipped daemon-reload and enable; on the target" \
      "run: systemctl daemon-reload && systemctl enable --now cellctl"
fi
# -- the compiled loops --------------------------------------------------------------------------------
WARM_CMD=(env "NUMBA_CACHE_DIR=$NUMBA_CACHE" CELLCTL_DATA_DIR=/var/lib/cellctl "$PREFIX/.venv/bin/cellctl" warm-up)
if [ "$WARM" -eq 0 ]; then
  say "skipped the warm-up (--no-warm-up): the service compiles on its first start; to do it now run:" \
      "runuser -u $SERVICE_USER -- ${WARM_CMD[*]}"
elif [ -n "$ROOT" ]; then
  say "skipped the warm-up (--root): numba's cache is keyed by the modules' paths, which differ inside $ROOT;" \
      "on the target run: runuser -u $SERVICE_USER -- ${WARM_CMD[*]}"
else
  say "compiling the renderer's, matcher's and solver's loops into $NUMBA_CACHE (about a minute of CPU)"
  AS=()
  [ -n "$OWNER" ] && AS=(runuser -u "$SERVICE_USER" --)
  (cd /var/lib/cellctl && "${AS[@]}" "${WARM_CMD[@]}" >/dev/null) ||
    die "cellctl warm-up failed (its output is above); fix it, or re-run with --no-warm-up to compile on first start"
fi
say "done: $PREFIX/.venv/bin/cellctl serve --config /etc/cellctl/cell.yaml"
