"""Benchmark: the clock of Marlin output, with and without the feeds' re-timing, on both profiles.

Run: ``python benchmarks/bench_marlin_clock.py [--files a.gcode,b.gcode] [--random N]``.  Compensates
the sample files on the default profile and on ``samples/profiles/other_delta.toml``, each with
``planner = "marlin"``, once with the re-timing off (``retime_passes=0``) and once as the CLI runs
(self-check limits lifted, so every file is measured), and prints per file the largest drift on
the absolute clock without and with it, the passes run, the re-timing's time and the whole run's
time and speed (print time / processing time).  ``--random N`` adds N small random files per
profile (``bench_random_drift.random_file``) and prints how many drift more than 0.2 ms.
What ``tests/test_retime.py`` checks with loose bounds.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file  # noqa: E402
from ffcomp.profile import default_profile, load_profile  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FILES = ("stress_square", "stress_square_off100", "stress_zigzag", "stress_circle64", "cube_prusa", "cube_cura",
         "ringing_tower_prusa")
LIFTED = dict(predict=False, self_check_drift_ms=1e9, self_check_tol_um=1e9)


def marlin(prof):
    return prof.with_(limits=replace(prof.limits, planner="marlin"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--files", default=",".join(FILES), help="sample names (samples/gcode/NAME.gcode) or paths")
    ap.add_argument("--random", type=int, default=0, help="random files per profile")
    a = ap.parse_args()
    profiles = {"default": marlin(default_profile()),
                "other_delta": marlin(load_profile(ROOT / "samples" / "profiles" / "other_delta.toml"))}
    out = Path(tempfile.mkdtemp(prefix="bench_marlin_")) / "o.gcode"
    for name, prof in profiles.items():
        print(f"\n{name} (planner = marlin)\n")
        print("| file | print (s) | drift without (ms) | drift with (ms) | passes | re-timing (s) | run (s) | speed |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|")
        for f in a.files.split(","):
            src = Path(f) if f.endswith(".gcode") else ROOT / "samples" / "gcode" / f"{f}.gcode"
            s0 = compensate_file(str(src), str(out), prof, CompensateOptions(retime_passes=0, **LIFTED))
            s = compensate_file(str(src), str(out), prof, CompensateOptions(**LIFTED))
            print(f"| {src.name} | {s.print_time_s:.1f} | {s0.self_check_drift_ms:+.3f} | "
                  f"{s.self_check_drift_ms:+.3f} | {s.retime_passes} | {s.retime_time_s or 0:.2f} | "
                  f"{s.wall_time_s:.2f} | {s.speed_ratio:.0f}x |",
                  flush=True)
        if a.random:
            sys.path.insert(0, str(ROOT / "benchmarks"))
            from bench_random_drift import random_file

            rng = np.random.default_rng(1)
            drifts = []
            src = out.with_name("r.gcode")
            for _ in range(a.random):
                src.write_text(random_file(rng))
                try:
                    s = compensate_file(str(src), str(out), prof, CompensateOptions(**LIFTED))
                except Exception as e:  # noqa: BLE001  (a benchmark: say which and go on)
                    print(f"random file failed: {e}")
                    continue
                drifts.append(abs(s.self_check_drift_ms))
            d = np.array(drifts)
            print(f"\nrandom files: {len(d)}; above 0.2 ms {int(np.sum(d > 0.2))}, above 1 ms {int(np.sum(d > 1))}; "
                  f"median {np.median(d):.3f} ms, largest {d.max():.3f} ms")


if __name__ == "__main__":
    main()
