"""Benchmark: the pin repair's weight on printed samples, judged on the printed lines.

Run: ``python benchmarks/bench_print_weight.py [--weights 1 2] [--file F ...] [--profiles P ...]``.
For each file and profile (``other_delta`` is compensated with ``other_delta.toml`` and simulated on
``other_delta_truth.toml``; ``default`` on its own model), compensates the file with
``RepairConfig.print_weight`` set to each weight (everything else the defaults), simulates the
written G-code against the source's plan (what ``ffcomp simulate SRC --compare OUT`` prints) and
prints the printed lines' lag-aligned / contour RMS (the samples where the plan extrudes: what marks
the part), the whole file's, and the self-check's drift and clock error.  About 90 s of CPU per
file, profile and weight (cube_prusa); the defaults reproduce the table of docs/gcode_clock.md (*Printed samples
weigh twice in the repair*).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PROFILES = {"default": (None, None),
            "other_delta": ("samples/profiles/other_delta.toml", "samples/profiles/other_delta_truth.toml")}


def row(src: Path, pname: str, weight: float, tmp: Path) -> str:
    from ffcomp.compensate.pin_repair import RepairConfig
    from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file
    from ffcomp.pipeline.sim_flow import simulate_gcode
    from ffcomp.profile import default_profile, load_profile

    comp, truth = PROFILES[pname]
    prof = default_profile() if comp is None else load_profile(ROOT / comp)
    plant = prof if truth is None else load_profile(ROOT / truth)
    out = tmp / f"{src.stem}_{pname}_{weight:g}.gcode"
    opts = dataclasses.replace(CompensateOptions(predict=False), repair=RepairConfig(print_weight=weight))
    s = compensate_file(str(src), str(out), prof, opts)
    run = simulate_gcode(plant, str(src), compare=str(out)).runs[-1]
    lag, contour = run.extruded_um if run.extruded_um is not None else (float("nan"),) * 2
    whole = run.report
    return (f"| {src.name} | {pname} | {weight:g} | {lag:.2f} / {contour:.2f} | "
            f"{whole.lag.rms_norm_um:.1f} / {whole.contour.rms_norm_um:.1f} | "
            f"{s.self_check_drift_ms:+.3f} | {s.self_check_abs_max_um:.1f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--file", type=Path, nargs="+", default=[ROOT / "samples/gcode/cube_prusa.gcode"])
    ap.add_argument("--profiles", nargs="+", default=["other_delta", "default"], choices=sorted(PROFILES))
    a = ap.parse_args()
    print("| file | profile | print weight | printed lines: lag / contour RMS (um) | whole file (um) "
          "| drift max (ms) | clock error max (um) |\n|---|---|---|---|---|---|---|", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_print_weight_") as d:
        for f in a.file:
            for p in a.profiles:
                for w in a.weights:
                    print(row(f, p, w, Path(d)), flush=True)


if __name__ == "__main__":
    main()
