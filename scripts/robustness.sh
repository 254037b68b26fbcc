#!/usr/bin/env bash
# Runs post and plan (cones 0, 3, 10) on generated CL files (scripts/generate_cl.py) for every bundled machine and
# prints one line per run: exit status and the first error. Exit status 1 is never expected; 2 (refused input)
# is a finding to read: a point out of reach or a collision with the machine is the machine's answer, but a
# program the post writes and the gate refuses, or a plan the post cannot follow, is a bug.
#   scripts/robustness.sh [SEED ...]      (default seeds: 1 2 3)
set -uo pipefail
cd "$(dirname "$0")/.."
CSCAM=${CSCAM:-$PWD/build/cscam}
[[ -x "$CSCAM" ]] || { echo "$CSCAM: not built" >&2; exit 2; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
seeds=("$@")
[[ ${#seeds[@]} -gt 0 ]] || seeds=(1 2 3)
for seed in "${seeds[@]}"; do
  mkdir -p "$work/$seed"
  python3 scripts/generate_cl.py "$work/$seed" "$seed"
done
for cl in "$work"/*/*.cls; do
  name="$(basename "$(dirname "$cl")")/$(basename "$cl")"
  for m in haas-umc750 trunnion-ac head-table-bc45 head-head-ac xmini; do
    out=$("$CSCAM" post "$cl" --machine "$m" -o "$work/o.ngc" 2>&1)
    echo "post $name $m: $? $(grep -m1 -E '^error|internal' <<<"$out" | cut -c1-200)"
    for cone in 0 3 10; do
      out=$(timeout 300 "$CSCAM" plan "$cl" --machine "$m" --cone "$cone" -o "$work/p.ngc" 2>&1)
      echo "plan $name $m cone $cone: $? $(grep -m1 -E '^error|internal' <<<"$out" | cut -c1-200)"
    done
  done
done
