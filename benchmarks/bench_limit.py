"""Benchmark: how far each compensation row sits from the physical limit, on both profiles.

Rows: no compensation, the default inverse (``lpv``: quintic spline, 4 ms knots), the accuracy
setting (``lpv-fine``: cubic spline, a knot per 1 kHz sample, :data:`ffcomp.compensate.inverse.FINE`)
and the physical limit (``limit``: a linear spline with a knot per sample, iterated on the model's
own nonlinear plant, see :mod:`ffcomp.compensate.limit`).  Also prints the inverse's CPU time per
second of motion for each row (noisy on a shared machine).

Cases: every synthetic bench case (squares and zig-zags at five bed positions, the 64-segment
polygon circle at 200 mm/s in the centre and off-centre, z loops) and
4 s windows of the stress samples, all at 10,000 mm/s^2.

Profiles: the default (compensated and simulated with the same profile) and the held-out printer
(compensated with ``samples/profiles/other_delta.toml``, simulated with ``other_delta_truth.toml``).

Run: ``python benchmarks/bench_limit.py [--quick]`` (full: about ten minutes on one core).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ROWS = ["none", "lpv", "lpv-fine", "limit"]


def cost_line(prof, res) -> str:
    """CPU seconds of each row's commands per second of motion, on the first three cases."""
    from ffcomp.sim.bench import VARIANTS

    parts = []
    for name in ROWS[1:]:
        t0, T = time.process_time(), 0.0
        for c in res.cases[:3]:
            tr = c.trajectory
            VARIANTS[name](prof, tr.t_s, tr.xyz_m, tr.q_m)
            T += tr.duration_s
        parts.append(f"{name} {(time.process_time() - t0) / T:.3f} s")
    return "Inverse CPU time per second of motion (first three cases): " + ", ".join(parts) + "\n"


def main(quick: bool = False) -> None:
    from ffcomp.profile import default_profile, load_profile
    from ffcomp.sim.bench import markdown_table, run_bench

    pairs = [("default profile", default_profile(), None),
             ("other_delta.toml on other_delta_truth.toml",
              load_profile(ROOT / "samples/profiles/other_delta.toml"),
              load_profile(ROOT / "samples/profiles/other_delta_truth.toml"))]
    for title, prof, plant in pairs:
        t0 = time.process_time()
        res = run_bench(prof, quick=quick, variants=ROWS, plant_profile=plant, include_gcode=not quick)
        print(f"## {title}\n")
        print(markdown_table(res))
        print(cost_line(prof, res))
        print(f"(CPU {time.process_time() - t0:.0f} s for the table)\n", flush=True)


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
