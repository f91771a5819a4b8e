#!/usr/bin/env bash
# Install what a fresh machine lacks for lpvid: the Cortex-M target and Debian packages.
# Idempotent: does nothing when everything is present.
set -euo pipefail

need_apt=()
for pkg in "$@"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
if [ ${#need_apt[@]} -gt 0 ]; then
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  echo "setup: installing Debian packages: ${need_apt[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

if command -v rustup >/dev/null 2>&1; then
  if ! rustup target list --installed | grep -qx thumbv7em-none-eabihf; then
    echo "setup: adding the thumbv7em-none-eabihf target"
    rustup target add thumbv7em-none-eabihf
  fi
  for comp in rustfmt clippy; do
    rustup component list --installed 2>/dev/null | grep -q "^$comp" || rustup component add "$comp"
  done
fi
