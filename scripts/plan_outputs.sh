#!/usr/bin/env bash
# Records everything the C-space planner produces on the bundled examples, or compares a new build against such a
# record (to show that a refactoring changed no output):
#   scripts/plan_outputs.sh record DIR    # run every case, store normalised outputs in DIR
#   scripts/plan_outputs.sh compare DIR   # run again into a temporary directory and diff against DIR
# Each case is a `compare` run (stdout, stderr, exit status, --json-out, the planned NC from -o, and for some cases
# the --svg pictures) or a `plan` run. Timings and peak memory are masked; everything else must match byte for
# byte, query counters included. Environment: BUILD (default build) or CSCAM (the binary), JOBS (parallel cases,
# default 2),
# PLAN_OUTPUTS_SVG=0 to leave the C-space pictures out (they change when the picture itself changes).
# Outputs known to vary from run to run (listed, not counted). Empty: the XMINI cone-0 plans' F words once
# alternated (F1200.000 / F1199.999, rounding down a value a few ulps either side); the post's feed floor has a
# relative slack since (src/post/post.cpp kFeedFloorSlack).
KNOWN_VARYING=()
set -euo pipefail
cd "$(dirname "$0")/.."
mode=${1:-}
dir=${2:-}
if [[ "$mode" != record && "$mode" != compare || -z "$dir" ]]; then
  echo "usage: $0 record|compare DIR" >&2
  exit 2
fi
dir=$(realpath -m "$dir")
B=${BUILD:-build}
CSCAM=${CSCAM:-$PWD/$B/cscam}
[[ -x "$CSCAM" ]] || { echo "$CSCAM: not built" >&2; exit 2; }
SVG=${PLAN_OUTPUTS_SVG:-1}

# name | command (compare or plan) | arguments | svg (1: also --svg)
cases() {
  local machines="haas-umc750 trunnion-ac head-table-bc45 head-head-ac"
  local cls="examples/cl/iso_catia.cls examples/cl/points_csv.cls examples/groove/groove.cls
             examples/machine-limits/wall.cls examples/nx-haas-umc750/variable_axis.cls
             examples/nx-haas-umc750/zigzag_smoothed.cls tests/data/lcnc-trace/nx_variable_axis_head.cls"
  local cl m cone
  for cl in $cls; do
    for m in $machines; do
      for cone in 0 5; do
        echo "$(basename "$cl" .cls)-$m-cone$cone|compare|$cl --machine $m --cone $cone|0"
      done
    done
  done
  for cl in seed000_x_cut seed000_x_cut_offset seed000_x_outback; do
    echo "$cl-xmini-cone0|compare|examples/xmini/$cl.cls --machine xmini --cone 0|0"
    echo "$cl-xmini-cone1|compare|examples/xmini/$cl.cls --machine xmini --cone 1 --resolution 0.25 --tilt-step 0.05|0"
  done
  local groove="examples/groove/groove.cls --machine trunnion-ac --part examples/groove/groove.stl"
  echo "groove-part-cone25|compare|$groove --cone 25|1"
  echo "groove-part-cone25-nocollision|compare|$groove --cone 25 --no-collision|0"
  echo "groove-part-cone10|compare|$groove --cone 10|0"
  echo "groove-part-cone0|compare|$groove --cone 0|0"
  echo "groove-part-cone25-plan|plan|$groove --cone 25|0"
  local wall="examples/machine-limits/wall.cls --machine haas-umc750 --part examples/machine-limits/block.stl"
  echo "wall-part-cone60|compare|$wall --cone 60|1"
  echo "wall-part-cone60-nomachine|compare|$wall --cone 60 --no-machine-geometry|0"
  echo "nx-haas-cone5-svg|compare|examples/nx-haas-umc750/variable_axis.cls --machine haas-umc750 --cone 5|1"
  echo "nx-haas-cone25|compare|examples/nx-haas-umc750/variable_axis.cls --machine haas-umc750 --cone 25|1"
  echo "iso-haas-cone0-plan|plan|examples/cl/iso_catia.cls --machine haas-umc750|0"
}

# Runs one case into $out/NAME.*; paths of $out become OUT/, timings and memory are masked.
run_case() {
  local out=$1 line=$2
  local name cmd args svg
  IFS='|' read -r name cmd args svg <<<"$line"
  local extra=(-o "$out/$name.ngc")
  [[ "$cmd" == compare ]] && extra+=(--json-out "$out/$name.json")
  [[ "$svg" == 1 && "$SVG" == 1 ]] && extra+=(--svg "$out/$name.svg")
  local rc=0
  # shellcheck disable=SC2086
  CSCAM_THREADS=${CSCAM_THREADS:-2} "$CSCAM" $cmd $args "${extra[@]}" >"$out/$name.stdout" 2>"$out/$name.stderr" || rc=$?
  echo "$rc" >"$out/$name.rc"
  local f
  for f in "$out/$name.stdout" "$out/$name.stderr"; do
    sed -i -E -e "s#$out/#OUT/#g" \
      -e 's/^(time \(s\) +)[0-9. ]+$/\1<time>/' \
      -e 's/peak memory [0-9]+ MB/peak memory <mem> MB/g' \
      -e 's/^planner: [0-9.]+ s,/planner: <time> s,/' "$f"
  done
  if [[ -f "$out/$name.json" ]]; then
    jq -S 'del(.conventional.seconds, .planner.seconds, .planner.peak_memory_mb)' "$out/$name.json" |
      sed -e "s#$out/#OUT/#g" >"$out/$name.json.tmp"
    mv "$out/$name.json.tmp" "$out/$name.json"
  fi
}
export -f run_case
export CSCAM SVG

run_all() {
  local out=$1
  mkdir -p "$out"
  cases | xargs -d '\n' -P "${JOBS:-2}" -I{} bash -c 'run_case "$1" "$2"' _ "$out" {}
  cases | cut -d'|' -f1 >"$out/CASES"
}

if [[ "$mode" == record ]]; then
  rm -rf "$dir"
  run_all "$dir"
  echo "recorded $(wc -l <"$dir/CASES") cases in $dir"
  exit 0
fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
run_all "$tmp/now"
# Compare file by file (the masked paths make both runs name OUT/).
excl=()
[[ "$SVG" == 1 ]] || excl=(-x '*.svg')
if diff -r "${excl[@]}" "$dir" "$tmp/now" >"$tmp/diff"; then
  echo "identical: $(wc -l <"$dir/CASES") cases, $(find "$dir" -type f | wc -l) files"
  exit 0
fi
known=()
for k in "${KNOWN_VARYING[@]}"; do known+=(-e "$k"); done
if ((${#known[@]})); then
  differing=$(grep -E '^diff|^Only' "$tmp/diff" | grep -v -F "${known[@]}" || true)
else
  differing=$(grep -E '^diff|^Only' "$tmp/diff" || true)
fi
if [[ -z "$differing" ]]; then
  echo "identical: $(wc -l <"$dir/CASES") cases, $(find "$dir" -type f | wc -l) files, except these, which vary" \
    "from run to run (the baseline's too):"
  grep -E '^diff|^Only' "$tmp/diff"
  exit 0
fi
head -200 "$tmp/diff"
echo "--- differing files:"
echo "$differing" | sed -E 's/^diff -r .* [^ ]*\/now\//  /'
echo "DIFFERENT: $(echo "$differing" | wc -l) file(s) differ" >&2
exit 1
