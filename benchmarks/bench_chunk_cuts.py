"""Benchmark: how the clock of a compensated file depends on where the pipeline's chunks end.

The writer gets the samples in chunks and holds back the last samples of a chunk where a cut would
split what it writes as one piece (a corner, a ratio change, a rest: ``writer.CARRY_*``).  This
script compensates one file many times, with the chunk that holds plan sample ``k`` cut in two there
(the tests' ``_cut_chunks_at`` wrapper of ``GcodeWriter.feed``), for every ``--step``-th ``k`` in
``[--from, --to)``, and prints the uncut run's largest drift on the absolute clock (ms), how many
cuts move it by more than 0.05 ms, the largest drift of any cut, and the worst cuts.

Run: ``python benchmarks/bench_chunk_cuts.py CASE [--profile other_delta|default|PATH] [--step N]
[--from K] [--to K]``.  ``CASE`` is a file, or one of the excerpts the timing tests hold:
``retracting_lift`` (``RETRACTING_LIFT``), ``tower_layer_change``, ``hop`` (the plate's z-hop),
``gyroid_hop``.  About 0.7 s per cut on one core.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import argparse  # noqa: E402
import tempfile  # noqa: E402

import pytest  # noqa: E402
import test_timing  # noqa: E402
from trace_drift import profile_named  # noqa: E402

CASES = {"retracting_lift": "RETRACTING_LIFT", "tower_layer_change": "TOWER_LAYER_CHANGE", "hop": "HOP",
         "gyroid_hop": "GYROID_HOP"}


def scan(text: str, profile, ks) -> tuple[float, list[tuple[int, float]]]:
    """The uncut drift (ms) and ``(k, drift ms)`` for a cut at each plan sample of ``ks``."""
    mp = pytest.MonkeyPatch()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            _, drift_ms = test_timing._cut_drift(Path(tmp), mp, text, profile)
            return drift_ms(), [(k, drift_ms(k)) for k in ks]
    finally:
        mp.undo()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", help="a G-code file, or " + ", ".join(CASES))
    ap.add_argument("--profile", default="other_delta", help="default, other_delta, or a profile file")
    ap.add_argument("--step", type=int, default=5, help="cut at every step-th plan sample")
    ap.add_argument("--from", dest="k0", type=int, default=1, help="first plan sample to cut at")
    ap.add_argument("--to", dest="k1", type=int, default=None, help="plan sample to stop before (default: the end)")
    a = ap.parse_args()
    text = getattr(test_timing, CASES[a.case]) if a.case in CASES else Path(a.case).read_text()
    prof = profile_named(a.profile)
    with tempfile.TemporaryDirectory() as tmp:
        moves, _ = test_timing._cut_drift(Path(tmp), pytest.MonkeyPatch(), text, prof)
    end = int(max(m.t_end_s for m in moves.values()) * 1000)
    ks = range(a.k0, min(a.k1, end) if a.k1 is not None else end, a.step)
    uncut, res = scan(text, prof, ks)
    off = [(k, d) for k, d in res if abs(d - uncut) > 0.05]
    worst = sorted(off, key=lambda r: -abs(r[1]))[:10]
    print(f"{a.case} on {a.profile}: uncut drift {uncut:+.3f} ms; {len(res)} cuts; "
          f"{len(off)} more than 0.05 ms off the uncut; largest |drift| "
          f"{max(abs(d) for _, d in res) if res else float('nan'):.3f} ms")
    if worst:
        print("worst cuts (plan sample: drift ms): " + ", ".join(f"{k}: {d:+.3f}" for k, d in worst))


if __name__ == "__main__":
    main()
