"""Benchmark: evaluate the LPV model at 1,000 poses x 300 frequencies (target: < 1 s on one core).

Run: ``python benchmarks/bench_model.py``.  Prints the median of several repeats for the joint and
task-space responses, the modal summary, and a state-space build.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from ffcomp.model import LpvModel, frequency_response, state_space  # noqa: E402
from ffcomp.model.modes import modes  # noqa: E402
from ffcomp.profile import default_profile  # noqa: E402


def _median_time(fn, repeats=5):
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main() -> None:
    prof = default_profile()
    model = LpvModel.from_profile(prof)
    rng = np.random.default_rng(0)
    r = np.sqrt(rng.uniform(0, 1, 1000)) * prof.geometry.print_radius_mm * 0.999
    th = rng.uniform(0, 2 * np.pi, 1000)
    poses = np.column_stack([r * np.cos(th), r * np.sin(th), rng.uniform(0, 250, 1000)]) * 1e-3
    freqs = np.geomspace(1, 500, 300)
    print(f"LPV model, {len(poses)} poses x {len(freqs)} frequencies, one thread")
    for frame in ("joint", "task"):
        t = _median_time(lambda fr=frame: frequency_response(model, poses, freqs, frame=fr))
        rate = len(poses) * len(freqs) / t / 1e6
        print(f"  frequency_response(frame={frame!r}): {t:.3f} s  ({rate:.2f} M pose-freq/s)")
    t = _median_time(lambda: model.matrices(poses))
    print(f"  pose matrices only: {t * 1e3:.1f} ms")
    t = _median_time(lambda: modes(model, poses))
    print(f"  modal summary: {t * 1e3:.1f} ms")
    t = _median_time(lambda: state_space(model, poses[0]), repeats=20)
    print(f"  one StateSpace build: {t * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
