#!/usr/bin/env bash
# ThreadSanitizer over the parallel parts, at CSCAM_THREADS=3: simulate's and diagnose's worker threads (their
# tests and a CLI simulate + diagnose run large enough to use the threads); the planner's TBB loops (cell
# enumeration and evaluation, the tier-4 beam, windows; the planner's tests that use collisions, and a CLI compare
# on the groove); batch posting (several files in parallel through the gate).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
cmake -S . -B build-tsan -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCSCAM_BUILD_BENCH=OFF -DCSCAM_TSAN=ON >/dev/null
cmake --build build-tsan -j"$(nproc)" --target sim_test diagnose_test plan_test cscam_cli
export TSAN_OPTIONS="halt_on_error=1" CSCAM_THREADS=3
build-tsan/tests/sim_test
build-tsan/tests/diagnose_test --gtest_filter=-*Committed*
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
build-tsan/cscam simulate examples/xmini/seed000_x_outback.cls --machine xmini --rate 700 --channels tip,enc \
  --inject backlash:q2:0.015 --noise tip:0.001 --seed 3 -o "$tmp/rec.csv"
build-tsan/cscam diagnose "$tmp/rec.csv" | tail -1
build-tsan/tests/plan_test --gtest_filter='PlannerIssue11.*:PlannerWindows.*:Planner.SeedGroove*:PlannerPictures.*'
build-tsan/cscam compare examples/groove/groove.cls --machine trunnion-ac --part examples/groove/groove.stl --cone 25 \
  -o "$tmp/groove.ngc" | tail -1
build-tsan/cscam post examples/nx-haas-umc750/*.cls examples/cl/*.cls --machine haas-umc750 -o "$tmp/batch/" | tail -3
echo "tsan: no data race reported"
