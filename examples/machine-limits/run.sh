#!/usr/bin/env bash
# Only the machine rules these orientations out: a ball-mill finish of a low block's side wall with a horizontal
# tool axis on the Haas UMC-750. The part never touches the tool; the holder and the spindle head would hit the
# platter. Compare the plan with and without the machine file's bodies.
set -euo pipefail
cd "$(dirname "$0")/../.."
B=${BUILD:-build}
CL=examples/machine-limits/wall.cls
PART=examples/machine-limits/block.stl
CONE=${CONE:-60}
mkdir -p out/machine-limits
echo "== with machine geometry (cone $CONE deg)"
"$B/cscam" compare "$CL" --machine haas-umc750 --part "$PART" --cone "$CONE" \
  --json-out out/machine-limits/compare.json -o out/machine-limits/planned.ngc
echo "== the planner told to ignore the machine: it keeps the horizontal CL axis"
# The report's collision count and the safety gate still check the machine bodies: the program would drive the
# holder and the spindle head into the platter, so the gate refuses to write it (exit status 2, no file).
rm -f out/machine-limits/planned-no-machine.ngc
if "$B/cscam" compare "$CL" --machine haas-umc750 --part "$PART" --cone "$CONE" --no-machine-geometry \
  --json-out out/machine-limits/compare-no-machine.json -o out/machine-limits/planned-no-machine.ngc; then
  echo "unexpected: the colliding program was written" >&2
  exit 1
fi
test ! -e out/machine-limits/planned-no-machine.ngc
echo "(refused, as it must be)"
