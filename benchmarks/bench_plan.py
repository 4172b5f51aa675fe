"""Benchmark: G-code parse + plan + sample throughput and peak memory (target: >= 50,000 lines/s parse+plan).

Run: ``python benchmarks/bench_plan.py [FILE] [--json]``.  Uses ``samples/large/plate_prusa.gcode`` when it
exists, otherwise a synthetic 200,000-line slicer-like file.  Each measurement runs in its own
subprocess on one thread:

* throughput in lines per CPU second (the best of ``--repeats`` runs, so other load on the machine
  does not distort it): parse only, parse + plan, parse + plan + sample (1 kHz, blocks of 4096 with 512
  overlap);
* peak memory (the process's max RSS; exact allocations with ``--tracemalloc``) of parse + plan + sample
  on the file and on the file repeated three times: streaming means the peak must not grow with the length.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import random  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_FILE = ROOT / "samples" / "large" / "plate_prusa.gcode"
TARGET_LINES_S = 50_000


def synthetic_gcode(path: Path, n_lines: int = 200_000, seed: int = 1) -> None:
    """A slicer-like file: layers of perimeters and infill, travels with retraction, comments, fans."""
    rnd = random.Random(seed)
    out = ["; synthetic benchmark file\nG28\nG90\nM83\nM104 S215\nM106 S255\nG1 Z0.3 F3000\n"]
    n = 7
    z = 0.3
    layer = 0
    while n < n_lines:
        out.append(f";LAYER_CHANGE\n;Z:{z:.2f}\nG1 Z{z:.2f} F3000\n;TYPE:External perimeter\n")
        n += 4
        cx, cy = rnd.uniform(-40, 40), rnd.uniform(-40, 40)
        r = rnd.uniform(10, 30)
        for k in range(120):
            a = 2 * math.pi * k / 120
            out.append(f"G1 X{cx + r * math.cos(a):.3f} Y{cy + r * math.sin(a):.3f} E0.0{rnd.randint(10, 99)}"
                       f"{' F1800' if k == 0 else ''}\n")
        n += 120
        out.append(";TYPE:Solid infill\nG1 E-0.8 F2100\nG0 X0 Y0 F12000\nG1 E0.8 F2100\n")
        n += 4
        for k in range(150):
            x = -30 + 60 * (k % 2)
            y = -30 + 0.4 * k
            out.append(f"G1 X{x:.3f} Y{y:.3f} E0.{rnd.randint(100, 999)} F6000\n")
        n += 150
        layer += 1
        z += 0.2
        if z > 250:
            z = 0.3
    path.write_text("".join(out))


def _child(mode: str, path: str) -> dict:
    from ffcomp.gcode import parse_gcode, plan_gcode
    from ffcomp.gcode.sampler import sample_gcode
    from ffcomp.profile import default_profile

    prof = default_profile()
    trace = mode.endswith("+mem")
    if trace:
        import tracemalloc

        tracemalloc.start()
    t0 = time.perf_counter()
    c0 = time.process_time()
    lines = moves = samples = 0
    if mode.startswith("parse"):
        for _ in parse_gcode(path):
            lines += 1
    elif mode.startswith("plan"):
        pl = plan_gcode(path, prof)
        for _ in pl:
            moves += 1
        lines = pl.parser.lines_read
    elif mode.startswith("sample"):
        for b in sample_gcode(path, prof, block_len=4096, overlap=512):
            samples += len(b) - b.overlap
        with open(path, "rb") as f:
            lines = sum(1 for _ in f)
    dt = time.perf_counter() - t0
    cpu = time.process_time() - c0
    res = {"mode": mode, "lines": lines, "moves": moves, "samples": samples, "seconds": dt,
           "cpu_seconds": cpu,
           "lines_per_s": lines / cpu, "samples_per_s": samples / cpu, "wall_lines_per_s": lines / dt,
           "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    if trace:
        import tracemalloc

        res["tracemalloc_peak_mb"] = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    return res


def _run(mode: str, path: Path) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", mode, str(path)], check=True,
                         capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    return json.loads(out.stdout)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file", nargs="?", help="G-code file (default: the large sample or a synthetic file)")
    ap.add_argument("--json", action="store_true", help="print the results as JSON")
    ap.add_argument("--tracemalloc", action="store_true",
                    help="measure memory peaks with tracemalloc (exact Python+numpy allocations, ~5x slower)")
    ap.add_argument("--repeats", type=int, default=3, help="runs of parse and plan; the fastest counts")
    ap.add_argument("--child", nargs=2, metavar=("MODE", "FILE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(*args.child)))
        return 0
    with tempfile.TemporaryDirectory() as td:
        td = Path(td)
        if args.file:
            src = Path(args.file)
        elif DEFAULT_FILE.exists():
            src = DEFAULT_FILE
        else:
            src = td / "synthetic.gcode"
            synthetic_gcode(src)
        big = td / "x3.gcode"
        text = src.read_text(encoding="utf-8", errors="surrogateescape")
        big.write_text(text * 3, encoding="utf-8", errors="surrogateescape")
        res = {"file": str(src)}
        for mode, repeats in (("parse", args.repeats), ("plan", args.repeats), ("sample", 1)):
            runs = [_run(mode, src) for _ in range(repeats)]
            res[mode] = min(runs, key=lambda r: r["cpu_seconds"])
        res["memory_1x"] = res["sample"]
        res["memory_3x"] = _run("sample", big)
        if args.tracemalloc:
            res["memory_1x"] = _run("sample+mem", src)
            res["memory_3x"] = _run("sample+mem", big)
    key = "tracemalloc_peak_mb" if args.tracemalloc else "max_rss_mb"
    m1, m3 = res["memory_1x"][key], res["memory_3x"][key]
    res["memory_growth_3x"] = m3 / m1
    res["target_met"] = res["plan"]["lines_per_s"] >= TARGET_LINES_S
    res["memory_bounded"] = m3 <= 1.25 * m1 + 2.0
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        n_lines, n_moves = res["parse"]["lines"], res["plan"]["moves"]
        print(f"file: {res['file']}  ({n_lines:,} lines, {n_moves:,} planned moves)")
        for mode, what in (("parse", "parse"), ("plan", "parse + plan"), ("sample", "parse + plan + sample")):
            r = res[mode]
            extra = f", {r['samples_per_s'] / 1e6:.2f} M samples/s" if r["samples"] else ""
            print(f"  {what:24s} {r['lines_per_s']:>10,.0f} lines/s  (CPU {r['cpu_seconds']:.2f} s, wall "
                  f"{r['seconds']:.2f} s{extra})")
        met = "met" if res["target_met"] else "NOT met"
        print(f"  target parse + plan >= {TARGET_LINES_S:,} lines/s: {met}")
        for k in ("memory_1x", "memory_3x"):
            r = res[k]
            tm = f"tracemalloc {r['tracemalloc_peak_mb']:.1f} MB, " if "tracemalloc_peak_mb" in r else ""
            print(f"  peak memory, parse + plan + sample, {k[-2:]} file ({r['lines']:,} lines): {tm}"
                  f"max RSS {r['max_rss_mb']:.0f} MB")
        print(f"  memory growth 3x / 1x: {res['memory_growth_3x']:.2f} "
              f"({'bounded' if res['memory_bounded'] else 'GROWS with file length'})")
    return 0 if res["target_met"] and res["memory_bounded"] else 1


if __name__ == "__main__":
    sys.exit(main())
