"""Benchmark: the compensated G-code run with the printer's input shaper still on, and off.

Run: ``python benchmarks/bench_shaper_stack.py [--quick]``.  A Klipper user with an accelerometer has
usually tuned ``[input_shaper]``.  Klipper shapes the toolhead's X and Y before the kinematics, so a
shaper left on under a compensated file convolves the compensation's command with its impulses.  The
output's header therefore switches shaping off (:data:`ffcomp.pipeline.header.SHAPER_OFF`,
:func:`ffcomp.pipeline.header.shaper_lines`).  For the default profile and ``other_delta`` (compensated
with the identified profile, simulated on ``other_delta_truth.toml``), on the G-code fidelity bench's
files: the lag-aligned RMS (um) of the uncompensated file, of the same with Klipper's ZV / MZV / EI at
the printer's centre x/y mode, of the compensated output as it runs (shaping off), and of the output
with each shaper left on.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_gcode_fidelity as fidelity  # noqa: E402

from ffcomp.pipeline.options import CompensateOptions  # noqa: E402
from ffcomp.pipeline.output_check import check_gcode_output  # noqa: E402
from ffcomp.profile import default_profile, load_profile  # noqa: E402
from ffcomp.sim.bench import shaper_tuning  # noqa: E402

SHAPERS = ("zv", "mzv", "ei")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="shorter files")
    a = ap.parse_args()
    profiles = {"default": (default_profile(), None),
                "other_delta": (load_profile(ROOT / "samples/profiles/other_delta.toml"),
                                load_profile(ROOT / "samples/profiles/other_delta_truth.toml"))}
    tmp = Path(tempfile.mkdtemp(prefix="bench_shaper_stack_"))
    for pname, (prof, truth) in profiles.items():
        f_hz = shaper_tuning(truth or prof).centre_hz  # what the user tuned on the real printer
        print(f"\n### {pname} (shapers at {f_hz:.2f} Hz)\n")
        cols = " | ".join(f"none + {s}" for s in SHAPERS) + " | ffcomp (shaping off) | " + " | ".join(
            f"ffcomp + {s}" for s in SHAPERS)
        print(f"| file | none | {cols} |\n|---|---|" + "---|" * (2 * len(SHAPERS) + 1))
        for name, text in fidelity.files(a.quick).items():
            src = tmp / "in.gcode"
            src.write_text(text)
            c = check_gcode_output(prof, src, tmp / "out.gcode", plant_profile=truth,
                                   opts=CompensateOptions(predict=False), shapers=tuple((s, f_hz) for s in SHAPERS))
            sh = [c.shaped[f"{s}@{f_hz:g}"] for s in SHAPERS]
            print(f"| {name} | {c.none.lag.rms_norm_um:.1f} | "
                  + " | ".join(f"{r['none'].lag.rms_norm_um:.1f}" for r in sh)
                  + f" | **{c.gcode.lag.rms_norm_um:.1f}** | "
                  + " | ".join(f"{r['gcode'].lag.rms_norm_um:.1f}" for r in sh) + " |", flush=True)


if __name__ == "__main__":
    main()
