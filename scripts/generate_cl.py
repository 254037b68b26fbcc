#!/usr/bin/env python3
"""Generates CL files of kinds the bundled examples do not cover, for robustness runs (scripts/robustness.sh).

    scripts/generate_cl.py OUTDIR [SEED]

Writes into OUTDIR:
  hemi.cls    a spiral over a hemisphere, the tool normal to it, tilting 0 -> 70 deg over 8 turns (a head C
              with limits of +-360 deg must unwind or flip)
  zig.cls     a zigzag across the vertical with small tilts
  blades.cls  six blade-like passes at 45 deg tilt, the azimuth turning with the pass
  walk.cls    a random walk of 1500 points: steps of 0.5 mm, tilt 0..69 deg, the axis passing the vertical
              (segments shorter than the tolerance, reversals beside themselves)
  side.cls    side milling with a horizontal tool
  rSEED.cls   a random walk with random step and axis scales, random rapids, mm or inch
The same SEED gives the same files.
"""
import math
import os
import random
import sys


def write(path, pts, units="MM", feed="MMPM,1500", partno="GENERATED"):
    with open(path, "w") as f:
        f.write(f"PARTNO {partno}\nUNITS/{units}\nMULTAX/ON\nCUTTER/6,3\nLOADTL/1\nSPINDL/8000,CLW\nFEDRAT/{feed}\n")
        for p in pts:
            if p is None:
                f.write("RAPID\n")
                continue
            x, y, z, i, j, k = p
            n = math.sqrt(i * i + j * j + k * k)
            f.write("GOTO/%.4f,%.4f,%.4f,%.6f,%.6f,%.6f\n" % (x, y, z, i / n, j / n, k / n))
        f.write("FINI\n")


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 1
    rng = random.Random(seed)
    pts = [None]
    for t in range(600):
        th = math.radians(70) * t / 599
        ph = 2 * math.pi * 8 * t / 599
        n = (math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th))
        pts.append((30 * n[0], 30 * n[1], 30 * n[2] - 10, *n))
    write(f"{out}/hemi.cls", pts, partno="HEMISPHERE SPIRAL")
    pts = []
    for r in range(8):
        pts.append(None)
        for c in range(60):
            u, v = -1 + 2 * c / 59, -1 + 2 * r / 7
            if r % 2:
                u = -u
            pts.append((40 * u, 40 * v, 5 * u * v, 0.4 * u + 0.05 * v, 0.3 * v - 0.02 * u, 1))
    write(f"{out}/zig.cls", pts, partno="ZIGZAG")
    pts = []
    for b in range(6):
        pts.append(None)
        a0 = 2 * math.pi * b / 6
        for s in range(80):
            a, rr = a0 + 0.8 * s / 79, 20 + 25 * s / 79
            pts.append((rr * math.cos(a), rr * math.sin(a), 10 - 8 * s / 79, math.cos(a + 1.2), math.sin(a + 1.2), 1.0))
    write(f"{out}/blades.cls", pts, partno="BLADES")
    pts, th, ph, x, y = [None], 0.2, 0.0, 0.0, 0.0
    for _ in range(1500):
        th = min(max(th + rng.gauss(0, 0.01), 0), 1.2)
        ph += rng.gauss(0, 0.05)
        x += rng.gauss(0, 0.5)
        y += rng.gauss(0, 0.5)
        pts.append((x, y, 0, math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)))
    write(f"{out}/walk.cls", pts, partno="RANDOM WALK")
    pts = [None]
    for s in range(200):
        a = 2 * math.pi * s / 199
        pts.append((30 * math.cos(a), 30 * math.sin(a), -5, math.cos(a), math.sin(a), 0.0))
    write(f"{out}/side.cls", pts, partno="SIDE MILLING")
    pts, th, ph, x, y, z = [None], rng.uniform(0, 0.5), rng.uniform(-3, 3), 0.0, 0.0, 20.0
    smax, amax = rng.choice([0.05, 0.3, 1.0]), rng.choice([0.005, 0.02, 0.05])
    for _ in range(800):
        th = min(max(th + rng.gauss(0, amax), 0), 1.0)
        ph += rng.gauss(0, amax * 5)
        x += rng.gauss(0, smax)
        y += rng.gauss(0, smax)
        z += rng.gauss(0, smax * 0.2)
        if rng.random() < 0.01:
            pts.append(None)
            z += 2
        pts.append((x, y, z, math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)))
    inch = rng.random() < 0.3
    write(f"{out}/r{seed}.cls", pts, units="INCH" if inch else "MM", feed="IPM,60" if inch else "MMPM,1500",
          partno=f"RANDOM {seed}")


if __name__ == "__main__":
    main()
