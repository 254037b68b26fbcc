#!/usr/bin/python3
"""One case of the LinuxCNC motion-controller tests (ctest label `linuxcnc`).

Posts a CL file for trunnion-ac with cscam, runs the program in LinuxCNC's own motion controller
(scripts/linuxcnc/run_program.py: headless, one sample per servo cycle), and checks the sampled tip path
against the CL path with `cscam trace` (FK of the sampled joints, the post's tolerance).

  linuxcnc_test.py --cscam BIN --cl FILE [--feed MMPM] [--tcp] [--mdi 'G64 P0.01']
                   [--drop-g64p] [--drop-g61] [--uniform-blend] [--tolerance MM] --expect pass|fail [--min-deviation MM]
                   [--worst-at-plunge]

--expect fail is the demonstration that the check can fail: the deviation must then exceed
--min-deviation and, with --worst-at-plunge, lie where the plunge blends into the first cut.
Exit 0 when the expectation holds, 1 when not, 77 (ctest SKIP_RETURN_CODE) when LinuxCNC is not installed
or the post lacks the TCP form asked for.
"""
import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
RUN_PROGRAM = os.path.join(HERE, "..", "scripts", "linuxcnc", "run_program.py")
SKIP = 77
# TCP mode: LinuxCNC's xyzac-trt-kins world position against cscam's FK of the same joints (both models of the
# one machine; halsampler prints 6 decimals).
WORLD_MATCH_TCP_MM = 1e-3


def run(cmd, **kw):
    print("+ " + " ".join(cmd), flush=True)
    return subprocess.run(cmd, text=True, capture_output=True, **kw)


def tcp_program_from_cl(cl_text, joint_program, feed):
    """A stand-in for the post's LinuxCNC TCP form (until it writes one): M428, then every CL feed point's tip as
    world X Y Z with the rotary angles the posted joint-mode program chose for it. Valid only where the post
    inserted no points (one feed block per CL point): anything else is an error."""
    tips, kinds, kind = [], [], "rapid"
    for line in cl_text.splitlines():
        if line.startswith("RAPID"):
            kind = "rapid"
        elif line.startswith("FEDRAT"):
            kind = "feed"
        elif line.startswith("GOTO/"):
            tips.append([float(v) for v in line[5:].split(",")[:3]])
            kinds.append(kind)
            kind = "feed" if kind == "rapid" else kind  # RAPID applies to one motion
    angles, start = [], None
    for line in joint_program.splitlines():
        m = re.search(r"\bA(-?[0-9.]+)\s+C(-?[0-9.]+)", line) or re.search(r"\bC(-?[0-9.]+)\s+A(-?[0-9.]+)", line)
        if not m:
            continue
        a, c = (m.group(1), m.group(2)) if "A" + m.group(1) in line.replace(" ", "") else (m.group(2), m.group(1))
        if line.startswith("G0"):
            start = (a, c) if start is None else start
        else:
            angles.append((a, c))
    if kinds.count("rapid") != 1 or kinds[0] != "rapid" or start is None or len(angles) != len(tips) - 2:
        raise ValueError("TCP stand-in: needs one rapid approach and one feed block per CL point")
    out = ["%", "(TCP stand-in for the harness: CL tips in world coordinates after M428)",
           "G21 G90 G94 G17 G40 G49 G80", "T1 M6", "G43 H1", "M429", "G0 Z250", f"G0 A{start[0]} C{start[1]}",
           "M428", "G0 X%.4f Y%.4f Z%.4f" % tuple(tips[0]), "G1 X%.4f Y%.4f Z%.4f F%g" % (*tips[1], feed)]
    out += ["G1 X%.4f Y%.4f Z%.4f A%s C%s" % (*t, a, c) for t, (a, c) in zip(tips[2:], angles)]
    out += ["M429", "G0 Z250", "M2", "%"]
    return "\n".join(out) + "\n"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cscam", required=True)
    ap.add_argument("--cl", required=True)
    ap.add_argument("--machine", default="trunnion-ac")
    ap.add_argument("--feed", type=float, help="replace every FEDRAT/MMPM of the CL with this feed")
    ap.add_argument("--tcp", action="store_true", help="post with TCP on (LinuxCNC: M428 world coordinates)")
    ap.add_argument("--mdi", default="", help="MDI command before the program, e.g. 'G64 P0.01'")
    ap.add_argument("--tcp-stand-in", action="store_true",
                    help="run a TCP (M428) program built from the CL tips and the joint program's angles")
    ap.add_argument("--drop-g64p", action="store_true",
                    help="remove a G64 P word the post wrote (the controller then blends without a tolerance)")
    ap.add_argument("--drop-g61", action="store_true",
                    help="replace the G61 (exact path) words the post wrote around retracts and plunges by the "
                         "program's own G64 P")
    ap.add_argument("--uniform-blend", action="store_true",
                    help="give every block the program's first G64 P (undo the post's narrowed corners)")
    ap.add_argument("--tolerance", type=float, default=0.0,
                    help="tip tolerance for cscam trace, mm (default: the post's tolerance plus slack)")
    ap.add_argument("--expect", choices=["pass", "fail"], required=True)
    ap.add_argument("--min-deviation", type=float, default=0.0)
    ap.add_argument("--worst-at-plunge", action="store_true")
    ap.add_argument("--timeout", type=float, default=120)
    args = ap.parse_args()

    if shutil.which("linuxcnc") is None or shutil.which("halsampler") is None:
        print("SKIP: LinuxCNC (linuxcnc-uspace) is not installed")
        return SKIP

    with tempfile.TemporaryDirectory(prefix="cscam-lcnc-test-") as tmp:
        cl = args.cl
        if args.feed:
            with open(cl) as f:
                text = f.read()
            text, n = re.subn(r"FEDRAT/(MMPM,)?\s*[0-9.]+", f"FEDRAT/MMPM,{args.feed:g}", text)
            if n == 0:
                print(f"{cl}: no FEDRAT/ to replace")
                return 1
            cl = os.path.join(tmp, os.path.basename(cl))
            with open(cl, "w") as f:
                f.write(text)
        nc = os.path.join(tmp, "program.ngc")
        post = [args.cscam, "post", cl, "--machine", args.machine, "-o", nc]
        if args.tcp:
            if "--tcp" not in run([args.cscam, "post", "--help"]).stdout:
                print("SKIP: this cscam post has no --tcp (the LinuxCNC TCP form is not there yet)")
                return SKIP
            post.append("--tcp")
        p = run(post)
        print(p.stdout + p.stderr)
        if p.returncode != 0:
            return 1
        with open(nc) as f:
            program = f.read()
        if args.tcp and "M428" not in program:
            print("FAIL: --tcp program for LinuxCNC without M428")
            return 1
        if args.tcp_stand_in:
            with open(cl) as f:
                program = tcp_program_from_cl(f.read(), program, args.feed or 1000)
            with open(nc, "w") as f:
                f.write(program)
            args.tcp = True
        if args.drop_g61:
            # The cut blends into the retract as any corner would: at the program's own P (the header's), not at a
            # narrowed P that an earlier corner left in force.
            first = re.search(r"G64 P[0-9.]+", program)
            program, n = re.subn(r"\bG61 ", first.group(0) + " " if first else "", program)
            if n == 0:
                print("FAIL: --drop-g61 but the program has no G61")
                return 1
            with open(nc, "w") as f:
                f.write(program)
        if args.uniform_blend:
            first = re.search(r"G64 P[0-9.]+", program)
            narrowed = [w for w in re.findall(r"G64 P[0-9.]+", program) if w != first.group(0)] if first else []
            if not narrowed:
                print("FAIL: --uniform-blend but the program narrows no corner")
                return 1
            program = re.sub(r"G64 P[0-9.]+", first.group(0), program)
            with open(nc, "w") as f:
                f.write(program)
        if args.drop_g64p:
            program = re.sub(r"G64\s*P[0-9.]+(\s*Q[0-9.]+)?", "", program)
            with open(nc, "w") as f:
                f.write(program)

        samples = os.path.join(tmp, "samples.txt")
        cmd = [sys.executable, RUN_PROGRAM, nc, "-o", samples, "--timeout", str(args.timeout)]
        if args.mdi:
            cmd += ["--mdi", args.mdi]
        p = run(cmd)
        print(p.stdout + p.stderr)
        if p.returncode != 0:
            print("FAIL: the program did not run to its end in LinuxCNC")
            return 1

        trace = [args.cscam, "trace", samples, "--machine", args.machine, "--cl", cl, "--json"]
        if args.tolerance > 0:
            trace += ["--tolerance", str(args.tolerance)]
        if not args.tcp_stand_in:  # ours has no cscam header (machine, tool length)
            trace += ["--nc", nc]
        p = run(trace)
        if p.returncode not in (0, 1):
            print(p.stdout + p.stderr)
            return 1
        r = json.loads(p.stdout)
        print(r["message"])
        for b in r["worst_blocks"]:
            print(f"  NC line {b['nc_line']}: {b['max_tip_deviation_mm']:.4f} mm ({b['samples']} samples)")
        lines = program.splitlines()
        print(f"controller world vs cscam: {r['max_world_mismatch_mm']:.6f} mm over all samples, "
              f"{r['max_world_mismatch_tcp_mm']:.6f} mm over {r['tcp_samples']} TCP samples")
        if args.tcp and (r["tcp_samples"] == 0 or r["max_world_mismatch_tcp_mm"] > WORLD_MATCH_TCP_MM):
            print(f"FAIL: with TCP the controller's world X Y Z must be cscam's FK tip within {WORLD_MATCH_TCP_MM} mm")
            return 1
        if args.expect == "pass":
            if not r["ok"]:
                print("FAIL: expected the sampled path within tolerance")
                return 1
            return 0
        if r["ok"] or r["max_tip_deviation_mm"] < args.min_deviation:
            print(f"FAIL: expected the check to fail with a deviation above {args.min_deviation} mm")
            return 1
        if args.worst_at_plunge:
            # The first feed block is the plunge; the blend into the first cut runs over its end and the start of
            # the next feed block.
            feed = [i + 1 for i, s in enumerate(lines) if re.match(r"^(N\d+\s+)?(G9[34]\s+)?G0?1\b", s.strip())]
            if len(feed) < 2 or r["max_tip_nc_line"] not in feed[:2]:
                print(f"FAIL: expected the largest deviation at the plunge (NC lines {feed[:2]}), "
                      f"got line {r['max_tip_nc_line']}")
                return 1
        print("as expected: the check fails there")
        return 0


if __name__ == "__main__":
    sys.exit(main())
