#!/usr/bin/python3
"""Run one G-code program in LinuxCNC's own motion controller, headless, and record every servo cycle.

    run_program.py PROGRAM.ngc -o SAMPLES.txt [--mdi 'G64 P0.01'] [--timeout S] [--keep DIR]

Copies config/ (the trunnion-ac ini, HAL file, remap subroutines, tool table and the driver that stands in
for the GUI) into a fresh temporary directory, starts `linuxcnc -r` there and waits. The driver homes, runs
the program and drains the sampler into SAMPLES.txt (halsampler -t: sample number, joints 0-4, commanded
world X Y Z A C, program line, motion type, current velocity). Exit status: 0 the program ran to its end,
1 LinuxCNC reported an error or the run failed or timed out (the message says which), 2 bad arguments
or LinuxCNC is missing.

Isolation: everything of the run lives in its temporary directory (HOME, the RTAPI FIFOs, the parameter file,
logs), removed afterwards unless --keep. LinuxCNC itself is one instance per host (its HAL shared memory and
/tmp/linuxcnc.lock are fixed), so runs take an exclusive flock and wait their turn. Whatever happens (error,
timeout, Ctrl-C) the LinuxCNC process group is stopped and the realtime side unloaded.
As root, rtapi_app needs an unprivileged uid to drop to: RTAPI_UID (default: the owner of `nobody`).
"""
import argparse
import fcntl
import json
import os
import pwd
import shutil
import signal
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(HERE, "config")
INI = "trunnion-ac.ini"
# LinuxCNC's own single-instance lock; ours serialises runs so that one never sees another's.
LINUXCNC_LOCK = "/tmp/linuxcnc.lock"
# Fixed like LinuxCNC's own lock (not $TMPDIR): every run on the host must see the same one.
HOST_LOCK = "/tmp/cscam-linuxcnc.flock"


def fail(code, msg):
    print(f"run_program: {msg}", file=sys.stderr)
    sys.exit(code)


def stop_group(proc):
    """SIGTERM, then SIGKILL, the whole process group of `proc` (linuxcnc and everything it started)."""
    for sig, grace in ((signal.SIGTERM, 10), (signal.SIGKILL, 5)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(grace)
            return
        except subprocess.TimeoutExpired:
            pass


# The processes a running LinuxCNC instance consists of (linuxcnc is a shell script; the rest are binaries).
LINUXCNC_PROCESS_NAMES = {"rtapi_app", "linuxcncsvr", "milltask", "io", "iocontrol", "halui", "linuxcnc"}


def linuxcnc_processes():
    """'name[pid]' of every live LinuxCNC process on the host, from /proc (the comm name, or the script name)."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/stat") as f:
                # A zombie is dead and holds nothing; where PID 1 does not reap (containers) they stay listed.
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                    continue
            with open(f"/proc/{pid}/comm") as f:
                comm = f.read().strip()
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                argv = [a.decode(errors="replace") for a in f.read().split(b"\0") if a]
        except OSError:
            continue  # gone meanwhile
        names = {comm} | {os.path.basename(a) for a in argv[:2]}
        hit = names & LINUXCNC_PROCESS_NAMES
        if hit:
            found.append(f"{sorted(hit)[0]}[{pid}]")
    return found


# The SysV shared memory a LinuxCNC instance leaves behind when it is killed outright: the NML channels (keys in
# LinuxCNC's NML file), motion's segment (its DEFAULT_SHMEM_KEY, 100), HAL and RTAPI ('HAL2', 'HHL4') and the
# sampler's streams ('HSA0' + n). A new instance attaches to stale NML channels and its task then times out
# talking to IO, so a stale instance must be cleared before the next one starts.
NML_FILE = "/usr/share/linuxcnc/linuxcnc.nml"
FIXED_SHM_KEYS = {100, 0x48414C32, 0x48484C34} | {0x48534130 + n for n in range(16)}


def linuxcnc_shm_keys():
    keys = set(FIXED_SHM_KEYS)
    try:
        with open(NML_FILE) as f:
            for line in f:
                fields = line.split()
                # B name SHMEM host size neut 0 buffer_number max_procs key ...
                if len(fields) >= 10 and fields[0] == "B" and fields[2] == "SHMEM":
                    keys.add(int(fields[9]))
    except (OSError, ValueError):
        pass
    return keys


def clear_stale_instance(env, cwd):
    """Unload what is left of a LinuxCNC that no longer runs: HAL and RTAPI (halrun -U), then the shared memory
    segments of LinuxCNC's keys that no process is attached to. Returns a note of what was removed."""
    try:
        subprocess.run(["halrun", "-U"], env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       timeout=30, start_new_session=True)
    except (subprocess.TimeoutExpired, OSError):
        pass
    keys = linuxcnc_shm_keys()
    removed = []
    out = subprocess.run(["ipcs", "-m"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True).stdout
    for line in out.splitlines():
        fields = line.split()  # key shmid owner perms bytes nattch [status]
        if len(fields) < 6 or not fields[0].startswith("0x"):
            continue
        try:
            key, shmid, nattch = int(fields[0], 16), fields[1], int(fields[5])
        except ValueError:
            continue
        if key in keys and nattch == 0:
            if subprocess.run(["ipcrm", "-m", shmid], stderr=subprocess.DEVNULL).returncode == 0:
                removed.append(fields[0])
    return f"removed {len(removed)} stale shared memory segment(s)" if removed else "no stale shared memory"


def die_with_parent():
    """In the linuxcnc child: SIGTERM when this script dies, even by SIGKILL (a test runner's hard timeout), so
    that linuxcnc's own trap shuts the instance down instead of leaving it running with its lock."""
    import ctypes
    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


def on_sigterm(signum, frame):
    raise KeyboardInterrupt  # the same cleanup as Ctrl-C (a test runner's timeout sends SIGTERM)


def main():
    signal.signal(signal.SIGTERM, on_sigterm)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("program")
    ap.add_argument("-o", "--samples", required=True, help="output: one line per servo cycle")
    ap.add_argument("--timeout", type=float, default=120, help="seconds for the whole run (default 120)")
    ap.add_argument("--keep", help="copy the run directory (logs, HAL dump) here")
    ap.add_argument("--mdi", action="append", default=[],
                    help="an MDI command run after homing, before the program (repeatable), e.g. 'G64 P0.01': "
                         "what an operator or the controller's setup would set (default: none, LinuxCNC's G64)")
    args = ap.parse_args()

    if shutil.which("linuxcnc") is None or shutil.which("halsampler") is None:
        fail(2, "LinuxCNC is not installed (linuxcnc, halsampler not on PATH): apt-get install linuxcnc-uspace")
    program = os.path.abspath(args.program)
    if not os.path.isfile(program):
        fail(2, f"{args.program}: no such file")

    uid = None
    if os.geteuid() == 0:
        try:
            uid = int(os.environ.get("RTAPI_UID") or pwd.getpwnam("nobody").pw_uid)
        except (KeyError, ValueError):
            fail(2, "as root, rtapi_app needs an unprivileged uid: set RTAPI_UID (there is no user `nobody`)")
    run_dir = tempfile.mkdtemp(prefix="cscam-lcnc-")
    env = dict(os.environ)
    env.pop("DISPLAY", None)  # no X: LinuxCNC must not try any GUI
    env.update(
        HOME=run_dir,  # linuxcnc copies its logs to $HOME on failure
        RUNTESTS="1",
        PATH="/usr/bin:/bin:" + env.get("PATH", ""),
        CSCAM_LCNC_PROGRAM=os.path.join(run_dir, "program.ngc"),
        CSCAM_LCNC_SAMPLES=os.path.join(run_dir, "samples.txt"),
        CSCAM_LCNC_RESULT=os.path.join(run_dir, "result.json"),
        CSCAM_LCNC_TIMEOUT_S=str(args.timeout),
        CSCAM_LCNC_OWNER_PID=str(os.getpid()),
        CSCAM_LCNC_MDI="\n".join(args.mdi),
    )
    if uid is not None:
        env["RTAPI_UID"] = str(uid)
        fifo = os.path.join(run_dir, "rtapi_fifo")
        os.mkdir(fifo)
        os.chown(fifo, uid, -1)
        # RTAPI_FIFO_PATH names the master's unix socket itself; its folder must be writable by that uid.
        env["RTAPI_FIFO_PATH"] = os.path.join(fifo, "rtapi_app.sock")
    shutil.copytree(CONFIG, os.path.join(run_dir, "config"))
    cfg = os.path.join(run_dir, "config")
    os.chmod(run_dir, 0o755)
    shutil.copyfile(program, env["CSCAM_LCNC_PROGRAM"])
    log_path = os.path.join(run_dir, "linuxcnc.log")

    lock = open(HOST_LOCK, "a")
    proc = None
    status, message = 1, ""
    try:
        t_wait = time.monotonic()
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() - t_wait > args.timeout:
                    raise TimeoutError("another LinuxCNC run held the host lock for too long")
                time.sleep(0.2)
        if os.path.exists(LINUXCNC_LOCK):
            # Not one of ours (we hold the flock): a LinuxCNC someone else started, or the lock of a run that was
            # killed outright (SIGKILL leaves no chance to clean up). linuxcnc itself would kill a live instance;
            # we never do: a live one is refused, a stale lock (no LinuxCNC process on the host) is removed.
            live = linuxcnc_processes()
            if live:
                raise RuntimeError(f"{LINUXCNC_LOCK} exists and LinuxCNC is running "
                                   f"({', '.join(live)}): wait for it to stop")
            note = clear_stale_instance(env, cfg)
            os.remove(LINUXCNC_LOCK)
            print(f"run_program: removed the stale {LINUXCNC_LOCK} (no LinuxCNC process is running); {note}",
                  file=sys.stderr)
        t0 = time.monotonic()
        with open(log_path, "w") as log:
            proc = subprocess.Popen(["linuxcnc", "-r", os.path.join(cfg, INI)], cwd=cfg, env=env, stdout=log,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                                    preexec_fn=die_with_parent)
            try:
                proc.wait(args.timeout + 30)  # the driver has its own timeouts; this one is the backstop
            except subprocess.TimeoutExpired:
                raise TimeoutError(f"LinuxCNC did not finish within {args.timeout + 30:g} s")
        try:
            with open(env["CSCAM_LCNC_RESULT"]) as f:
                result = json.load(f)
        except FileNotFoundError:
            raise RuntimeError("LinuxCNC stopped before its driver reported (see the log below)")
        if not result["ok"]:
            raise RuntimeError(result.get("message", "the driver failed"))
        samples = env["CSCAM_LCNC_SAMPLES"]
        tmp = args.samples + ".tmp"
        shutil.copyfile(samples, tmp)
        os.replace(tmp, args.samples)
        n = sum(1 for _ in open(args.samples))
        status = 0
        message = (f"{program}: ran in {result['run_s']:.2f} s of motion, {n} servo samples -> {args.samples} "
                   f"(LinuxCNC up and down in {time.monotonic() - t0:.1f} s)")
    except (RuntimeError, TimeoutError, OSError) as e:
        message = f"{program}: {e}"
    except KeyboardInterrupt:
        message = f"{program}: interrupted"
    finally:
        if proc is not None and proc.poll() is None:
            stop_group(proc)
        if proc is not None and status != 0:
            # After a kill the realtime side and the shared memory may linger: clear them, release LinuxCNC's lock.
            live = linuxcnc_processes()
            if live:
                message += f"\n(LinuxCNC processes still running after the stop: {', '.join(live)})"
            else:
                clear_stale_instance(env, cfg)
            if os.path.exists(LINUXCNC_LOCK):
                os.remove(LINUXCNC_LOCK)
        fcntl.flock(lock, fcntl.LOCK_UN)
        lock.close()
        if status != 0 and os.path.exists(log_path):
            with open(log_path, errors="replace") as f:
                tail = f.read().splitlines()[-40:]
            message += "\n--- linuxcnc log (last lines) ---\n" + "\n".join(tail)
        if args.keep:
            shutil.copytree(run_dir, args.keep, dirs_exist_ok=True)
        shutil.rmtree(run_dir, ignore_errors=True)
    print(message, file=sys.stderr if status else sys.stdout)
    return status


if __name__ == "__main__":
    sys.exit(main())
