#!/usr/bin/env bash
# Seed 000 on the XMINI (machines/xmini.yaml): the cut along X with a vertical tool, posted by the
# conventional post (joint space: legs U V W, wrist C A). Prints the per-joint travel and reversals,
# checks every program by FK inside every block, and simulates a 10 um lost motion on leg 2 (q2).
#  - seed000_x_cut.cls: y = 0, the line crosses the wrist singularity (a = 0) and the q2 minimum at x = 0;
#  - seed000_x_cut_offset.cls: the same line 0.05 mm off (y = 0.05), next to the singularity.
set -euo pipefail
cd "$(dirname "$0")/../.."
B=${BUILD:-build}
M=machines/xmini.yaml
mkdir -p out/xmini
for cut in seed000_x_cut seed000_x_cut_offset; do
  "$B/cscam" post "examples/xmini/$cut.cls" --machine "$M" -o "out/xmini/$cut.conventional.ngc"
  # The conventional post flips C by 180 deg at the singularity: verify reports the mark it leaves.
  "$B/cscam" verify "out/xmini/$cut.conventional.ngc" --machine "$M" --cl "examples/xmini/$cut.cls" || true
done
echo "== conventional post: per-joint travel and reversals (whole program: approach, cut, retract)"
"$B/cscam" stats out/xmini/seed000_x_cut.conventional.ngc out/xmini/seed000_x_cut_offset.conventional.ngc --machine "$M"
echo "== a lost motion of 10 um on q2: the tip deviation it causes, per component"
"$B/cscam" backlash out/xmini/seed000_x_cut.conventional.ngc out/xmini/seed000_x_cut_offset.conventional.ngc \
  --machine "$M" --axis q2 --width-mm 0.010
echo "== the C-space planner: cone 0 (exact orientation, square end mill) and a 1 deg cone (ball mill)"
"$B/cscam" compare examples/xmini/seed000_x_cut.cls --machine "$M" --cone 0 -o out/xmini/seed000_x_cut.cone0.ngc \
  --json-out out/xmini/compare-cone0.json
"$B/cscam" compare examples/xmini/seed000_x_cut.cls --machine "$M" --cone 1 --resolution 0.25 --tilt-step 0.05 \
  -o out/xmini/seed000_x_cut.cone1.ngc --json-out out/xmini/compare-cone1.json
"$B/cscam" verify out/xmini/seed000_x_cut.cone1.ngc --machine "$M" --cl examples/xmini/seed000_x_cut.cls --cone 1
echo "== the consequence: 10 um of lost motion on q2, conventional vs planned (cone 0, cone 1)"
"$B/cscam" backlash out/xmini/seed000_x_cut.conventional.ngc out/xmini/seed000_x_cut.cone0.ngc \
  out/xmini/seed000_x_cut.cone1.ngc --machine "$M" --axis q2 --width-mm 0.010 | tail -8
