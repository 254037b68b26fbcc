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
  "$B/cscam" verify "out/xmini/$cut.conventional.ngc" --machine "$M" --cl "examples/xmini/$cut.cls"
done
echo "== conventional post: per-joint travel and reversals (whole program: approach, cut, retract)"
"$B/cscam" stats out/xmini/seed000_x_cut.conventional.ngc out/xmini/seed000_x_cut_offset.conventional.ngc --machine "$M"
echo "== a lost motion of 10 um on q2: the tip deviation it causes, per component"
"$B/cscam" backlash out/xmini/seed000_x_cut.conventional.ngc out/xmini/seed000_x_cut_offset.conventional.ngc \
  --machine "$M" --axis q2 --width-mm 0.010
