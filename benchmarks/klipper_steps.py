"""Real Klipper against ffcomp's planner: run a G-code file through Klipper's batch mode and compare
every extruder step with the time ffcomp's firmware-faithful plan crosses that step.

Run: ``python benchmarks/klipper_steps.py FILE.gcode --klipper PATH [--python PY] [--config CFG]
[--compensate] [--carriages]``.  ``PATH`` is a Klipper checkout with ``out/klipper.dict`` built for the Linux MCU
(``echo CONFIG_MACH_LINUX=y > .config && make olddefconfig && make``); ``PY`` a Python with Klipper's
requirements (``cffi greenlet jinja2 pyserial markupsafe``).  ``CFG`` (default
``benchmarks/data/klipper_linux_delta.cfg``, with a ``[firmware_retraction]``) is imported as the ffcomp
profile (``ffcomp profile import --klipper``), so both sides run the same printer.  ``--compensate``
first compensates FILE with that profile and checks the output instead; ``--carriages`` compares the
three carriages' steps too (on the extruder's clock offset), which is where a firmware input shaper
left on under a compensated file would show (``benchmarks/data/klipper_linux_delta_shaper.cfg`` has one).

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
import re
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


def planned_carriage_steps(moves, geom, step_m: float, q_home_m: np.ndarray, fs_hz: float = 100_000.0
                           ) -> list[np.ndarray]:
    """Times (s) at which each planned carriage crosses a half-step boundary of the lattice through
    its homed height ``q_home_m`` (Klipper's: the stepper position set at homing, then whole steps),
    for the XYZ moves of ``moves``; the carriage heights are sampled at ``fs_hz`` within each move
    and the crossings interpolated linearly (the carriage path is smooth: well under 1 us of error)."""
    from ffcomp.kinematics import inverse

    out: list[list[float]] = [[], [], []]
    for m in moves:
        if m.kind != "move":
            continue
        n = max(2, int(math.ceil(m.duration_s * fs_hz)) + 1)
        tt = np.linspace(0.0, m.duration_s, n)
        s = np.array([_distance_at(m, t) for t in tt])
        xyz = (np.asarray(m.start_mm[:3]) + np.outer(s, m.unit[:3])) * 1e-3
        q = (inverse(geom, xyz) - q_home_m) / step_m - 0.5  # crossings at whole numbers
        for i in range(3):
            k0, k1 = np.floor(q[:-1, i]), np.floor(q[1:, i])
            for j in np.nonzero(k0 != k1)[0]:
                lo, hi = sorted((k0[j], k1[j]))
                for level in np.arange(lo + 1, hi + 1):  # every lattice line between the two samples
                    f = (level - q[j, i]) / (q[j + 1, i] - q[j, i])
                    out[i].append(m.t_start_s + tt[j] + f * (tt[j + 1] - tt[j]))
    return [np.array(sorted(o)) for o in out]


def _compare(name: str, kt: np.ndarray, pt: np.ndarray, offset: float | None = None) -> float:
    """Print how Klipper's step times ``kt`` and the plan's ``pt`` differ; returns the clock offset.

    Equal counts are compared step by step.  Otherwise (``offset`` given) each planned step is paired
    with the nearest of Klipper's within 0.5 ms and the unpaired ones are counted: Klipper's step search
    can pass over a carriage that crosses a step boundary and comes back within a fraction of a
    millisecond (a pair of steps the plan has and the firmware does not make)."""
    print(f"{name} steps: Klipper {len(kt)}, ffcomp's plan {len(pt)}")
    if not len(kt) or not len(pt) or (len(kt) != len(pt) and offset is None):
        print(f"  the step counts differ: the plans do not move {name} alike")
        return float("nan") if offset is None else offset
    off = float(np.median(kt - pt)) if offset is None else offset
    if len(kt) == len(pt):
        res = (kt - pt - off) * 1e6
    else:
        j = np.clip(np.searchsorted(kt, pt + off), 1, len(kt) - 1)
        j = np.where(np.abs(kt[j - 1] - pt - off) < np.abs(kt[j] - pt - off), j - 1, j)
        d = kt[j] - pt - off
        ok = np.abs(d) < 5e-4
        # one to one: where two planned steps found the same step of Klipper's, the nearer keeps it
        order = np.argsort(np.abs(d), kind="stable")
        first = np.zeros(len(d), bool)
        first[order[np.unique(j[order], return_index=True)[1]]] = True
        ok &= first
        res = d[ok] * 1e6
        print(f"  paired {int(ok.sum())} steps within 0.5 ms; unpaired: {int((~ok).sum())} of the plan's, "
              f"{len(kt) - int(ok.sum())} of Klipper's")
    print(f"  step time difference after one clock offset: max {np.abs(res).max():.2f} us, "
          f"RMS {np.sqrt(np.mean(res ** 2)):.2f} us")
    return off


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("gcode", type=Path)
    ap.add_argument("--klipper", type=Path, required=True, help="Klipper checkout with out/klipper.dict (Linux MCU)")
    ap.add_argument("--python", default=sys.executable, help="Python with Klipper's requirements")
    ap.add_argument("--config", type=Path, default=ROOT / "benchmarks/data/klipper_linux_delta.cfg")
    ap.add_argument("--compensate", action="store_true", help="check FILE's compensated output instead")
    ap.add_argument("--carriages", action="store_true",
                    help="also compare the three carriages' steps (the file must home first: G28)")
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
    k_src = src
    if a.carriages:
        # batch mode's homing never triggers an endstop: its moves run their full length, and with an
        # [input_shaper] their drip moves overlap the print's first moves on the steppers' clock.  Klipper
        # gets the homed position set directly instead (the plan homes in no time to the same place)
        k_src = tmp / "klipper_input.gcode"
        home = f"SET_KINEMATIC_POSITION X=0 Y=0 Z={prof.geometry.z_max_mm:g} ; was: "
        with open(src, encoding="utf-8", errors="surrogateescape") as fi, \
                open(k_src, "w", encoding="utf-8", errors="surrogateescape") as fo:
            for ln in fi:
                fo.write(home + ln if ln.split(";")[0].strip().upper() == "G28" else ln)
    argv = [str(a.config.resolve()), "-i", str(k_src), "-o", str(tmp / "out.serial"), "-d", str(dictionary)]
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
    moves = list(GcodePlan(str(src), prof))
    off = _compare("extruder", kt, planned_e_steps(moves, step_mm))
    if a.carriages:  # the same clock offset: one timeline for every stepper
        from ffcomp.kinematics import inverse

        geom = prof.geometry_si()
        q_home = inverse(geom, np.array([0.0, 0.0, prof.geometry.z_max_mm * 1e-3]))
        c_step = 1e-3 / prof.limits.steps_per_mm
        planned = planned_carriage_steps(moves, geom, c_step, q_home)
        for i, t in enumerate("abc"):
            pin = cp.get(f"stepper_{t}", "step_pin").strip()
            oid = next(int(o) for o, ln in cfg.items() if re.search(rf"step_pin=(\S*/)?{pin} ", ln + " "))
            kt_i = klipper_step_times(dump, oid, clock)
            if len(planned[i]):  # only the plan's span: Klipper's homing moves (a G28 takes no time in
                # the plan) come before it, and after it where the file homes again at its end
                kt_i = kt_i[(kt_i >= planned[i][0] + off - 1e-3) & (kt_i <= planned[i][-1] + off + 1e-3)]
            _compare(f"stepper_{t}", kt_i, planned[i], off)


if __name__ == "__main__":
    main()
