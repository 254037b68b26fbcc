#!/usr/bin/env bash
# Real CAM data: NX's variable-axis ball-mill finish on the Haas UMC-750 (B/C trunnion).
# NX's own post vs our conventional post, then conventional vs the C-space planner at cones 0, 5 and 25 deg,
# each planned program verified by back-simulation.
set -euo pipefail
cd "$(dirname "$0")/../.."
B=${BUILD:-build}
CL=examples/nx-haas-umc750/variable_axis.cls
mkdir -p out/nx
"$B/cscam" post "$CL" --machine haas-umc750 -o out/nx/conventional.ngc
"$B/cscam" stats out/nx/conventional.ngc examples/nx-haas-umc750/variable_axis.nx-post.nc --machine haas-umc750
for cone in 0 5 25; do
  echo "== cone $cone deg"
  "$B/cscam" compare "$CL" --machine haas-umc750 --cone "$cone" -o "out/nx/planned-cone$cone.ngc" \
    --json-out "out/nx/compare-cone$cone.json" --svg "out/nx/svg-cone$cone"
  "$B/cscam" verify "out/nx/planned-cone$cone.ngc" --machine haas-umc750 --cl "$CL" --cone "$cone"
done
