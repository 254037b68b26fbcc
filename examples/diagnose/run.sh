#!/usr/bin/env bash
# Regenerates the diagnosis examples: recordings made by `cscam simulate` with effects injected (the truth is
# written only in TRUTH.md, which the tool never reads), then diagnoses each one. Seeds are fixed, so the
# recordings are reproducible byte for byte.
#   BUILD=build-sim bash examples/diagnose/run.sh        # default build dir: build
set -euo pipefail
cd "$(dirname "$0")/../.."
B=${BUILD:-build}
D=examples/diagnose
X=machines/xmini.yaml
T=machines/trunnion-ac.yaml
sim() { "$B/cscam" simulate "$@" --decimals 5; }

# 1. Seed 000 on the XMINI: the X-direction cut, leg-2 lost motion, tooth-passing vibration, a geometric error.
sim examples/xmini/seed000_x_outback.cls -m $X -o $D/seed000_xmini.csv --rate 350 --channels tip \
  --inject backlash:q2:0.015 --inject vibration:tip.z:166.67:0.00322 --inject geometric:A1x=-150.15 \
  --noise tip:0.001 --spindle-rpm 5000 --flutes 2 --seed 1 --note "seed 000 X out and back, 150 mm/min"
# 2. Servo lag on one axis of the trunnion (ballbar circle, tip and encoders).
sim $D/circle.ngc -m $T -o $D/servo_lag.csv --rate 100 --channels tip,enc --inject servo_lag:y:0.002 \
  --noise tip:0.001 --noise enc:0.0002 --seed 2
# 3. Thermal drift of the XMINI tip during the cut.
sim examples/xmini/seed000_x_cut.cls -m $X -o $D/thermal_drift.csv --rate 50 --channels tip \
  --inject thermal_drift:tip.z:0.02:8 --noise tip:0.001 --seed 3
# 4. Two effects at once: backlash on y and a cyclic (screw pitch) error on x.
sim $D/circle.ngc -m $T -o $D/two_effects.csv --rate 100 --channels tip --inject backlash:y:0.006 \
  --inject cyclic:x:5:0.003:0 --noise tip:0.0005 --seed 4
# 5. Ballbar-style circle on the serial trunnion: backlash and a reversal spike.
sim $D/circle.ngc -m $T -o $D/ballbar.csv --rate 250 --channels tip --inject backlash:x:0.008 \
  --inject friction_spike:y:0.006:0.04 --noise tip:0.0005 --seed 5
# 6. Scale and squareness from a raster.
sim $D/raster.ngc -m $T -o $D/raster_scale_squareness.csv --rate 25 --channels tip --inject scale:x:40 \
  --inject squareness:x,y:60 --noise tip:0.0005 --seed 6
# 7. A screw that expands with the recorded bed temperature (which rises and falls within the run), beside an unrelated
#    spindle temperature that rises steadily.
sim $D/raster.ngc -m $T -o $D/raster_thermal.csv --rate 25 --channels tip,enc --temperatures $D/raster_temperatures.csv \
  --inject thermal_expansion:y:ppm_per_degC=12,sensor=bed --noise tip:0.0005 --noise enc:0.0001 --seed 8
# 8. Clean: noise only.
sim $D/circle.ngc -m $T -o $D/clean.csv --rate 100 --channels tip,enc --noise tip:0.001 --noise enc:0.0002 --seed 7

mkdir -p out/diagnose
for r in seed000_xmini servo_lag thermal_drift two_effects ballbar raster_scale_squareness raster_thermal clean; do
  echo "== $r"
  "$B/cscam" diagnose $D/$r.csv --json > out/diagnose/$r.json
  "$B/cscam" diagnose $D/$r.csv --svg out/diagnose/$r --write-model out/diagnose/$r.machine.yaml | tail -n +1
done
