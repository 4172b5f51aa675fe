"""Step-timed 1 kHz points (ffcomp.compensate.step_timing) against the firmware's own staircase,
judged on the nonlinear simulator with the step times held on a fine grid (an independent
representation: the timer scores candidates on the linear model)."""

import numpy as np

from ffcomp.compensate.inverse import invert
from ffcomp.compensate.step_timing import StepTimer
from ffcomp.model.lpv import LpvModel
from ffcomp.sim.metrics import evaluate
from ffcomp.sim.moves import pattern
from ffcomp.sim.plant import DeltaPlant
from ffcomp.sim.staircase import simulate_steps, staircase


def test_staircase_lattice_through_a_given_origin():
    q = np.column_stack([np.linspace(0.0, 1e-4, 11)] * 3) + np.array([3e-6, 0.0, -3e-6])
    org = np.array([3e-6, 1e-6, 0.0])
    _, st = staircase(q, 1e-3, 80.0, 5, org)
    k = (st - org) / 12.5e-6
    np.testing.assert_allclose(k, np.round(k), atol=1e-9)


def test_runs_through_the_plant_together_equal_runs_alone(profile):
    """``simulate_steps`` with (R, N, 3) commands integrates the runs in one pass: each run's path
    is bit for bit the path of that run alone."""
    tr = pattern("square", profile.geometry_si(), (0.0, 0.0, 30.0))
    t, Q = tr.t_s[:200], tr.q_m[:200]
    plant = DeltaPlant.from_profile(profile)
    both = simulate_steps(plant, t, np.stack([Q, Q + 3e-6]), 80.0, upsample=5)
    assert both.shape == (2, len(t), 3)
    for y, q in zip(both, (Q, Q + 3e-6)):
        assert np.array_equal(y, simulate_steps(plant, t, q, 80.0, upsample=5))


def test_step_timed_points_ring_less_than_the_firmware_staircase(profile):
    """The timer moves points by at most a step and carries its state across calls; on a fast
    square the staircase of its points leaves well under the firmware staircase's error
    (bench_step_timing.py: 0.39x)."""
    spm = profile.limits.steps_per_mm
    model = LpvModel.from_profile(profile)
    tr = pattern("square", profile.geometry_si(), (0.0, 0.0, 30.0))
    t, X, Q = tr.t_s, tr.xyz_m, tr.q_m
    n = len(t)
    c = invert(model, Q, X, float(t[1] - t[0])).q_cmd
    timer = StepTimer(model, float(t[1] - t[0]), spm, np.zeros(3))
    h = n // 2
    (q1, m1), (q2, m2) = timer(c[:h], X[:h]), timer(c[h:], X[h:])
    q = np.vstack([q1, q2])
    assert np.max(np.abs(q - c)) <= 12.5e-6 * (1 + 1e-9) and q[0].tolist() == c[0].tolist()
    assert 0.1 < np.mean(np.r_[m1, m2]) < 0.95
    plant = DeltaPlant.from_profile(profile)
    # (both staircases through the plant in one pass: the integrator's cost is per step, not per run)
    ef, et = (evaluate(t, X, y).lag.rms_norm_um for y in simulate_steps(plant, t, np.stack([c, q]), spm, upsample=25))
    assert et < 0.6 * ef, (et, ef)
