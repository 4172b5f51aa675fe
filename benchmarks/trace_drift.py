"""Where a compensated file's clock drifts: the re-planned output, segment by segment.

Run: ``python benchmarks/trace_drift.py FILE [--profile other_delta|default|PATH] [--at T] [--span S]
[--context N]``.  Compensates ``FILE`` (self-check limits lifted, prediction off), re-plans the output
with the firmware-faithful planner (the self-check's own measurement, through its ``TRACE`` hook) and
prints, for the segments around the largest lateness (or around print time ``T``), when each ends,
how late it ends on the absolute clock, its re-planned and intended durations and its line.  A
segment whose re-planned duration exceeds its intended one is where the firmware's limits (its
acceleration caps, junction rules) bind the written command.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from ffcomp.pipeline import self_check  # noqa: E402
from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file  # noqa: E402
from ffcomp.profile import default_profile, load_profile  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def trace(src: Path, profile, opts: CompensateOptions | None = None) -> tuple[object, dict, list[str]]:
    """Compensate ``src``; returns the summary, the per-segment arrays (``line``, ``end_s``,
    ``late_s``, ``dur_s``, ``intended_s``) and the output's lines."""
    opts = opts or CompensateOptions(predict=False, self_check_drift_ms=1e9, self_check_tol_um=1e9)
    out = Path(tempfile.mkdtemp(prefix="trace_drift_")) / "out.gcode"
    self_check.TRACE = []
    try:
        s = compensate_file(str(src), str(out), profile, opts)
        rows = self_check.TRACE
    finally:
        self_check.TRACE = None
    names = ("line", "end_s", "late_s", "dur_s", "intended_s")
    seg = {k: np.concatenate([r[i] for r in rows]) if rows else np.zeros(0) for i, k in enumerate(names)}
    lines = out.read_text().splitlines()
    out.unlink()
    return s, seg, lines


def profile_named(name: str):
    """The profile a benchmark's ``--profile`` names: ``default``, ``other_delta``, or a file."""
    if name == "default":
        return default_profile()
    if name == "other_delta":
        return load_profile(ROOT / "samples" / "profiles" / "other_delta.toml")
    return load_profile(name)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("file", type=Path)
    ap.add_argument("--profile", default="default", help="default, other_delta, or a profile file")
    ap.add_argument("--at", type=float, default=None, help="print time to look at, s (default: the largest lateness)")
    ap.add_argument("--context", type=int, default=20, help="segments before and after")
    a = ap.parse_args()
    s, seg, lines = trace(a.file, profile_named(a.profile))
    print(f"drift max {s.self_check_drift_ms:+.3f} ms near t = {s.self_check_drift_at_s:.3f} s; "
          f"at the end {s.self_check_drift_end_ms:+.3f} ms")
    if not len(seg["late_s"]):
        return
    i = int(np.argmax(np.abs(seg["late_s"]))) if a.at is None else int(np.argmin(np.abs(seg["end_s"] - a.at)))
    print("\n| ends (s) | late (ms) | re-planned (ms) | intended (ms) | line |\n|---|---|---|---|---|")
    for k in range(max(i - a.context, 0), min(i + a.context + 1, len(seg["line"]))):
        ln = int(seg["line"][k])
        print(f"| {seg['end_s'][k]:.4f} | {seg['late_s'][k] * 1e3:+.3f} | {seg['dur_s'][k] * 1e3:.3f} | "
              f"{seg['intended_s'][k] * 1e3:.3f} | {ln}: `{lines[ln - 1][:80] if ln <= len(lines) else ''}` |")


if __name__ == "__main__":
    main()
