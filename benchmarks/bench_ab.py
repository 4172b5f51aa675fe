"""Benchmark: this tree against another revision, back to back, on the same file.

The shared machine's speed wanders by 10-15 % within minutes, so a table measured today says little
against one measured yesterday; runs of two codes interleaved on the same machine do.

Run: ``python benchmarks/bench_ab.py REV [--lines 40000] [--rounds 2] [--file F] [--profile P]``.
``REV`` is any git revision of this repository (checked out into a temporary worktree, removed
afterwards).  Each run is a fresh process on one thread compensating the first ``--lines`` lines of
the file (default: the big plate, regenerated if missing) with the default options (prediction and
self-check on); the runs alternate ``REV``, this tree, ``REV``, ...  Prints the wall and CPU time of
every run, the print/wall ratios, the prediction's and the self-check's time (where the code reports
them: ``predict_time_s``, ``self_check_time_s``), and whether the two outputs are byte for byte equal.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BIG = ROOT / "samples" / "large" / "plate_prusa.gcode"

_RUN = """
import json, resource, sys, time
from ffcomp.pipeline.compensate_flow import compensate_file
from ffcomp.profile import default_profile, load_profile
prof = load_profile(sys.argv[3]) if sys.argv[3] else default_profile()
t0, c0 = time.perf_counter(), time.process_time()
s = compensate_file(sys.argv[1], sys.argv[2], prof)
print(json.dumps({"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                  "print_s": s.print_time_s, "predict_s": getattr(s, "predict_time_s", None),
                  "check_s": getattr(s, "self_check_time_s", None)}))
"""


def run(code_root: Path, src: Path, out: Path, profile: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(code_root))
    r = subprocess.run([sys.executable, "-c", _RUN, str(src), str(out), profile], capture_output=True, text=True,
                       env=env, cwd=code_root)
    if r.returncode != 0:
        raise SystemExit(f"the run of {code_root} failed:\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def md5(path: Path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rev", help="the git revision to compare with (e.g. HEAD~3, a commit)")
    ap.add_argument("--file", type=Path, default=BIG)
    ap.add_argument("--lines", type=int, default=40000, help="the first N lines of the file (0: all)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--profile", default="", help="a profile file (default: the embedded default profile)")
    a = ap.parse_args()
    if not a.file.exists() and a.file == BIG:
        subprocess.run([sys.executable, str(ROOT / "samples" / "make_samples.py"), "--large"], check=True)
    profile = str(Path(a.profile).resolve()) if a.profile else ""
    with tempfile.TemporaryDirectory(prefix="ffcomp_ab_") as tmp:
        tmp = Path(tmp)
        src = tmp / "src.gcode"
        with open(a.file, encoding="utf-8", errors="surrogateescape", newline="") as f, \
                open(src, "w", encoding="utf-8", errors="surrogateescape", newline="") as g:
            for i, ln in enumerate(f):
                if a.lines and i >= a.lines:
                    break
                g.write(ln)
        wt = tmp / "rev"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(wt), a.rev], check=True)
        try:
            rows = []
            for k in range(a.rounds):
                for name, root in ((a.rev, wt), ("this tree", ROOT)):
                    out = tmp / f"out_{'rev' if root == wt else 'this'}.gcode"
                    d = run(root, src, out, profile)
                    rows.append((name, k + 1, d))
                    print(f"round {k + 1}, {name}: {d['wall_s']:.2f} s wall, {d['cpu_s']:.2f} s CPU, "
                          f"{d['print_s'] / d['wall_s']:.0f}x", flush=True)
            same = md5(tmp / "out_rev.gcode") == md5(tmp / "out_this.gcode")
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(wt)], check=False)
    print(f"\nfile: {a.file.name}, first {a.lines or 'all'} lines ({rows[0][2]['print_s']:.0f} s of printing)\n")
    print("| code | wall time per run | CPU time per run | print/wall (mean) | of which prediction / self-check |")
    print("|---|---|---|---|---|")
    for name in (a.rev, "this tree"):
        ds = [d for n, _, d in rows if n == name]
        walls = " / ".join(f"{d['wall_s']:.2f}" for d in ds)
        cpus = " / ".join(f"{d['cpu_s']:.2f}" for d in ds)
        ratio = sum(d["print_s"] / d["wall_s"] for d in ds) / len(ds)
        checks = " / ".join(f"{d['predict_s']:.2f} + {d['check_s']:.2f}" for d in ds
                            if d.get("predict_s") is not None and d.get("check_s") is not None) or "-"
        print(f"| {name} | {walls} s | {cpus} s | {ratio:.0f}x | {checks} s |")
    print(f"\noutputs byte for byte equal: {'yes' if same else 'no'}")


if __name__ == "__main__":
    main()
