"""Benchmark: the multi-core speed-up of ``--jobs N`` on the big real-slicer file.

Run: ``python benchmarks/bench_parallel.py [--file F] [--jobs 1 2] [--repeat R]``.  Each run is a fresh
``ffcomp`` process with prediction and self-check on (the defaults); the table gives the wall time, the
speed ratio (print time / wall time), the peak RSS of the main process and of the largest worker, the
self-check's numbers and the output's re-planned print time, then the speed-up of every job count
over ``--jobs 1`` (best of ``--repeat`` runs each).  The load average before and after is printed:
on a shared machine the other processes' load takes cores from the workers.
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

ROOT = Path(__file__).resolve().parents[1]
BIG = ROOT / "samples" / "large" / "plate_prusa.gcode"


def run(path: Path, jobs: int, extra: list[str]) -> dict:
    out = Path("/tmp") / f"bench_par_{os.getpid()}_{jobs}.gcode"
    code = ("import resource, sys, json; from ffcomp.cli import main\n"
            "try:\n    main(sys.argv[1:])\nexcept SystemExit as e:\n    pass\n"
            "print(json.dumps({'self_kb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,"
            " 'child_kb': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss,"
            " 'self_cpu': sum(resource.getrusage(resource.RUSAGE_SELF)[:2]),"
            " 'child_cpu': sum(resource.getrusage(resource.RUSAGE_CHILDREN)[:2])}), file=sys.stderr)")
    cmd = [sys.executable, "-c", code, str(path), "-o", str(out), "--json", "--no-progress", "--jobs", str(jobs),
           *extra]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"--jobs {jobs} failed: {r.stderr[-2000:]}")
    d = json.loads(r.stdout)
    rss = json.loads(r.stderr.strip().splitlines()[-1])
    d["rss_main_mb"], d["rss_worker_mb"] = rss["self_kb"] / 1024, rss["child_kb"] / 1024
    d["cpu_main_s"], d["cpu_workers_s"] = rss["self_cpu"], rss["child_cpu"]
    # the critical path on free cores: the main process's own CPU time (it waits while the workers
    # run) plus the slowest worker's
    pieces = d.get("pieces") or []
    d["critical_s"] = d["cpu_main_s"] + max((p["cpu_s"] for p in pieces), default=0.0)
    d["process_wall_s"] = wall
    out.unlink()
    return d


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--file", type=Path, default=BIG)
    ap.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--no-self-check", action="store_true")
    a = ap.parse_args(argv)
    if not a.file.exists():
        raise SystemExit(f"{a.file} is missing: python samples/make_samples.py --large")
    extra = ["--no-self-check"] if a.no_self_check else []
    print(f"file: {a.file.name}; cores: {os.cpu_count()}; load average before: {os.getloadavg()}")
    best: dict[int, dict] = {}
    for _ in range(a.repeat):
        for j in a.jobs:
            d = run(a.file, j, extra)
            print(f"  --jobs {j}: {d['process_wall_s']:.1f} s", flush=True)
            if j not in best or d["process_wall_s"] < best[j]["process_wall_s"]:
                best[j] = d
    print(f"load average after: {os.getloadavg()}\n")
    print("| jobs | print time | wall time | print/wall | CPU main + workers | critical path (CPU) | "
          "peak RSS main / worker | self-check max | drift max | output print time |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for j in a.jobs:
        d = best[j]
        ratio = d["print_time_s"] / d["process_wall_s"]
        sc = "-" if d.get("self_check_max_um") is None else f"{d['self_check_max_um']:.1f} um"
        dr = "-" if d.get("self_check_drift_ms") is None else f"{d['self_check_drift_ms']:+.2f} ms"
        op = "-" if d.get("output_print_time_s") is None else f"{d['output_print_time_s']:.2f} s"
        worker = f"{d['rss_worker_mb']:.0f} MB" if j > 1 else "-"
        print(f"| {j} | {d['print_time_s'] / 3600:.2f} h | {d['process_wall_s']:.1f} s | {ratio:.0f}x | "
              f"{d['cpu_main_s']:.1f} + {d['cpu_workers_s']:.1f} s | {d['critical_s']:.1f} s | "
              f"{d['rss_main_mb']:.0f} MB / {worker} | {sc} | {dr} | {op} |")
    for j in a.jobs:
        for i, p in enumerate(best[j].get("pieces") or []):
            print(f"  --jobs {j} piece {i + 1}: from line {p['first_line']}, ends at {p['cut'] or 'the end'}, "
                  f"print {p['print_s']:.0f} s, worker wall {p['wall_s']:.1f} s, CPU {p['cpu_s']:.1f} s")
    if 1 in best:
        print()
        for j in a.jobs:
            if j != 1:
                b1, bj = best[1], best[j]
                print(f"speed-up --jobs {j} over --jobs 1: {b1['process_wall_s'] / bj['process_wall_s']:.2f}x measured "
                      f"(wall); {b1['critical_s'] / bj['critical_s']:.2f}x on free cores (CPU critical path)")


if __name__ == "__main__":
    main()
