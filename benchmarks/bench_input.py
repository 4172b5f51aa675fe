"""Benchmark: what the input policy costs and guarantees (issue 10 items 2-4, issue 12 items 3 and 7).

Run: ``python benchmarks/bench_input.py``.  For the default profile and ``samples/profiles/other_delta.toml``:

* **stops**: a 60 mm square (150 mm/s) compensated with and without an ``M600`` at one corner: how far
  the compensated command stands from the plan's rest point on the three points before the stop line,
  the time the stop adds to the output (the stream's settle and pre-roll), and the predicted residual
  vibration with and without the stop;
* **start**: the same square without G28: the first motion line (a travel at the plan's speed);
* **guards**: how long pathological lines take to be refused (they used to run for minutes);
* **marks**: the double-compensation scan's speed on the largest sample.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import re  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from ffcomp.errors import GcodeError  # noqa: E402
from ffcomp.gcode.signature import scan_gcode  # noqa: E402
from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file  # noqa: E402
from ffcomp.profile import default_profile, load_profile  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def square(stop: str | None, home: bool = True) -> str:
    lines = (["G28"] if home else []) + ["G90", "M83", "SET_VELOCITY_LIMIT ACCEL=10000", "G1 X-30 Y-30 Z0.3 F9000"]
    for _ in range(2):
        lines += ["G1 X30 Y-30 E2 F9000", "G1 X30 Y30 E2"] + ([stop] if stop else []) + ["G1 X-30 Y30 E2",
                                                                                         "G1 X-30 Y-30 E2"]
    return "\n".join(lines) + "\n"


def _xyz(line: str) -> np.ndarray:
    return np.array([float(re.search(a + r"(-?[\d.]+)", line).group(1)) for a in "XYZ"])


def main() -> None:
    profiles = {"default": default_profile(), "other_delta": load_profile(ROOT / "samples/profiles/other_delta.toml")}
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        for name, prof in profiles.items():
            print(f"== profile {name}")
            res = {}
            for tag, stop in (("no stop", None), ("M600 at a corner", "M600")):
                src, out = d / "sq.gcode", d / "out.gcode"
                src.write_text(square(stop))
                s = compensate_file(str(src), str(out), prof, CompensateOptions())
                res[tag] = s
                extra = ""
                if stop:
                    lines = out.read_text().splitlines()
                    dists = []
                    for i, ln in enumerate(lines):
                        if ln == stop:
                            pts = [_xyz(x) for x in lines[:i] if x.startswith("G1 X")][-3:]
                            dists.append(max(np.linalg.norm(p - [30, 30, 0.3]) for p in pts) * 1e3)
                    extra = f", command at the stop lines within {max(dists):.1f} um of the plan's rest point"
                print(f"  {tag:18s}: predicted RMS {s.rms_before_um:6.1f} -> {s.rms_after_um:5.2f} um, "
                      f"self-check {s.self_check_max_um:5.1f} um, print {s.print_time_s:.3f} s -> output "
                      f"{s.output_print_time_s:.3f} s{extra}")
            added = (res["M600 at a corner"].output_print_time_s - res["M600 at a corner"].print_time_s) - \
                (res["no stop"].output_print_time_s - res["no stop"].print_time_s)
            print(f"  time added per stop (settle + pre-roll): {added / 2 * 1e3:.0f} ms")
            src.write_text(square(None, home=False))
            s = compensate_file(str(src), str(out), prof, CompensateOptions(predict=False))
            first = next(ln for ln in out.read_text().splitlines() if ln.startswith("G1 "))
            print(f"  no G28: warnings {s.warnings}, first motion line: {first}")
        print("== guards (time to a clean error)")
        for line in ("G1 X10 Y10 E2 F0.001", "G1 X10 Y10 E2 F1", "G4 P86400000", "G2 X10 Y0 I100000 J0 F3000"):
            src = d / "bad.gcode"
            src.write_text(f"G28\nG1 X0 Y0 Z5 F6000\n{line}\n")
            t = time.perf_counter()
            try:
                compensate_file(str(src), str(d / "o.gcode"), profiles["default"], CompensateOptions(predict=False))
                msg = "no error"
            except GcodeError as e:
                msg = str(e).split(": ", 2)[1][:70]
            print(f"  {line:28s} {time.perf_counter() - t:6.2f} s  {msg}")
        big = max((ROOT / "samples").rglob("*.gcode"), key=lambda p: p.stat().st_size)
        t = time.perf_counter()
        r = scan_gcode(str(big))
        dt = time.perf_counter() - t
        print(f"== marks: scan of {big.name} ({big.stat().st_size / 1e6:.1f} MB, {r.lines} lines) in {dt * 1e3:.0f} ms "
              f"({big.stat().st_size / 1e6 / dt:.0f} MB/s); compensated: {r.compensated}")


if __name__ == "__main__":
    main()
