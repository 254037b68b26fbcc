#!/usr/bin/env bash
# The main job on a bundled example: NX's real CL file -> G-code for the Haas UMC-750 -> verified by FK,
# checked by LinuxCNC's rs274, compared with NX's own post output, then planned in the rotary C-space.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p out
CL=examples/nx-haas-umc750/variable_axis.cls
./build/cscam post "$CL" --machine haas-umc750 -o out/variable_axis.ngc
./build/cscam verify out/variable_axis.ngc --machine haas-umc750 --cl "$CL"
if command -v rs274 >/dev/null; then
  rs274 -g out/variable_axis.ngc >out/variable_axis.rs274.txt 2>&1 && ! grep -qi "error" out/variable_axis.rs274.txt \
    && echo "rs274 (LinuxCNC's interpreter) accepted out/variable_axis.ngc: $(grep -c STRAIGHT_ out/variable_axis.rs274.txt) moves"
fi
./build/cscam stats out/variable_axis.ngc examples/nx-haas-umc750/variable_axis.nx-post.nc --machine haas-umc750 | tee out/variable_axis.stats.txt
echo
echo "== the C-space planner on the same file, tool axis free within a 25 deg cone (ball mill: centre kept)"
./build/cscam compare "$CL" --machine haas-umc750 --cone 25 -o out/variable_axis.planned.ngc \
  --json-out out/variable_axis.compare.json --svg out/svg | tee out/variable_axis.compare.txt
echo
echo "NC files: out/variable_axis.ngc (conventional), out/variable_axis.planned.ngc (planner)"
echo "reports:  out/variable_axis.stats.txt, out/variable_axis.compare.txt, out/variable_axis.compare.json, out/svg/*.svg"
