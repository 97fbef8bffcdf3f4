#!/usr/bin/env bash
# Installs the Debian packages the test suite needs (PostgreSQL server, Chromium), once.
# Idempotent: does nothing when they are already present. Needs root (as on CI and dev machines).
set -euo pipefail
need=()
if ! ls /usr/lib/postgresql/*/bin/postgres >/dev/null 2>&1; then need+=(postgresql); fi
if ! command -v chromium >/dev/null 2>&1; then need+=(chromium); fi
if [ ${#need[@]} -eq 0 ]; then exit 0; fi
if [ "$(id -u)" -ne 0 ]; then
  echo "install_system_deps: need root to apt-get install ${need[*]}" >&2
  exit 1
fi
echo "install_system_deps: installing ${need[*]}"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
# The Debian package starts a cluster service we do not use; tests run their own server.
if command -v pg_ctlcluster >/dev/null 2>&1; then service postgresql stop >/dev/null 2>&1 || true; fi
