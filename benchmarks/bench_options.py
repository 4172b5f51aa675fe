"""Benchmark: what the G-code output options cost, the G-code output on the simulator, the floor
that step quantisation sets, and what the quantisation-aware step stream recovers.  Prints the
figures README quotes.

Run: ``python benchmarks/bench_options.py`` (about two minutes).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def options_table() -> None:
    src = ROOT / "samples" / "gcode" / "stress_square_off100.gcode"
    print(f"G-code output options on {src.name} (LPV-model prediction, um):\n")
    print("| option | RMS before | RMS after | max after | self-check max | catch-up max |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as td:
        for args in (["--z-mode", "keep"], ["--z-mode", "hold"], ["--pin-holds"]):
            r = subprocess.run([sys.executable, "-m", "ffcomp", str(src), "-o", f"{td}/o.gcode", "--json",
                                "--no-progress", *args], capture_output=True, text=True, check=True)
            d = json.loads(r.stdout)
            print(f"| {' '.join(args)} | {d['rms_before_um']:.1f} | {d['rms_after_um']:.2f} | {d['max_after_um']:.1f} "
                  f"| {d['self_check_max_um']:.1f} | {d['self_check_catch_up_max_um']:.1f} |")


def gcode_on_simulator() -> None:
    sys.path.insert(0, str(ROOT / "tests"))
    from test_compensate_sim import SQUARE_100

    from ffcomp.pipeline.output_check import check_gcode_output
    from ffcomp.profile import default_profile

    with tempfile.TemporaryDirectory() as td:
        src = Path(td) / "square100.gcode"
        src.write_text("\n".join(SQUARE_100) + "\n")
        chk = check_gcode_output(default_profile(), src, Path(td) / "out.gcode")
    print("\nG-code output re-planned and simulated (square 100 mm out, 10,000 mm/s^2), um:\n")
    lim = _limit_on(default_profile(), SQUARE_100)
    print("| commands | lag-aligned RMS | contour RMS | x the physical limit |\n|---|---|---|---|")
    for name, r in (("none", chk.none), ("exact compensated", chk.exact), ("G-code output", chk.gcode),
                    ("physical limit (ffcomp.compensate.limit)", lim)):
        print(f"| {name} | {r.lag.rms_norm_um:.2f} | {r.contour.rms_norm_um:.2f} | "
              f"{r.lag.rms_norm_um / lim.lag.rms_norm_um:.2f}x |")
    print(f"\nthe G-code output keeps {chk.kept('lag') * 100:.1f} % of the exact commands' lag-aligned reduction "
          f"and {chk.kept('contour') * 100:.1f} % of the contour reduction; re-planned timing drift "
          f"{chk.drift_s * 1e3:.3f} ms over {chk.summary.print_time_s:.2f} s")


def _limit_on(profile, lines):
    """The physical-limit commands of a G-code source on the simulator (the same timeline as
    :func:`ffcomp.pipeline.output_check.check_gcode_output`: rest before, for pre-actuation)."""
    import numpy as np

    from ffcomp.compensate.inverse import InverseConfig
    from ffcomp.compensate.limit import limit_commands
    from ffcomp.gcode.sampler import concat_blocks, sample_gcode
    from ffcomp.model.lpv import LpvModel
    from ffcomp.pipeline.compensate_flow import inv_pre_samples
    from ffcomp.sim.metrics import evaluate
    from ffcomp.sim.plant import DeltaPlant

    with tempfile.TemporaryDirectory() as td:
        src = Path(td) / "src.gcode"
        src.write_text("\n".join(lines) + "\n")
        ref = concat_blocks(sample_gcode(str(src), profile, overlap=0))
    dt = ref.t_s[1] - ref.t_s[0]
    n_pre = inv_pre_samples(InverseConfig(), dt)
    X = np.vstack([np.repeat(ref.xyz_m[:1], n_pre, 0), ref.xyz_m])
    q = np.vstack([np.repeat(ref.q_m[:1], n_pre, 0), ref.q_m])
    t = np.arange(len(q)) * dt
    c = limit_commands(LpvModel.from_profile(profile), q, X, dt).q_cmd
    return evaluate(t, X, DeltaPlant.from_profile(profile).simulate(t, c, hold="linear").xyz_m[0])


def quantisation_floor() -> None:
    from ffcomp.profile import default_profile
    from ffcomp.sim.bench import bench_cases, load_providers, run_case
    from ffcomp.sim.plant import DeltaPlant

    p = default_profile()
    load_providers()
    plant = DeltaPlant.from_profile(p)
    print(f"\nStep quantisation at {p.limits.steps_per_mm:g} steps/mm, the simulator's model (samples rounded to "
          "steps, linear in between: pessimistic, see the staircase table below) (lag-aligned RMS / contour RMS, "
          "um):\n")
    print("| case | none | zvd-centre | lpv | lpv, exact commands |\n|---|---|---|---|---|")
    for traj in bench_cases(p, quick=True):
        rq = run_case(plant, p, traj, ["none", "zvd-centre", "lpv"], quantize=True).reports
        re = run_case(plant, p, traj, ["lpv"], quantize=False).reports[0]
        cells = [f"{r.lag.rms_norm_um:.1f} / {r.contour.rms_norm_um:.1f}" for r in rq]
        print(f"| {traj.name} | " + " | ".join(cells) + f" | {re.lag.rms_norm_um:.2f} / {re.contour.rms_norm_um:.2f} |")


def quantisation_aware() -> None:
    """The real step staircase at 80 steps/mm on the nonlinear plant: the firmware's steps of the
    exact commands, against the quantisation-aware stream (:mod:`ffcomp.compensate.quantise`), on
    both profiles (the second compensated with other_delta.toml and simulated with its truth)."""

    from ffcomp.compensate.inverse import invert
    from ffcomp.compensate.limit import limit_commands
    from ffcomp.compensate.quantise import shape_quantisation
    from ffcomp.model.lpv import LpvModel
    from ffcomp.profile import default_profile, load_profile
    from ffcomp.sim.bench import bench_cases
    from ffcomp.sim.metrics import evaluate
    from ffcomp.sim.moves import pattern
    from ffcomp.sim.plant import DeltaPlant
    from ffcomp.sim.staircase import simulate_steps

    pairs = [("default", default_profile(), None),
             ("other_delta on its truth", load_profile(ROOT / "samples/profiles/other_delta.toml"),
              load_profile(ROOT / "samples/profiles/other_delta_truth.toml"))]
    for title, p, truth in pairs:
        spm = p.limits.steps_per_mm
        model = LpvModel.from_profile(p)
        plant = DeltaPlant.from_profile(truth or p)
        g = p.geometry_si()
        cases = bench_cases(p, quick=True) + [pattern("polygon", g, (0.0, 0.0, 30.0)),
                                              pattern("polygon", g, (60.0, 40.0, 30.0)),
                                              pattern("zmove", g, (-50.0, -60.0, 30.0))]
        print(f"\nStep staircase at {spm:g} steps/mm, {title} (lag-aligned RMS, um; steps timed exactly, "
              "simulated at 10 kHz):\n")
        print("| case | none, steps | limit, no steps | lpv, no steps | lpv, firmware steps | lpv, 1 kHz shaped "
              "points | lpv, shaped step stream | shaped / firmware |\n|---|---|---|---|---|---|---|---|")
        for tr in cases:
            c = invert(model, tr.q_m, tr.xyz_m, float(tr.t_s[1] - tr.t_s[0])).q_cmd
            lim = limit_commands(model, tr.q_m, tr.xyz_m, float(tr.t_s[1] - tr.t_s[0])).q_cmd
            runs = [simulate_steps(plant, tr.t_s, tr.q_m, spm),
                    plant.simulate(tr.t_s, lim, hold="linear").xyz_m[0],
                    plant.simulate(tr.t_s, c, hold="linear").xyz_m[0],
                    simulate_steps(plant, tr.t_s, c, spm),
                    simulate_steps(plant, tr.t_s, shape_quantisation(c, spm, 2), spm),
                    simulate_steps(plant, tr.t_s, c, spm, shaped=True)]
            e = [evaluate(tr.t_s, tr.xyz_m, x).lag.rms_norm_um for x in runs]
            print(f"| {tr.name} | " + " | ".join(f"{v:.2f}" for v in e) + f" | {e[5] / e[3]:.2f}x |")



if __name__ == "__main__":
    options_table()
    gcode_on_simulator()
    quantisation_floor()
    quantisation_aware()
