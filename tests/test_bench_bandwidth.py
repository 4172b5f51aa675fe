"""The two-pass prototype of benchmarks/bench_bandwidth.py (a coarse inverse, then each stage's
residual fitted on a 1 ms spline) must track a fast square closer than the coarse inverse alone."""

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("bench_bandwidth", ROOT / "benchmarks" / "bench_bandwidth.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_parse_setting():
    assert _bench().parse_setting("d5k4") == (5, 4)
    assert _bench().parse_setting("d3k1") == (3, 1)


def test_second_pass_tracks_closer_than_the_coarse_inverse():
    from ffcomp.compensate.inverse import InverseConfig, invert
    from ffcomp.model.lpv import LpvModel
    from ffcomp.profile import default_profile
    from ffcomp.sim import metrics
    from ffcomp.sim.bench import HOLD
    from ffcomp.sim.moves import pattern
    from ffcomp.sim.plant import DeltaPlant

    prof = default_profile()
    tr = pattern("square", prof.geometry_si(), (0.0, 0.0, 30.0), accel_mm_s2=10000.0,
                 rate_hz=float(prof.limits.sample_rate_hz), loops=1)
    model = LpvModel.from_profile(prof)
    dt = float(np.median(np.diff(tr.t_s)))
    coarse = invert(model, tr.q_m, tr.xyz_m, dt, InverseConfig()).q_cmd
    two = _bench().refined(model, tr.q_m, tr.xyz_m, dt, (5, 4), (3, 1))
    res = DeltaPlant.from_profile(prof).simulate(tr.t_s, np.stack([coarse, two]), hold=HOLD)
    e = [metrics.evaluate(tr.t_s, tr.xyz_m, res.xyz_m[k]).lag.rms_norm_um for k in range(2)]
    # measured: 0.39 um -> 0.14 um (the physical limit: 0.11 um; with the same spline twice: 0.39 um)
    assert e[1] < 0.5 * e[0], e
