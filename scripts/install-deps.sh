#!/usr/bin/env bash
# Installs every Debian 12 package cspace-cam needs to build, test and benchmark. Run as root.
set -euo pipefail
PKGS=(build-essential cmake ninja-build ccache pkg-config
      libeigen3-dev libfcl-dev libccd-dev libassimp-dev libcgal-dev libyaml-cpp-dev libcli11-dev libfmt-dev libtbb-dev
      libceres-dev libgtest-dev libgmock-dev libbenchmark-dev
      linuxcnc-uspace)
missing=()
for p in "${PKGS[@]}"; do dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p"); done
if [ ${#missing[@]} -gt 0 ]; then
  echo "installing: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q
  apt-get install -y -q --no-install-recommends "${missing[@]}"
fi
