"""Benchmark: cost of one simulated second of the nonlinear simulator, and its accuracy settings.

Run: ``python benchmarks/bench_sim.py``.  Case: the 60 mm square at (100, 0, 30) mm, 150 mm/s,
10 000 mm/s^2, 1 kHz commands.  Prints

* wall time per simulated second at the defaults (RK4 at 10 kHz, pose matrices every 1 ms) for
  1, 4, 13 (the bench's rows) and 32 runs batched;
* the nozzle-path difference against the reference that re-evaluates the pose matrices at every
  RK4 stage (``pose_every=0``), for several integration rates and hold windows.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from ffcomp.profile import default_profile  # noqa: E402
from ffcomp.sim.moves import pattern  # noqa: E402
from ffcomp.sim.plant import DeltaPlant  # noqa: E402


def _best_time(fn, repeats=3):
    """Smallest CPU time (``process_time``: robust on a shared machine) and the last result."""
    ts = []
    for _ in range(repeats):
        t0 = time.process_time()
        out = fn()
        ts.append(time.process_time() - t0)
    return float(min(ts)), out


def main() -> None:
    prof = default_profile()
    plant = DeltaPlant.from_profile(prof)
    tr = pattern("square", plant.geometry, (100.0, 0.0, 30.0))
    T = tr.duration_s
    print(f"nonlinear simulator, {tr.name}: {T:.2f} s of 1 kHz commands, one thread, CPU seconds")
    print("cost of one simulated second (defaults: RK4 10 kHz, pose matrices every 1 ms):")
    for R in (1, 4, 13, 32):
        q = np.repeat(tr.q_m[None], R, axis=0)
        t, _ = _best_time(lambda q=q: plant.simulate(tr.t_s, q), repeats=2 if R > 4 else 3)
        print(f"  {R:3d} run(s) batched: {t / T:.3f} s per simulated second "
              f"({t / T / R * 1e3:.0f} ms per run-second)")
    # accuracy against the stage-exact reference on the first 0.6 s (two corners)
    n = 600
    t_s, q = tr.t_s[:n], tr.q_m[:n]
    t_ref, ref = _best_time(lambda: plant.simulate(t_s, q, substeps=20, pose_every=0), repeats=1)
    print(f"reference (20 kHz, matrices at every RK4 stage): {t_ref / t_s[-1]:.2f} s per simulated second")
    print("  substeps  pose_every  hold window  max |dX| vs reference   s per simulated second")
    for sub, pe in ((5, 5), (10, 5), (10, 10), (10, 20), (20, 20), (10, 40)):
        t, res = _best_time(lambda sub=sub, pe=pe: plant.simulate(t_s, q, substeps=sub, pose_every=pe),
                            repeats=2)
        err = np.abs(res.xyz_m - ref.xyz_m).max()
        print(f"  {sub:8d}  {pe:10d}  {pe / sub:8.1f} ms  {err * 1e9:12.3f} nm  {t / t_s[-1]:22.3f}")


if __name__ == "__main__":
    main()
