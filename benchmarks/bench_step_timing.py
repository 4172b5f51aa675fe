"""Benchmark: quantisation-aware 1 kHz points (step timing) against the firmware's own staircase.

Run: ``python benchmarks/bench_step_timing.py``.  For both profiles (the second compensated with
``other_delta.toml`` and simulated on ``other_delta_truth.toml``) and the quick bench cases plus a
polygon circle and a z loop: the default inverse's exact commands, run through the firmware's step
staircase at 80 steps/mm (steps at the exact crossing times, held on a 50 kHz grid: 20 us, the
size of Klipper's step-compression tolerance), against the same commands with their points moved by
:class:`ffcomp.compensate.step_timing.StepTimer` (lag-aligned RMS, um).  Also the share of samples
with a moved point, the share of samples where a timed carriage reverses against its command (what
keeps the timing out of the G-code output, see the module) and the timer's CPU time per second of
motion.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
UPSAMPLE = 50


def run(title: str, p, truth) -> None:
    from ffcomp.compensate.inverse import invert
    from ffcomp.compensate.step_timing import StepTimer
    from ffcomp.model.lpv import LpvModel
    from ffcomp.sim.bench import bench_cases
    from ffcomp.sim.metrics import evaluate
    from ffcomp.sim.moves import pattern
    from ffcomp.sim.plant import DeltaPlant
    from ffcomp.sim.staircase import simulate_steps

    spm = p.limits.steps_per_mm
    model = LpvModel.from_profile(p)
    plant = DeltaPlant.from_profile(truth or p)
    g = p.geometry_si()
    cases = bench_cases(p, quick=True) + [pattern("polygon", g, (0.0, 0.0, 30.0)),
                                          pattern("zmove", g, (-50.0, -60.0, 30.0))]
    print(f"\n### {title}: step staircase at {spm:g} steps/mm, lag-aligned RMS (um)\n")
    print("| case | lpv, no steps | lpv, firmware steps | lpv, step-timed points | timed / firmware "
          "| points moved | reversals | timer CPU per s |\n|---|---|---|---|---|---|---|---|")
    for tr in cases:
        dt = float(tr.t_s[1] - tr.t_s[0])
        c = invert(model, tr.q_m, tr.xyz_m, dt).q_cmd
        t0 = time.process_time()
        q, moved = StepTimer(model, dt, spm, np.zeros(3))(c, tr.xyz_m)
        cpu = (time.process_time() - t0) / tr.duration_s
        dq, dc = np.diff(q, axis=0), np.diff(c, axis=0)
        rev = float(np.mean(np.any(dq * dc < 0, axis=1) | np.any((dc == 0) & (dq != 0), axis=1)))
        e0 = evaluate(tr.t_s, tr.xyz_m, plant.simulate(tr.t_s, c, hold="linear").xyz_m[0]).lag.rms_norm_um
        ef, et = (evaluate(tr.t_s, tr.xyz_m, simulate_steps(plant, tr.t_s, x, spm, upsample=UPSAMPLE)).lag.rms_norm_um
                  for x in (c, q))
        print(f"| {tr.name} | {e0:.2f} | {ef:.2f} | {et:.2f} | {et / ef:.2f}x | {moved.mean():.2f} | {rev:.2f} "
              f"| {cpu:.2f} s |", flush=True)


def main() -> None:
    from ffcomp.profile import default_profile, load_profile

    run("default", default_profile(), None)
    run("other_delta on its truth", load_profile(ROOT / "samples/profiles/other_delta.toml"),
        load_profile(ROOT / "samples/profiles/other_delta_truth.toml"))


if __name__ == "__main__":
    main()
