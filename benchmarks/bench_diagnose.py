"""Benchmark: the model loop on hidden-effect sets it has never seen (issue 11's table).

Run: ``python benchmarks/bench_diagnose.py [--printer other|default|both] [--n 250] [--only NAME]``.

Each set is made by the virtual-measure machinery from a "truth" printer: 44 sweeps (the two
identification sweeps, x/y/z at 7 points and 2 heights), 2 % complex noise, a coherence column as
from 50 averages and **no** ``averages`` header key.  ``other`` is the paper-frame delta of
``samples/profiles/other_delta_truth.toml`` (arm 330, radius 155, H_ez 25 mm); ``default`` the
embedded Monoprice Delta Pro.  The loop then runs as a new user would:

1. ``identify`` from the set's two identification sweeps (masses from the truth), geometry from
   the profile under test (wrong on purpose in the geometry rows);
2. ``diagnose`` -> ``fit`` the best significant candidate (base dynamics refitted with it) ->
   ``diagnose`` ... until nothing significant is left or the verdict is "unexplained";
3. for the motor-mount row, the user's plug-in (``docs/effects_example_motor_mount.py``) is then
   fitted with the base.

Printed per set: what the loop did, the mean complex residual before and after, the noise floor
(from the data) and the ratio, the recovered parameters, and the time (one core; noisy when the
machine is shared).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from ffcomp.loop.diagnose import diagnose  # noqa: E402
from ffcomp.loop.fit import fit_effects, fitted_profile  # noqa: E402
from ffcomp.loop.identify import identify  # noqa: E402
from ffcomp.loop.validate import validate  # noqa: E402
from ffcomp.measure.virtual import virtual_measurements  # noqa: E402
from ffcomp.model.effects import load_plugin  # noqa: E402
from ffcomp.profile import default_profile, load_profile  # noqa: E402
from ffcomp.profile_set import set_values  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PLUGIN = ROOT / "docs" / "effects_example_motor_mount.py"
BELT = {"name": "belt_span", "l1_ref_mm": 300.0, "loop_mm": 1300.0}
TOWER_B = {"name": "tower_scale", "k_scale_B": 0.75}
FOREARM = {"name": "forearm_inertia", "scale": 1.0}
MOUNT = {"name": "motor_mount", "f_hz": 250.0, "zeta": 0.03, "mu": 0.6, "zeta_zero": 0.02}

# name -> (hidden effects, geometry change of the profile under test, what to check)
SETS = {
    "no hidden effect": ([], {}, "nothing reported, <= 1.25x"),
    "belt_span": ([BELT], {}, "first + applied, <= 1.5x, l1_ref_mm within 10 %"),
    "tower B 25 % softer": ([TOWER_B], {}, "first + applied, <= 1.5x, k_scale_B within 10 %"),
    "belt + tower B + forearm": ([BELT, TOWER_B, FOREARM], {}, "all three, <= 1.75x"),
    "delta radius 5 mm too large": ([], {"delta_radius_mm": 5.0}, "named as geometry"),
    "arm length 10 mm too long": ([], {"arm_length_mm": 10.0}, "named as geometry"),
    "firmware frame 210/330/90": ([], {"tower_angles_deg": (210.0, 330.0, 90.0)}, "named as geometry"),
    "motor mount (outside the library)": ([MOUNT], {}, "unexplained + band; plug-in <= 1.5x"),
}


def _truth(printer: str):
    if printer == "other":
        return load_profile(ROOT / "samples" / "profiles" / "other_delta_truth.toml")
    return default_profile()


def _under_test(truth, ms, geometry: dict):
    c = next(m for m in ms if m.kind == "carriage")
    a = next(m for m in ms if m.kind == "assembled" and m.input == "z" and m.output == "qA")
    ident = identify(c, a, truth.dynamics.m_n, truth.dynamics.m_f)
    prof = ident.apply_to(truth).with_(name="identified")
    # radius and arm length: offsets from the truth; tower angles: absolute
    g = {k: (tuple(v) if isinstance(v, tuple) else tuple(float(x) + v for x in getattr(prof.geometry, k)))
         for k, v in geometry.items()}
    return ident, prof.with_(geometry=replace(prof.geometry, **g)) if g else prof


def run_set(printer: str, name: str, n_freq: int) -> dict:
    hidden, geometry, _ = SETS[name]
    truth = _truth(printer)
    ms = virtual_measurements(truth, hidden, freq_hz=np.geomspace(5.0, 400.0, n_freq), noise=0.02, seed=31,
                              averages=50, averages_key=False)
    t0 = time.perf_counter()
    ident, prof = _under_test(truth, ms, geometry)
    start = validate(prof, ms)
    did, params = [], []
    if ident.warnings:
        did.append(f"identify warned ({len(ident.warnings)})")
    d = None
    for _ in range(5):
        d = diagnose(prof, ms)
        if d.status in ("ok", "unexplained") or not d.significant:
            break
        best = d.significant[0]
        if best.kind == "geometry":  # the user corrects the profile (ffcomp profile set) and goes on
            did.append(f"geometry named: {best.set_value}")
            prof = set_values(prof, [best.set_value])
            continue
        fit = fit_effects(prof, ms, [] if best.refit else [best.effect])
        prof = fitted_profile(prof, fit)
        did.append(f"{best.label} ({best.removed:.0%})")
        params = [f"{e.effect}:{e.param}={e.value:.4g}" + ("(at bound)" if e.at_bound else "")
                  for e in fit.estimates if e.effect not in ("base",) and abs(e.value - e.start) > 1e-9]
    did.append(f"{d.status}" + (": fixed band" if any(e.key == "fixed_band" for e in d.evidence) else ""))
    end = validate(prof, ms)
    if hidden and hidden[0]["name"] == "motor_mount":
        fit = fit_effects(prof, ms, ["motor_mount"])
        prof = fitted_profile(prof, fit)
        end = validate(prof, ms)
        did.append("plug-in motor_mount fitted")
        params = [f"{e.param}={e.value:.4g}" for e in fit.estimates if e.effect == "motor_mount"]
    return {"printer": printer, "set": name, "did": "; ".join(did), "start": start.mean_residual,
            "end": end.mean_residual, "noise": end.noise_floor, "ratio": end.mean_residual / end.noise_floor,
            "params": ", ".join(params), "seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--printer", choices=("other", "default", "both"), default="other")
    ap.add_argument("--n", type=int, default=250, help="frequencies per sweep")
    ap.add_argument("--only", default=None, help="run only the sets whose name contains this")
    args = ap.parse_args()
    load_plugin(str(PLUGIN))  # to hide the motor mount; diagnose only tries it once named
    printers = ("other", "default") if args.printer == "both" else (args.printer,)
    print("| printer | set | what the loop did | mean complex residual | noise | end / noise | parameters | time (s) |")
    print("|---|---|---|---|---|---|---|---:|")
    for printer in printers:
        for name in SETS:
            if args.only and args.only not in name:
                continue
            r = run_set(printer, name, args.n)
            print(f"| {r['printer']} | {r['set']} | {r['did']} | {r['start']:.4f} -> {r['end']:.4f} | "
                  f"{r['noise']:.4f} | {r['ratio']:.2f} | {r['params']} | {r['seconds']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
