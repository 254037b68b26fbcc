#!/usr/bin/env bash
# The suite again under AddressSanitizer + UndefinedBehaviorSanitizer (clang, with the libFuzzer targets in
# the same build), then every fuzz target briefly on its seed corpus (FUZZ_SECONDS each, default 60).
# CI runs this after scripts/test.sh. A long fuzzing campaign: FUZZ_SECONDS=1800 bash scripts/sanitize.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
CC=clang CXX=clang++ cmake -S . -B build-asan -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCSCAM_BUILD_BENCH=OFF \
  -DCSCAM_FUZZ=ON >/dev/null
cmake --build build-asan -j"$(nproc)"
export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
secs=${FUZZ_SECONDS:-60}
for t in cl nc machine mesh; do
  work=$(mktemp -d)
  cp -r fuzz/corpus/$t/. "$work/"
  echo "fuzz: $t for ${secs}s"
  # New inputs go to a scratch copy of the corpus; a crash input is written to build-asan/ and fails CI.
  build-asan/fuzz/${t}_fuzz -max_total_time="$secs" -timeout=10 -rss_limit_mb=2048 -print_final_stats=1 \
    -artifact_prefix=build-asan/${t}_ "$work" 2>&1 | grep -E "stat::number_of_executed_units|ERROR|crash|Done" || true
  rm -rf "$work"
  if ls build-asan/${t}_crash-* build-asan/${t}_leak-* build-asan/${t}_timeout-* 2>/dev/null | grep -q .; then
    echo "fuzz: $t found a failing input (see build-asan/${t}_*)" >&2
    exit 1
  fi
done
ctest --test-dir build-asan --output-on-failure -j"$(nproc)"
