#!/usr/bin/env bash
# scripts/batch-parallel.sh on a few files: outputs equal single `cscam post` runs, the same bytes at any number
# of processes, a summary in input order, and exit codes that say what happened (0 / 2 refused / 3 error).
# Usage: batch_parallel_test.sh CSCAM SOURCE_DIR
set -uo pipefail
cscam="$1" src="$2"
script="$src/scripts/batch-parallel.sh"
tmp="$(mktemp -d "${TMPDIR:-/tmp}/cscam_batch_parallel.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT
fail() { echo "FAIL: $*" >&2; exit 1; }

mkdir -p "$tmp/cl"
cp "$src/examples/groove/groove.cls" "$src/examples/nx-haas-umc750/variable_axis.cls" \
  "$src/examples/nx-haas-umc750/zigzag_smoothed.cls" "$tmp/cl/"
printf 'UNITS/MM\nMULTAX\nGOTO/1,2,3,0,0,1\nGOTO/1,2,x3,0,0,1\n' >"$tmp/cl/bad.cls"
good=("$tmp/cl/groove.cls" "$tmp/cl/variable_axis.cls" "$tmp/cl/zigzag_smoothed.cls")

# The oracle: one cscam post per file.
mkdir -p "$tmp/single"
for f in "${good[@]}"; do
  "$cscam" post "$f" -m haas-umc750 --tolerance 0.005 -o "$tmp/single/$(basename "${f%.*}").ngc" >/dev/null ||
    fail "single post of $f"
done

# All good: exit 0, outputs identical to the single runs, at 1 and 3 processes.
for j in 1 3; do
  "$script" -c "$cscam" -m haas-umc750 -o "$tmp/out$j" -j $j "${good[@]}" -- --tolerance 0.005 2>"$tmp/err$j"
  rc=$?
  [[ $rc == 0 ]] || fail "all-good batch at -j $j exited $rc: $(cat "$tmp/err$j")"
  for f in "${good[@]}"; do
    n="$(basename "${f%.*}").ngc"
    cmp -s "$tmp/single/$n" "$tmp/out$j/$n" || fail "$n at -j $j differs from the single run"
  done
  [[ $(ls "$tmp/out$j"/.*.tmp.* 2>/dev/null | wc -l) == 0 ]] || fail "temporary files left behind"
done
cmp -s "$tmp/out1/summary.tsv" <(sed "s|$tmp/out3|$tmp/out1|" "$tmp/out3/summary.tsv") || fail "summary depends on -j"

# One bad file (files read from stdin): the others are converted, exit 2, the summary names the bad one.
printf '%s\n' "$tmp/cl/bad.cls" "${good[@]}" |
  "$script" -c "$cscam" -m haas-umc750 -o "$tmp/mixed" -j 2 -- --tolerance 0.005 2>"$tmp/err_mixed"
rc=$?
[[ $rc == 2 ]] || fail "a refused file must exit 2, got $rc: $(cat "$tmp/err_mixed")"
[[ ! -e "$tmp/mixed/bad.ngc" ]] || fail "bad.ngc written"
head -n2 "$tmp/mixed/summary.tsv" | tail -n1 | grep -q $'bad.cls\trefused\t2\t-' || fail "summary row of bad.cls: $(cat "$tmp/mixed/summary.tsv")"
grep -q 'bad.cls:4:' "$tmp/err_mixed" || fail "the error of bad.cls is not shown: $(cat "$tmp/err_mixed")"
for f in "${good[@]}"; do cmp -s "$tmp/single/$(basename "${f%.*}").ngc" "$tmp/mixed/$(basename "${f%.*}").ngc" ||
  fail "$f not converted next to a bad file"; done

# A run that dies for another reason (here a cscam that crashes): exit 3.
printf '#!/bin/sh\nkill -SEGV $$\n' >"$tmp/crash" && chmod +x "$tmp/crash"
"$script" -c "$tmp/crash" -m haas-umc750 -o "$tmp/crashed" "${good[0]}" 2>/dev/null
rc=$?
[[ $rc == 3 ]] || fail "a crashing run must exit 3, got $rc"
grep -q $'\terror\t' "$tmp/crashed/summary.tsv" || fail "crash not in the summary"

# Two files with one stem, or no files: refused before anything runs.
mkdir -p "$tmp/cl2" && cp "$tmp/cl/groove.cls" "$tmp/cl2/"
"$script" -c "$cscam" -m haas-umc750 -o "$tmp/twins" "$tmp/cl/groove.cls" "$tmp/cl2/groove.cls" 2>/dev/null
[[ $? == 2 ]] || fail "two files with one stem must exit 2"
[[ ! -e "$tmp/twins" ]] || fail "the output directory was made for a refused batch"
echo "batch-parallel: all checks passed"
