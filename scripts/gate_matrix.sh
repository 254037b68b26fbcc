#!/usr/bin/env bash
# Posts every bundled example CL through every bundled machine; each must pass the safety gate or be
# refused with a clear error (and no file). Prints one line per pair. BUILD=dir selects the build.
set -uo pipefail
cd "$(dirname "$0")/.."
BUILD=${BUILD:-build}
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
for m in machines/*.yaml; do
  mn=$(basename "$m" .yaml)
  for f in examples/nx-haas-umc750/*.cls examples/cl/*.cls examples/groove/*.cls examples/xmini/*.cls; do
    b=$(basename "$f" .cls)
    msg=$("$BUILD/cscam" post "$f" --machine "$m" -o "$out/$mn.$b.ngc" 2>&1)
    rc=$?
    if [ $rc -eq 0 ]; then
      printf '%-16s %-22s passed  %s\n' "$mn" "$b" "$(echo "$msg" | grep '^gate' | cut -c1-110)"
    else
      [ -e "$out/$mn.$b.ngc" ] && echo "BUG: $mn $b refused but a file exists" && exit 1
      printf '%-16s %-22s REFUSED %s\n' "$mn" "$b" "$(echo "$msg" | grep '^error' | cut -c1-150)"
    fi
  done
done
