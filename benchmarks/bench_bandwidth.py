"""Benchmark: the inverse's basis bandwidth against the physical limit and against the G-code
pipeline's time (issue 13, item 2).

Bench part: every case of ``bench_limit.py`` on both profiles, one row per spline setting
(``dDkK``: degree D, a knot every K samples of 1 kHz; the default is ``d5k4``) plus the physical
limit; prints the per-case ratio to the limit and each row's inverse CPU time per second of motion.
A setting ``dDkK+dEkL`` is a batch-only prototype of a two-pass inverse (:func:`refined`): the
``dDkK`` inverse, then each stage's residual fitted again on the finer ``dEkL`` spline.  It exists
only here (not in :mod:`ffcomp.compensate.stream`), to measure that idea.

Pipeline part (``--pipeline``): compensates ``samples/gcode/cube_prusa.gcode`` with each setting on
both profiles (self-check and prediction on, as the CLI does) and prints the wall time, the output
lines, the predicted RMS and the self-check figures.  A setting that runs longer than
``--timeout`` seconds is stopped and reported as such.

Run: ``python benchmarks/bench_bandwidth.py [--quick] [--pipeline] [--settings d5k4,d5k2,d3k1]``.
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
SETTINGS = ["d5k4", "d5k3", "d5k2", "d3k2", "d3k1"]
PROFILES = [("default profile", None, None),
            ("other_delta.toml on other_delta_truth.toml", "samples/profiles/other_delta.toml",
             "samples/profiles/other_delta_truth.toml")]


def parse_setting(name: str) -> tuple[int, int]:
    """``"d5k4"`` -> (degree 5, 4 samples per knot interval)."""
    d, k = name[1:].split("k")
    return int(d), int(k)


def refined(model, q_ref_m, xyz_ref_m, dt_s: float, coarse: tuple[int, int], fine: tuple[int, int]):
    """Two-pass prototype (batch only): the default ``lpv`` inverse on the ``coarse`` spline, then the
    mechanics stage's residual (centre-model units) and each tower's drive residual fitted again on
    the ``fine`` spline and added.  Returns the commands (N, 3), m."""
    import numpy as np

    from ffcomp.compensate import inverse as inv
    from ffcomp.compensate.bspline import UniformBasis
    from ffcomp.compensate.fbs import FbsConfig, fbs_solve
    from ffcomp.compensate.kernels import (
        DriveFilter,
        drive_kernel,
        drive_tail_samples,
        mech_kernels,
        mech_tail_samples,
    )

    cfg = inv.InverseConfig(degree=coarse[0], knot_samples=coarse[1])
    N = len(q_ref_m)
    cb, fb = UniformBasis(*coarse, dt_s), UniformBasis(*fine, dt_s)
    m = cb.m
    n_pre, n_post = inv._round_to(int(round(cfg.pre_s / dt_s)), m), int(round(cfg.post_s / dt_s))
    pad = lambda a: np.concatenate([np.repeat(a[:1], n_pre, 0), a, np.repeat(a[-1:], n_post, 0)])  # noqa: E731
    q, X = pad(np.asarray(q_ref_m, float)), pad(np.asarray(xyz_ref_m, float))
    Np = len(q)
    qd, qdd = inv._derivatives(q, dt_s)
    win = inv._round_to(int(round(cfg.window_s / dt_s)), m)
    adv = inv._round_to(int(round(cfg.advance_s / dt_s)), m)
    coef_u, pred_minus_target = inv._mech_stage_fast(model, q, qd, qdd, X, X, cb, win, adv, cfg)
    x0 = X[:1].copy()
    x0[:, :2] = 0.0
    mats0 = model.matrices(x0, check=False)
    L = fb.support + mech_tail_samples(mats0, dt_s, cfg.kernel_tol)
    k0 = mech_kernels(mats0, fb, L, cfg.substeps)[0]
    cf, _ = fbs_solve(-pred_minus_target, lambda j0, j1: np.broadcast_to(k0[None], (j1 - j0,) + k0.shape), L,
                      FbsConfig(fb, win, adv, cfg.reg, lti=True, row_stride=cfg.row_stride))
    u = q + cb.evaluate(coef_u, Np) + fb.evaluate(cf, Np)
    dwin = inv._round_to(int(round(cfg.drive_window_s / dt_s)), m)
    dadv = inv._round_to(int(round(cfg.drive_advance_s / dt_s)), m)
    q_cmd = np.empty_like(q)
    for i in range(3):
        p = (mats0.d0[i], mats0.d1[i], mats0.d2[i], mats0.lag_s[i], mats0.delay_s[i])
        target = (u[:, i] - (DriveFilter(*p, dt_s)(q[:, i] - q[0, i]) + q[0, i]))[:, None]
        eps = np.zeros(Np)
        for b in (cb, fb):
            Lb = b.support + drive_tail_samples(p[0], p[2], p[3], dt_s)
            k = drive_kernel(*p, b, Lb)
            def kfn(j0, j1, k=k):
                return np.broadcast_to(k[None, None, :, None], (j1 - j0, 1, len(k), 1))

            c, pred = fbs_solve(target, kfn, Lb, FbsConfig(b, dwin, dadv, cfg.reg, lti=True))
            eps += b.evaluate(c[:, 0], Np)
            target = target - pred
        q_cmd[:, i] = q[:, i] + eps
    return q_cmd[n_pre:n_pre + N]


def register(settings) -> None:
    """Add one bench row per setting (lpv inverse with that spline, or the two-pass prototype)."""
    import numpy as np

    from ffcomp.compensate.inverse import InverseConfig
    from ffcomp.compensate.variants import _row
    from ffcomp.model.lpv import LpvModel
    from ffcomp.sim.bench import load_providers, register_variant

    load_providers()
    for s in settings:
        if "+" in s:
            coarse, fine = (parse_setting(x) for x in s.split("+"))

            def fn(profile, t_s, xyz, q, coarse=coarse, fine=fine):
                return refined(LpvModel.from_profile(profile), q, xyz, float(np.median(np.diff(t_s))), coarse, fine)

            register_variant(s, fn)
        else:
            d, k = parse_setting(s)
            register_variant(s, _row("lpv", InverseConfig(degree=d, knot_samples=k)))


def bench(settings, quick: bool) -> None:
    from ffcomp.profile import default_profile, load_profile
    from ffcomp.sim.bench import VARIANTS, markdown_table, run_bench

    register(settings)
    for title, prof_path, plant_path in PROFILES:
        prof = default_profile() if prof_path is None else load_profile(ROOT / prof_path)
        plant = None if plant_path is None else load_profile(ROOT / plant_path)
        res = run_bench(prof, quick=quick, variants=list(settings) + ["limit"], plant_profile=plant,
                        include_gcode=not quick)
        print(f"## {title}\n\n{markdown_table(res)}")
        parts = []
        for s in settings:
            t0, T = time.process_time(), 0.0
            for c in res.cases:
                tr = c.trajectory
                VARIANTS[s](prof, tr.t_s, tr.xyz_m, tr.q_m)
                T += tr.duration_s
            parts.append(f"{s} {(time.process_time() - t0) / T:.3f} s")
        print("Inverse CPU time per second of motion (all cases): " + ", ".join(parts) + "\n", flush=True)


PIPE = """
import json, sys, time
from ffcomp.compensate.inverse import InverseConfig
from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file
from ffcomp.profile import default_profile, load_profile
src, out, prof, d, k = sys.argv[1:6]
p = default_profile() if prof == "-" else load_profile(prof)
t0 = time.perf_counter()
s = compensate_file(src, out, p, CompensateOptions(inverse=InverseConfig(degree=int(d), knot_samples=int(k))))
w = time.perf_counter() - t0
print(json.dumps({"wall_s": w, "lines": sum(1 for _ in open(out)), "rms_after_um": s.rms_after_um,
                  "self_check_max_um": s.self_check_max_um, "self_check_rms_um": s.self_check_rms_um,
                  "peak_command_accel_mm_s2": s.peak_command_accel_mm_s2}))
"""


def pipeline(settings, timeout_s: float) -> None:
    src = str(ROOT / "samples/gcode/cube_prusa.gcode")
    print("| profile | setting | wall (s) | lines out | predicted RMS (um) | self-check max / RMS (um) | "
          "peak command accel (m/s^2) |\n|---|---|---:|---:|---:|---:|---:|")
    for title, prof_path, _ in PROFILES:
        for s in [s for s in settings if "+" not in s]:
            d, k = parse_setting(s)
            args = [sys.executable, "-c", PIPE, src, f"/tmp/bench_bandwidth_{s}.gcode",
                    "-" if prof_path is None else str(ROOT / prof_path), str(d), str(k)]
            try:
                r = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s, check=True)
            except subprocess.TimeoutExpired:
                print(f"| {title} | {s} | > {timeout_s:.0f} (stopped) | - | - | - | - |", flush=True)
                continue
            j = json.loads(r.stdout.strip().splitlines()[-1])
            print(f"| {title} | {s} | {j['wall_s']:.2f} | {j['lines']} | {j['rms_after_um']:.2f} | "
                  f"{j['self_check_max_um']:.1f} / {j['self_check_rms_um']:.2f} | "
                  f"{j['peak_command_accel_mm_s2'] * 1e-3:.0f} |", flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="three short cases only")
    ap.add_argument("--pipeline", action="store_true", help="time the G-code pipeline on cube_prusa instead")
    ap.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated dDkK settings")
    ap.add_argument("--timeout", type=float, default=300.0, help="pipeline: seconds before a run is stopped")
    a = ap.parse_args(argv)
    settings = [s.strip() for s in a.settings.split(",") if s.strip()]
    if a.pipeline:
        pipeline(settings, a.timeout)
    else:
        bench(settings, a.quick)


if __name__ == "__main__":
    main()
