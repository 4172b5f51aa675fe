"""Benchmark: the validation loop on a default-size virtual data set (44 sweeps x 250 frequencies).

Run: ``python benchmarks/bench_diagnose.py``.  Prints the time of: generating the measurements,
``validate``, ``diagnose`` (5 candidates, 4-fold cross-validation by pose), ``fit`` of the found
effect, and the HTML report; and checks that the hidden effect was found.  Targets on one core:
validate < 1 s, diagnose < 10 s, fit < 3 s.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from ffcomp.loop.diagnose import diagnose  # noqa: E402
from ffcomp.loop.fit import fit_effects  # noqa: E402
from ffcomp.loop.validate import validate  # noqa: E402
from ffcomp.measure.virtual import virtual_measurements  # noqa: E402
from ffcomp.profile import default_profile  # noqa: E402

HIDDEN = [{"name": "belt_span", "l1_ref_mm": 320.0, "loop_mm": 1300.0}]


def _timed(label, fn):
    t0 = time.perf_counter()
    out = fn()
    print(f"{label:<44s} {time.perf_counter() - t0:7.2f} s")
    return out


def main() -> None:
    prof = default_profile()
    f = np.geomspace(5.0, 400.0, 250)
    ms = _timed("virtual measurements (44 x 250)", lambda: virtual_measurements(prof, HIDDEN, freq_hz=f, seed=1))
    rep = _timed("validate", lambda: validate(prof, ms))
    d = _timed("diagnose (5 candidates, 4 folds)", lambda: diagnose(prof, ms))
    fit = _timed(f"fit {d.best.effect}", lambda: fit_effects(prof, ms, [d.best.effect]))
    after = validate(prof.with_(effects=fit.effects), ms)
    with tempfile.TemporaryDirectory() as tmp:
        from ffcomp.report.validate_report import html_report

        _timed("HTML report (12 Bode overlays)", lambda: html_report(Path(tmp) / "r.html", after, others=(rep,)))
    print(f"found {d.best.effect} ({d.status}); residual {rep.mean_residual:.4f} -> {after.mean_residual:.4f} "
          f"(noise {after.noise_floor:.4f}); parameters "
          + ", ".join(f"{e.param}={e.value:.4g}" for e in fit.estimates))


if __name__ == "__main__":
    main()
