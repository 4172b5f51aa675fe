"""Benchmark: the clock on small random files, on both profiles.

Run: ``python benchmarks/bench_random_drift.py [--n N] [--seed S] [--repair KEY=VALUE] [--dump DIR]``.
Generates ``N`` small random G-code files (deterministic for a seed: optionally G28, 3-8 moves inside
a 40 mm radius, z 0.2-8 mm rising, some z-only, some extruding or retracting, some extruder-only moves
between them), compensates each on the default profile and on ``samples/profiles/other_delta.toml``
alternately (self-check limits lifted, so every file is measured) and prints, per profile, how many files drift
more than 0.2 ms and 1 ms on the absolute clock, the median and the largest drift, the clock error
(the largest distance of the re-planned output from the intended command at the same instant, um;
its median and largest over the files), and the worst file.  What the hypothesis test
``tests/test_compensate_random.py`` checks with loose bounds.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file  # noqa: E402
from ffcomp.profile import default_profile, load_profile  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def random_file(rng: np.random.Generator) -> str:
    """One small random file (see the module docstring)."""
    lines = ["G90", "M83"] + (["G28"] if rng.random() < 0.5 else [])
    z = 0.0
    for i in range(int(rng.integers(3, 9))):
        w = ["G1"]
        xy = i == 0 or rng.random() < 0.6
        if xy:
            r, a = rng.uniform(0, 40), rng.uniform(0, 2 * np.pi)
            w += [f"X{r * np.cos(a):.3f}", f"Y{r * np.sin(a):.3f}"]
        if i == 0 or not xy or rng.random() < 0.4:
            z = rng.uniform(0.2, 8) if i == 0 else z + rng.uniform(0.2, 4)
            w.append(f"Z{z:.3f}")
        if i > 0 and rng.random() < 0.5:
            w.append(f"E{rng.uniform(-1, 2):.4f}")
        w.append(f"F{int(rng.integers(1200, 15000))}")
        if len(w) > 2:
            lines.append(" ".join(w))
        if rng.random() < 0.2:
            lines.append(f"G1 E{rng.choice([-0.8, 0.8])} F2100")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=80, help="files (half on each profile)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--repair", action="append", default=[], metavar="KEY=VALUE",
                    help="a RepairConfig field of the pin repair (as bench_gcode_fidelity.py --repair)")
    ap.add_argument("--dump", type=Path, default=None,
                    help="write every file that drifts more than 0.2 ms here, as PROFILE-K.gcode, to trace")
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    profs = [("default", default_profile()), ("other_delta", load_profile(ROOT / "samples/profiles/other_delta.toml"))]
    tmp = Path(tempfile.mkdtemp(prefix="bench_random_"))
    extra = {}
    if a.repair:
        from bench_gcode_fidelity import repair_from_args

        extra["repair"] = repair_from_args(a.repair)
    res: dict[str, list] = {name: [] for name, _ in profs}
    for k in range(a.n):
        name, prof = profs[k % 2]
        text = random_file(rng)
        src = tmp / "r.gcode"
        src.write_text(text)
        try:
            s = compensate_file(str(src), str(tmp / "o.gcode"), prof,
                                CompensateOptions(predict=False, self_check_drift_ms=1e9, self_check_tol_um=1e9,
                                                  **extra))
            res[name].append((abs(s.self_check_drift_ms), s.self_check_max_um, s.self_check_abs_max_um, text))
            if a.dump is not None and abs(s.self_check_drift_ms) > 0.2:
                a.dump.mkdir(parents=True, exist_ok=True)
                (a.dump / f"{name}-{k:03d}.gcode").write_text(f"; drift {s.self_check_drift_ms:+.3f} ms\n" + text)
        except Exception as e:  # a failure is a row
            res[name].append((float("nan"), float("nan"), float("nan"), f"{type(e).__name__}: {e}"[:200]))
    print("| profile | files | failed | drift > 0.2 ms | drift > 1 ms | median drift (ms) | max drift (ms) "
          "| self-check max (um) | median / max clock error (um) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, rows in res.items():
        d = np.array([r[0] for r in rows])
        sc = np.array([r[1] for r in rows])
        ce = np.array([r[2] for r in rows])
        print(f"| {name} | {len(d)} | {int(np.isnan(d).sum())} | {int(np.sum(d > 0.2))} | {int(np.sum(d > 1.0))} "
              f"| {np.nanmedian(d):.3f} | {np.nanmax(d):.3f} | {np.nanmax(sc):.1f} "
              f"| {np.nanmedian(ce):.1f} / {np.nanmax(ce):.1f} |")
    for name, rows in res.items():
        worst = max((r for r in rows if np.isfinite(r[0])), key=lambda r: r[0])
        print(f"\nworst on {name} ({worst[0]:.3f} ms):\n\n```\n{worst[3]}```")


if __name__ == "__main__":
    main()
