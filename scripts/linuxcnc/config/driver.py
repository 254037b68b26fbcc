#!/usr/bin/python3
"""The DISPLAY program of cscam's headless LinuxCNC configuration (instead of a GUI).

Started by `linuxcnc -r` (see run_program.py) with `-ini FILE`. It takes LinuxCNC out of e-stop, homes
every joint, enables the HAL sampler, runs one program in AUTO mode, waits until the interpreter is idle and
motion has stopped, drains the sampler FIFO through `halsampler`, writes result.json and exits; LinuxCNC
shuts down when its display exits. Settings come from the environment (set by run_program.py):
  CSCAM_LCNC_PROGRAM   the G-code file to run
  CSCAM_LCNC_SAMPLES   where halsampler writes one line per servo cycle
  CSCAM_LCNC_RESULT    where this driver writes its JSON status
  CSCAM_LCNC_TIMEOUT_S the longest the program may run (seconds)
  CSCAM_LCNC_MDI       MDI commands (one a line) run after homing, before the program, e.g. G64 P0.01
  CSCAM_LCNC_OWNER_PID the run_program.py that started this run: if it dies (even by SIGKILL), the run stops
Uses /usr/bin/python3: the `linuxcnc` module is installed for the system Python only.
"""
import json
import os
import signal
import subprocess
import sys
import time

import linuxcnc

PROGRAM = os.environ["CSCAM_LCNC_PROGRAM"]
SAMPLES = os.environ["CSCAM_LCNC_SAMPLES"]
RESULT = os.environ["CSCAM_LCNC_RESULT"]
TIMEOUT_S = float(os.environ.get("CSCAM_LCNC_TIMEOUT_S", "60"))
MDI = [c for c in os.environ.get("CSCAM_LCNC_MDI", "").split("\n") if c.strip()]
OWNER_PID = int(os.environ.get("CSCAM_LCNC_OWNER_PID", "0"))

stat = linuxcnc.stat()
cmd = linuxcnc.command()
err = linuxcnc.error_channel()
messages = []  # every error and message LinuxCNC reported, in order


class Failure(Exception):
    pass


def drain_errors():
    """Collects LinuxCNC's error channel; an (operator) error fails the run."""
    while True:
        e = err.poll()
        if not e:
            return
        kind, text = e
        messages.append(text)
        if kind in (linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR):
            raise Failure(f"LinuxCNC error: {text}")


def owner_alive():
    if OWNER_PID <= 0:
        return True
    try:
        os.kill(OWNER_PID, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True


def wait_for(what, predicate, timeout_s):
    deadline = time.monotonic() + timeout_s
    while True:
        if not owner_alive():
            # Nobody will read the result: stop the program now, so that LinuxCNC shuts down and frees the host.
            cmd.abort()
            raise Failure(f"the run's owner (pid {OWNER_PID}) is gone while waiting for {what}")
        stat.poll()
        drain_errors()
        if predicate():
            return
        if time.monotonic() > deadline:
            raise Failure(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(0.01)


def halcmd(*args):
    subprocess.run(["halcmd", *args], check=True, stdout=subprocess.DEVNULL)


def halget(pin):
    return subprocess.run(["halcmd", "getp", pin], check=True, capture_output=True, text=True).stdout.strip()


def run():
    # Task needs a moment after startup before it accepts commands.
    deadline = time.monotonic() + 20
    while True:
        try:
            stat.poll()
            break
        except linuxcnc.error:
            if time.monotonic() > deadline:
                raise Failure("LinuxCNC status channel did not come up")
            time.sleep(0.1)

    cmd.state(linuxcnc.STATE_ESTOP_RESET)
    cmd.state(linuxcnc.STATE_ON)
    wait_for("machine on", lambda: stat.task_state == linuxcnc.STATE_ON, 10)
    cmd.mode(linuxcnc.MODE_MANUAL)
    wait_for("manual mode", lambda: stat.task_mode == linuxcnc.MODE_MANUAL, 10)
    cmd.home(-1)  # HOME_SEARCH_VEL 0: every joint is homed where it stands (all at 0)
    wait_for("homing", lambda: all(stat.homed[: stat.joints]), 20)

    if MDI:
        cmd.mode(linuxcnc.MODE_MDI)
        wait_for("MDI mode", lambda: stat.task_mode == linuxcnc.MODE_MDI, 10)
        for line in MDI:
            cmd.mdi(line)
            if cmd.wait_complete(20) == -1:
                raise Failure(f"MDI {line} did not complete")
            wait_for(f"MDI {line}", lambda: stat.interp_state == linuxcnc.INTERP_IDLE and stat.queue == 0, 20)
    cmd.mode(linuxcnc.MODE_AUTO)
    wait_for("auto mode", lambda: stat.task_mode == linuxcnc.MODE_AUTO, 10)
    cmd.program_open(PROGRAM)
    wait_for("program loaded", lambda: stat.file == PROGRAM, 10)

    sampler = subprocess.Popen(["halsampler", "-t", SAMPLES])
    try:
        halcmd("setp", "sampler.0.enable", "1")
        t0 = time.monotonic()
        cmd.auto(linuxcnc.AUTO_RUN, 0)
        wait_for("program start", lambda: stat.interp_state != linuxcnc.INTERP_IDLE or time.monotonic() - t0 > 1, 10)
        wait_for(
            "program end",
            lambda: stat.interp_state == linuxcnc.INTERP_IDLE and stat.queue == 0 and stat.inpos,
            TIMEOUT_S,
        )
        run_s = time.monotonic() - t0
        halcmd("setp", "sampler.0.enable", "0")
        # Let halsampler empty the FIFO before stopping it.
        deadline = time.monotonic() + 10
        while int(halget("sampler.0.curr-depth")) > 0:
            if time.monotonic() > deadline:
                raise Failure("halsampler did not drain the sampler FIFO")
            time.sleep(0.05)
        time.sleep(0.2)
    finally:
        sampler.send_signal(signal.SIGTERM)
        try:
            sampler.wait(5)
        except subprocess.TimeoutExpired:
            sampler.kill()
    return run_s


def main():
    result = {"ok": False, "program": PROGRAM}
    try:
        result["run_s"] = run()
        result["ok"] = True
    except Failure as e:
        result["message"] = str(e)
    except Exception as e:  # a driver bug or a LinuxCNC that went away: still report it
        result["message"] = f"{type(e).__name__}: {e}"
    result["messages"] = messages
    with open(RESULT + ".tmp", "w") as f:
        json.dump(result, f, indent=1)
    os.replace(RESULT + ".tmp", RESULT)
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
