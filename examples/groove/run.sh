#!/usr/bin/env bash
# Seed 002's experiment: conventional post vs C-space planner on the overhanging groove (A/C trunnion).
# Regenerates the part and the CL, then prints the comparison with and without collision pruning.
set -euo pipefail
cd "$(dirname "$0")/../.."
B=${BUILD:-build}
"$B/examples/make_groove" examples/groove
mkdir -p out/groove
echo "== with collision pruning (cone 25 deg)"
"$B/cscam" compare examples/groove/groove.cls --machine trunnion-ac --part examples/groove/groove.stl --cone 25 \
  --json-out out/groove/compare.json -o out/groove/planned.ngc --svg out/groove/svg
"$B/cscam" verify out/groove/planned.ngc --machine trunnion-ac --cl examples/groove/groove.cls --cone 25
echo "== without collision pruning: the same search, meshes ignored"
# The planned program then drives the tool through the lip; the safety gate checks it against the mesh and
# refuses to write it (exit status 2, no file): that refusal is the expected outcome here.
if "$B/cscam" compare examples/groove/groove.cls --machine trunnion-ac --part examples/groove/groove.stl \
  --cone 25 --no-collision --json-out out/groove/compare-nocollision.json -o out/groove/planned-nocollision.ngc; then
  echo "unexpected: the colliding program was written" >&2
  exit 1
fi
test ! -e out/groove/planned-nocollision.ngc
echo "(refused, as it must be)"
