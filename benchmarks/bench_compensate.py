"""Benchmark: compensation speed and memory on the big real-slicer file, and the accuracy/time
trade-off of the inverse variants.

Run: ``python benchmarks/bench_compensate.py [--file F] [--quick] [--profile] [--steps]``.  The big sample
(samples/large/plate_prusa.gcode, ~244k lines, ~3.4 h of printing) is regenerated with PrusaSlicer
if missing (``python samples/make_samples.py --large``).  One thread; prints a Markdown table.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BIG = ROOT / "samples" / "large" / "plate_prusa.gcode"


def run_file(path: Path, args: list[str], suffix: str = ".gcode") -> dict:
    """One compensation in a fresh process (so peak memory is its own)."""
    out = Path("/tmp") / f"bench_out_{os.getpid()}{suffix}"
    cmd = [sys.executable, "-c",
           "import resource, sys, json; from ffcomp.cli import main\n"
           "try:\n    main(sys.argv[1:])\nexcept SystemExit as e:\n    code = e.code\n"
           "print(json.dumps({'maxrss_kb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}), file=sys.stderr)",
           str(path), "-o", str(out), "--json", "--no-progress", *args]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"compensation failed: {r.stderr[-2000:]}")
    d = json.loads(r.stdout)
    d["maxrss_mb"] = json.loads(r.stderr.strip().splitlines()[-1])["maxrss_kb"] / 1024
    d["process_wall_s"] = wall
    d["out_bytes"] = out.stat().st_size
    out.unlink()
    return d


def variants_table() -> list[str]:
    sys.path.insert(0, str(ROOT / "tests"))
    from trajectories import square, trapezoid_path

    from ffcomp.compensate.inverse import METHODS, InverseConfig, invert
    from ffcomp.compensate.predict import predict_lpv
    from ffcomp.kinematics import inverse, jacobian
    from ffcomp.model import LpvModel
    from ffcomp.profile import default_profile

    model = LpvModel.from_profile(default_profile())
    rows = ["| variant | centre square RMS (um) | 100 mm square RMS (um) | time per print second (ms) |",
            "|---|---|---|---|"]
    paths = {}
    for name, pts in (("c", square(0, 0)), ("o", square(100, 0, side=50))):
        X = trapezoid_path(pts)
        paths[name] = (X, inverse(model.geometry, X), jacobian(model.geometry, X))

    def rms(X, q, J, qc):
        e = np.einsum("nij,nj->ni", J, predict_lpv(model, qc, X, 1e-3) - q)
        return float(np.sqrt(np.mean(np.sum(e**2, 1)))) * 1e6

    base = {k: rms(X, q, J, q) for k, (X, q, J) in paths.items()}
    rows.append(f"| none | {base['c']:.1f} | {base['o']:.1f} | - |")
    for meth in METHODS:
        res, tsum, dur = {}, 0.0, 0.0
        for k, (X, q, J) in paths.items():
            t0 = time.perf_counter()
            r = invert(model, q, X, 1e-3, InverseConfig(method=meth))
            tsum += time.perf_counter() - t0
            dur += len(q) * 1e-3
            res[k] = rms(X, q, J, r.q_cmd)
        rows.append(f"| {meth} | {res['c']:.2f} | {res['o']:.2f} | {tsum / dur * 1e3:.1f} |")
    return rows


def profile_shares(path: Path, n_lines: int = 12000) -> None:
    """Where the time goes: cProfile over the first ``n_lines`` lines, shares of the main stages."""
    import cProfile
    import pstats

    from ffcomp.pipeline.compensate_flow import compensate_file
    from ffcomp.profile import default_profile

    part = Path("/tmp") / f"bench_profile_{os.getpid()}.gcode"
    with open(path) as f, open(part, "w") as g:
        for i, ln in enumerate(f):
            if i >= n_lines:
                break
            g.write(ln)
    prof = cProfile.Profile()
    prof.runcall(compensate_file, str(part), str(part.with_suffix(".out.gcode")), default_profile())
    st = pstats.Stats(prof)
    import inspect

    from ffcomp.compensate import pin_repair as prp
    from ffcomp.compensate.stream_inverse import StreamingInverse
    from ffcomp.gcode.writer import GcodeWriter
    from ffcomp.pipeline import compensate_flow as cf
    from ffcomp.pipeline import predictor as pr
    from ffcomp.pipeline import self_check as sc

    def key(fn):
        return (inspect.getsourcefile(fn), inspect.getsourcelines(fn)[1], fn.__name__)

    cum = {k: v[3] for k, v in st.stats.items()}
    total = cum[key(cf._compensate_file)]
    stages = {"G-code writer": key(GcodeWriter.feed), "streaming inverse": key(StreamingInverse.push),
              "self-check re-plan": key(sc.self_check), "LPV prediction for the summary": key(pr.Predictor.flush),
              "pin repair (re-solved windows)": key(prp.repair_window)}
    print(f"\nTime profile of the first {n_lines:,} lines ({total:.1f} s under cProfile):\n")
    print("| part | share |\n|---|---|")
    for name, key in stages.items():
        print(f"| {name} | {cum.get(key, 0.0) / total * 100:.0f} % |")
    for p_ in (part, part.with_suffix(".out.gcode")):
        p_.unlink(missing_ok=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--file", type=Path, default=BIG)
    ap.add_argument("--quick", action="store_true", help="first 20,000 lines of the file only")
    ap.add_argument("--profile", action="store_true", help="only the time profile of the first 12,000 lines")
    ap.add_argument("--steps", action="store_true", help="only the step-stream output (--format steps)")
    a = ap.parse_args()
    path = a.file
    if not path.exists() and path == BIG:
        subprocess.run([sys.executable, str(ROOT / "samples" / "make_samples.py"), "--large"], check=True)
    if a.profile:
        profile_shares(path)
        return
    if a.quick:
        q = Path("/tmp/bench_quick.gcode")
        with open(path) as f, open(q, "w") as g:
            for i, ln in enumerate(f):
                if i >= 20000:
                    break
                g.write(ln)
        path = q
    n_lines = sum(1 for _ in open(path))
    print(f"file: {path} ({n_lines:,} lines)\n")
    if a.steps:
        d = run_file(path, ["--format", "steps"], suffix=".ffsteps")
        print("| output | print time | wall time | print/wall | peak RSS | steps | queue lines | max error |")
        print("|---|---|---|---|---|---|---|---|")
        print(f"| .ffsteps | {d['print_time_s'] / 3600:.2f} h | {d['wall_time_s']:.1f} s | "
              f"{d['print_time_s'] / d['wall_time_s']:.0f}x | {d['maxrss_mb']:.0f} MB | {d['steps']:,} | "
              f"{d['queue_lines']:,} | {d['max_step_error_steps']:.2f} steps |")
        return
    print("| run | print time | wall time | print/wall | of which prediction / self-check | peak RSS "
          "| predicted RMS before -> after | self-check max | drift max / at end |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, args in (("full (predict + self-check)", []),
                        ("no prediction, no self-check", ["--no-predict", "--no-self-check"])):
        d = run_file(path, args)
        pred = (f"{d['rms_before_um']:.1f} -> {d['rms_after_um']:.2f} um" if d.get("rms_before_um") else "-")
        sc = f"{d['self_check_max_um']:.1f} um" if d.get("self_check_max_um") is not None else "-"
        dr = (f"{d['self_check_drift_ms']:+.2f} / {d['self_check_drift_end_ms']:+.2f} ms"
              if d.get("self_check_drift_ms") is not None else "-")
        checks = (f"{d['predict_time_s']:.1f} / {d['self_check_time_s']:.1f} s"
                  if d.get("predict_time_s") is not None and d.get("self_check_time_s") is not None else "-")
        print(f"| {label} | {d['print_time_s'] / 3600:.2f} h | {d['wall_time_s']:.1f} s | "
              f"{d['print_time_s'] / d['wall_time_s']:.0f}x | {checks} | {d['maxrss_mb']:.0f} MB | {pred} | {sc} "
              f"| {dr} |")
    print("\nInverse variants on 10,000 mm/s^2 squares (LPV model as judge):\n")
    print("\n".join(variants_table()))


if __name__ == "__main__":
    main()
