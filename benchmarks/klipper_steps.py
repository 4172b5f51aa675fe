"""Real Klipper against ffcomp's planner: run a G-code file through Klipper's batch mode and compare
every extruder step with the time ffcomp's firmware-faithful plan crosses that step.

Run: ``python benchmarks/klipper_steps.py FILE.gcode --klipper PATH [--python PY] [--config CFG]
[--compensate]``.  ``PATH`` is a Klipper checkout with ``out/klipper.dict`` built for the Linux MCU
(``echo CONFIG_MACH_LINUX=y > .config && make olddefconfig && make``); ``PY`` a Python with Klipper's
requirements (``cffi greenlet jinja2 pyserial markupsafe``).  ``CFG`` (default
``benchmarks/data/klipper_linux_delta.cfg``, with a ``[firmware_retraction]``) is imported as the ffcomp
profile (``ffcomp profile import --klipper``), so both sides run the same printer.  ``--compensate``
first compensates FILE with that profile and checks the output instead.

Klipper steps where the commanded extruder position crosses the middle between two step positions;
the script predicts those times from the plan (one constant offset aligns the two clocks) and prints
the largest and RMS difference: within Klipper's step compression error (25 us), ffcomp's plan is
the firmware's timeline.  Klipper runs without its batch-mode background flush's extra 0.25 s (see
``main``): with it, a dwell that meets a pause between two chunks of input re-primes the clock 0.25 s
later, which a printing host whose input keeps ahead never does.  Tested with Klipper of 2026-08-07
(84104bb).  Not run by the tests (CI has no Klipper).  ``benchmarks/data/firmware_retraction.gcode`` exercises G10/G11,
SET_RETRACTION and M220/M221.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from ffcomp.gcode.planner import GcodePlan
from ffcomp.profile_import import from_klipper_cfg

ROOT = Path(__file__).resolve().parents[1]


def klipper_step_times(dump: str, oid: int, clock_hz: float) -> np.ndarray:
    """Step times (s) of stepper ``oid`` from ``parsedump.py`` text (queue_step commands)."""
    t, out = 0, []
    for ln in dump.splitlines():
        if not ln.startswith(("queue_step ", "reset_step_clock ")) or f" oid={oid} " not in ln + " ":
            continue
        kv = dict(w.split("=", 1) for w in ln.split()[1:])
        if ln.startswith("reset_step_clock"):
            t = int(kv["clock"])
            continue
        iv, add = int(kv["interval"]), int(kv["add"])
        for _ in range(int(kv["count"])):
            t += iv
            out.append(t)
            iv += add
    return np.array(out, float) / clock_hz


def _distance_at(m, t: float) -> float:
    a, v0, ta, tc = m.accel_mm_s2, m.start_v_mm_s, m.accel_t_s, m.cruise_t_s
    if t <= ta:
        return v0 * t + 0.5 * a * t * t
    s = v0 * ta + 0.5 * a * ta * ta
    if t <= ta + tc:
        return s + m.cruise_v_mm_s * (t - ta)
    t3 = t - ta - tc
    return s + m.cruise_v_mm_s * (tc + t3) - 0.5 * a * t3 * t3


def planned_e_steps(moves, step_mm: float) -> np.ndarray:
    """Times (s) at which the planned extruder position crosses ``(n + 1/2) step_mm``."""
    out = []
    for m in moves:
        e0, e1 = m.start_mm[3], m.end_mm[3]
        if m.kind == "dwell" or abs(e1 - e0) < 1e-12:
            continue
        lo, hi = sorted((e0, e1))
        levels = (np.arange(math.ceil(lo / step_mm - 0.5), math.floor(hi / step_mm - 0.5) + 1) + 0.5) * step_mm
        for level in (levels if e1 > e0 else levels[::-1]):
            target = abs(level - e0) / abs(m.unit[3])
            a, b = 0.0, m.duration_s
            for _ in range(60):  # bisection: s(t) is monotonic within a move
                mid = 0.5 * (a + b)
                a, b = (mid, b) if _distance_at(m, mid) < target else (a, mid)
            out.append(m.t_start_s + 0.5 * (a + b))
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("gcode", type=Path)
    ap.add_argument("--klipper", type=Path, required=True, help="Klipper checkout with out/klipper.dict (Linux MCU)")
    ap.add_argument("--python", default=sys.executable, help="Python with Klipper's requirements")
    ap.add_argument("--config", type=Path, default=ROOT / "benchmarks/data/klipper_linux_delta.cfg")
    ap.add_argument("--compensate", action="store_true", help="check FILE's compensated output instead")
    a = ap.parse_args()
    kl, tmp = a.klipper.resolve(), Path(tempfile.mkdtemp(prefix="klipper_steps_"))
    prof = from_klipper_cfg(a.config)
    src = a.gcode.resolve()
    if a.compensate:
        from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file

        out = tmp / "compensated.gcode"
        s = compensate_file(str(src), str(out), prof, CompensateOptions(predict=False))
        print(f"compensated: self-check drift {s.self_check_drift_ms:+.3f} ms, "
              f"{s.firmware_retractions} G10/G11 timed as the firmware's moves")
        src = out
    dictionary = kl / "out" / "klipper.dict"
    argv = [str(a.config.resolve()), "-i", str(src), "-o", str(tmp / "out.serial"), "-d", str(dictionary)]
    # batch mode's background flush (motion_queuing._flush_handler_debug) runs between chunks of input
    # and, finding nothing queued, generates steps 0.25 s (BGFLUSH_EXTRA_TIME) past the queue's end, as
    # a printing host does only when its input runs dry: the next move after a dwell then re-primes
    # there, 0.25 s late.  The wrapper keeps the handler's batching and drops that extra flush (the
    # end of the run still flushes everything), so the check sees a host that keeps ahead
    wrapper = ("import sys\nsys.path.insert(0, sys.argv.pop(1))\nimport klippy\n"
               "import extras.motion_queuing as mq\n"
               "def fh(self, eventtime):\n"
               "    faux, batch, n = self.need_flush_time - 1.5, mq.BGFLUSH_SG_HIGH_TIME - mq.BGFLUSH_SG_LOW_TIME, 0\n"
               "    while self.last_step_gen_time < faux:\n"
               "        target = self.last_step_gen_time + batch\n"
               "        if n > 100 and faux > target:\n"
               "            target += int((faux - target) / batch) * batch\n"
               "        self._advance_flush_time(0., target)\n"
               "        n += 1\n"
               "    if n:\n"
               "        return self.reactor.NOW\n"
               "    self.do_kick_flush_timer = True\n"
               "    return self.reactor.NEVER\n"
               "mq.PrinterMotionQueuing._flush_handler_debug = fh\n"
               "sys.argv[0] = 'klippy.py'\nklippy.main()\n")
    subprocess.run([a.python, "-c", wrapper, str(kl / "klippy"), *argv], check=True, capture_output=True)
    dump = subprocess.run([a.python, str(kl / "klippy" / "parsedump.py"), str(dictionary), str(tmp / "out.serial")],
                          check=True, capture_output=True, text=True).stdout
    import json

    clock = float(json.loads(dictionary.read_text())["config"]["CLOCK_FREQ"])
    cfg = {ln.split()[1].split("=")[1]: ln for ln in dump.splitlines() if ln.startswith("config_stepper")}
    e_oid = next(int(o) for o, ln in cfg.items() if "gpio13 " in ln + " ")  # the config's extruder step pin
    kt = klipper_step_times(dump, e_oid, clock)
    import configparser

    cp = configparser.ConfigParser(inline_comment_prefixes=("#", ";"))
    cp.read(a.config)
    step_mm = cp.getfloat("extruder", "rotation_distance") / (
        cp.getint("extruder", "microsteps") * cp.getint("extruder", "full_steps_per_rotation", fallback=200))
    pt = planned_e_steps(list(GcodePlan(str(src), prof)), step_mm)
    print(f"extruder steps: Klipper {len(kt)}, ffcomp's plan {len(pt)}")
    if len(kt) != len(pt) or not len(kt):
        raise SystemExit("the step counts differ: the plans do not move the extruder alike")
    off = float(np.median(kt - pt))
    res = (kt - pt - off) * 1e6
    print(f"step time difference after one clock offset: max {np.abs(res).max():.2f} us, "
          f"RMS {np.sqrt(np.mean(res ** 2)):.2f} us")


if __name__ == "__main__":
    main()
