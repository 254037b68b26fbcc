#!/usr/bin/env bash
# Installs every Debian 12 package cspace-cam needs to build, test and benchmark. Run as root.
# CGAL (mesh validation and repair) and TBB (parallel planning and batch) are used; GNU parallel serves the batch-spreading script.
set -euo pipefail
PKGS=(build-essential cmake ninja-build ccache pkg-config
      libeigen3-dev libfcl-dev libccd-dev libassimp-dev libyaml-cpp-dev libcli11-dev libfmt-dev nlohmann-json3-dev
      libceres-dev libgtest-dev libgmock-dev libbenchmark-dev libfftw3-dev
      libtbb-dev libcgal-dev libgmp-dev libmpfr-dev parallel
      linuxcnc-uspace clang)
missing=()
for p in "${PKGS[@]}"; do dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p"); done
if [ ${#missing[@]} -gt 0 ]; then
  echo "installing: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q
  apt-get install -y -q --no-install-recommends "${missing[@]}"
fi
