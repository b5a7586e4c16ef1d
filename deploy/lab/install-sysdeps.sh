#!/usr/bin/env bash
# Installs the Debian packages the network lab needs (nftables, iproute2) when missing,
# and a C compiler for the codec's C speed-ups (protocol/_speedups.c; `make test` runs this
# before the install, so that CI builds them).
# Needs root; outside CI a non-root user is told what to install and nothing fails here.
set -euo pipefail
need=()
command -v nft >/dev/null 2>&1 || need+=(nftables)
command -v ip  >/dev/null 2>&1 || need+=(iproute2)
command -v tc  >/dev/null 2>&1 || need+=(iproute2)
# the browser test of `crosspath view` (tests/view) loads the page in headless Chromium
command -v chromium >/dev/null 2>&1 || need+=(chromium)
# tests/deploy checks the units with `systemd-analyze verify` and `security` (only the tool)
command -v systemd-analyze >/dev/null 2>&1 || need+=(systemd)
command -v cc >/dev/null 2>&1 || need+=(gcc libc6-dev)
[ ${#need[@]} -eq 0 ] && exit 0
if [ "$(id -u)" -ne 0 ]; then
  echo "crosspath lab and view tests need: ${need[*]} (run as root, or install them yourself)" >&2
  if [ -n "${CI:-}" ]; then exit 1; fi
  exit 0
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
