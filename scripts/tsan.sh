#!/usr/bin/env bash
# ThreadSanitizer over the parallel parts (simulate's and diagnose's worker threads, CSCAM_THREADS=3):
# their tests and a CLI simulate + diagnose run large enough to use the threads.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
cmake -S . -B build-tsan -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCSCAM_BUILD_BENCH=OFF -DCSCAM_TSAN=ON >/dev/null
cmake --build build-tsan -j"$(nproc)" --target sim_test diagnose_test cscam_cli
export TSAN_OPTIONS="halt_on_error=1" CSCAM_THREADS=3
build-tsan/tests/sim_test
build-tsan/tests/diagnose_test --gtest_filter=-*Committed*
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
build-tsan/cscam simulate examples/xmini/seed000_x_outback.cls --machine xmini --rate 700 --channels tip,enc \
  --inject backlash:q2:0.015 --noise tip:0.001 --seed 3 -o "$tmp/rec.csv"
build-tsan/cscam diagnose "$tmp/rec.csv" | tail -1
echo "tsan: no data race reported"
