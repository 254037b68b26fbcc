#!/usr/bin/env bash
# Installs what is missing, builds, and runs the whole test suite with CTest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
bash scripts/build.sh -DCSCAM_BUILD_BENCH=OFF
ctest --test-dir build --output-on-failure -j"$(nproc)"
