"""The nonlinear simulator: equilibrium, linearisation = LPV model, accuracy, batching, quantisation."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ffcomp.errors import KinematicsError
from ffcomp.kinematics import inverse
from ffcomp.model.lpv import state_space_arrays
from ffcomp.sim import metrics
from ffcomp.sim.moves import pattern, plan_polyline
from ffcomp.sim.plant import GRAVITY_M_S2, DeltaPlant, quantize


@pytest.fixture(scope="module")
def plant(model):
    return DeltaPlant(model)


def _num_jacobians(plant, x0, r0, h=1e-7):
    """Central differences of the right-hand side (springs anchored at ``r0``)."""
    n = x0.shape[0]
    A = np.zeros((n, n))
    B = np.zeros((n, 3))
    for i in range(n):
        e = np.zeros(n)
        e[i] = h
        A[:, i] = (plant.rhs(x0 + e, r0, r0) - plant.rhs(x0 - e, r0, r0)) / (2 * h)
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        B[:, i] = (plant.rhs(x0, r0 + e, r0) - plant.rhs(x0, r0 - e, r0)) / (2 * h)
    return A, B


@pytest.mark.parametrize("pose_mm", [(0, 0, 30), (80, -50, 30), (-100, 0, 60), (0, 110, 10)])
def test_linearised_rhs_equals_state_space(plant, pose_mm):
    X0 = np.asarray(pose_mm, float) * 1e-3
    r0 = inverse(plant.geometry, X0)
    x0 = plant.equilibrium(r0)
    assert np.abs(plant.rhs(x0, r0)).max() < 1e-8  # at rest
    A, B = _num_jacobians(plant, x0, r0)
    As, Bs, _, _ = state_space_arrays(plant.model.matrices(X0[None]))
    assert np.abs(A - As[0]).max() <= 1e-6 * np.abs(As[0]).max()
    assert np.abs(B - Bs[0]).max() <= 1e-6 * np.abs(Bs[0]).max()


class _HeavierCarriageC:
    """Stand-in effect: carriage C 30 % heavier and its belt 20 % stiffer (acts on PoseMatrices)."""

    def apply(self, mats, model):
        M, K, Bk = mats.M.copy(), mats.K.copy(), mats.B_k.copy()
        M[:, 2, 2] += 0.3 * model.carriage.m[2]
        K[:, 2, 2] *= 1.2
        Bk[:, 2] *= 1.2
        return mats.replace(M=M, K=K, B_k=Bk)


def test_effects_are_honoured(model):
    plant = DeltaPlant(model.with_effects([_HeavierCarriageC()]))
    X0 = np.array([0.05, 0.03, 0.04])
    r0 = inverse(plant.geometry, X0)
    A, _ = _num_jacobians(plant, plant.equilibrium(r0), r0)
    As, _, _, _ = state_space_arrays(plant.model.matrices(X0[None]))
    A_plain, _, _, _ = state_space_arrays(model.matrices(X0[None]))
    assert np.abs(A - As[0]).max() <= 1e-6 * np.abs(As[0]).max()
    assert np.abs(A - A_plain[0]).max() > 1e-2 * np.abs(As[0]).max()


def test_rest_stays_at_rest(plant):
    t = np.arange(200) * 1e-3
    q = np.repeat(inverse(plant.geometry, np.array([0.06, -0.04, 0.05]))[None], t.size, axis=0)
    res = plant.simulate(t, q)
    assert res.q_m.shape == (1, t.size, 3)
    assert np.abs(res.q_m[0] - q).max() < 1e-12
    assert np.abs(res.xyz_m[0] - [0.06, -0.04, 0.05]).max() < 1e-12


def test_gravity_sag_at_centre(model):
    plant = DeltaPlant(model, gravity=True)
    t = np.arange(100) * 1e-3
    q = np.repeat(inverse(plant.geometry, np.array([0.0, 0.0, 0.03]))[None], t.size, axis=0)
    res = plant.simulate(t, q)
    cp = model.carriage
    sag = (cp.m[0] + model.m_nt / 3) * GRAVITY_M_S2 / cp.k[0]  # each carriage carries a third at the centre
    dz = res.xyz_m[0, :, 2] - 0.03
    assert np.allclose(dz, -sag, rtol=1e-3)
    assert np.ptp(dz) < 1e-12  # started at the sagged equilibrium


def test_slow_move_sub_micron(plant):
    t, xyz = plan_polyline([[0.05, 0.02, 0.03], [0.053, 0.022, 0.031]], 0.005, 0.01, pad_s=(0.05, 0.1))
    res = plant.simulate(t, inverse(plant.geometry, xyz))
    rep = metrics.evaluate(t, xyz, res.xyz_m[0])
    assert rep.lag.max_norm_um < 1.0
    assert rep.contour.max_norm_um < 1.0
    assert 1.5e-3 < rep.lag_s < 4e-3  # drive + mechanics (~2.6 ms) + half a held sample


def test_fast_path_matches_stage_exact_reference(plant, profile):
    tr = pattern("square", plant.geometry, (100.0, 0.0, 30.0), loops=1)
    sl = slice(40, 240)  # through the first corner at 10 000 mm/s^2
    t, q = tr.t_s[sl] - tr.t_s[sl][0], tr.q_m[sl]
    ref = plant.simulate(t, q, pose_every=0)
    fast = plant.simulate(t, q)
    coarse = plant.simulate(t, q, substeps=5, pose_every=20)
    assert np.abs(fast.xyz_m - ref.xyz_m).max() < 1e-8  # 10 nm
    assert np.abs(coarse.xyz_m - ref.xyz_m).max() < 1e-7
    # something actually happened: the carriages moved and vibrated
    assert np.abs(ref.xyz_m[0, -1] - ref.xyz_m[0, 0]).max() > 1e-3


def test_batch_equals_single_runs(plant):
    tr = pattern("zigzag", plant.geometry, (0.0, 50.0, 20.0), lines=2)
    q2 = tr.q_m + np.array([1e-4, -2e-4, 0.0])
    both = plant.simulate(tr.t_s, np.stack([tr.q_m, q2]))
    one = plant.simulate(tr.t_s, q2)
    assert both.n_runs == 2
    assert np.abs(both.q_m[1] - one.q_m[0]).max() < 1e-13


def test_linear_hold_and_validation(plant):
    t = np.arange(50) * 1e-3
    q = np.repeat(inverse(plant.geometry, np.zeros(3) + [0, 0, 0.03])[None], 50, axis=0)
    q[10:, 0] += 1e-4
    zoh = plant.simulate(t, q)
    lin = plant.simulate(t, q, hold="linear")
    assert not np.allclose(zoh.q_m, lin.q_m)
    with pytest.raises(ValueError):
        plant.simulate(t, q, hold="cubic")
    with pytest.raises(ValueError):
        plant.simulate(t[:10], q)
    bad = q.copy()
    bad[5] = [2.0, 0.0, 0.0]
    with pytest.raises(KinematicsError):
        plant.simulate(t, bad)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.lists(st.floats(-0.5, 0.5, allow_nan=False), min_size=1, max_size=30),
       st.sampled_from([80.0, 100.0, 400.0, 1600.0]))
def test_quantize_within_half_a_step(values, spm):
    q = np.asarray(values)
    qq = quantize(q, spm)
    step = 1e-3 / spm
    assert np.all(np.abs(qq - q) <= 0.5 * step * (1 + 1e-9) + 1e-15)
    assert np.allclose(qq / step, np.round(qq / step), atol=1e-6)


def test_quantized_simulation_commands(plant, profile):
    tr = pattern("square", plant.geometry, (0.0, 0.0, 30.0), loops=1, side_m=0.02)
    spm = profile.limits.steps_per_mm
    res = plant.simulate(tr.t_s, tr.q_m, steps_per_mm=spm)
    assert np.abs(res.q_cmd_m[0] - tr.q_m).max() <= 0.5e-3 / spm + 1e-15
    assert np.abs(res.q_cmd_m[0] - tr.q_m).max() > 0.3e-3 / spm  # it did quantise


def test_carriage_only(plant):
    c = plant.carriage_only()
    assert c.model.m_nt == 0.0 and c.model.b_nt == 0.0
    assert plant.model.m_nt > 0  # the original is untouched
    assert replace(plant.model, m_nt=0.0, b_nt=0.0) == c.model


class _SlowDrive:
    """Stand-in effect: a 0.4 ms lag and a 0.8 ms delay on every drive (Pade in the simulator)."""

    def apply(self, mats, model):
        return mats.replace(lag_s=np.full(3, 4e-4), delay_s=np.full(3, 8e-4))


def test_fast_path_matches_full_state_rk4_with_lag_and_delay(model):
    plant = DeltaPlant(model.with_effects([_SlowDrive()]))
    assert plant.n_drive_states == 3 * (2 + 1 + 6)
    t, xyz = plan_polyline([[0.02, -0.01, 0.04], [0.021, -0.01, 0.0401]], 0.1, 5.0, pad_s=(0.005, 0.01))
    q = inverse(plant.geometry, xyz)
    fast = plant.simulate(t, q)
    # reference: classical RK4 on the full state (drive states included), commands held, 20 kHz
    sub, dt = 20, float(t[1] - t[0]) / 20
    x = plant.equilibrium(q[0])
    nf = plant.n_drive_states
    ref = [x[nf:nf + 3]]
    for k in range(len(t) - 1):
        for _ in range(sub):
            k1 = plant.rhs(x, q[k])
            k2 = plant.rhs(x + 0.5 * dt * k1, q[k])
            k3 = plant.rhs(x + 0.5 * dt * k2, q[k])
            k4 = plant.rhs(x + dt * k3, q[k])
            x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        ref.append(x[nf:nf + 3])
    ref = np.asarray(ref)
    assert np.abs(fast.q_m[0] - q).max() > 1e-5  # dynamics visible (a 1 mm move)
    assert np.abs(fast.q_m[0] - ref).max() < 2e-9


@pytest.mark.parametrize("name,values", [
    ("frame_coupling", {"coupling": 0.1}),
    ("belt_span", {}),
    ("tower_scale", {"k_scale_A": 1.2, "m_scale_B": 1.3}),
    ("drive_delay", {"delay_ms": 1.0, "lag_ms": 0.5}),
    ("forearm_inertia", {"scale": 1.0}),
])
def test_effects_library_linearises_to_the_model(model, name, values):
    from ffcomp.model.effects import EFFECTS, _load_library

    _load_library()
    if name not in EFFECTS:
        pytest.skip(f"effect {name} not in the library")
    try:
        eff = EFFECTS[name](**values)
    except (TypeError, ValueError) as e:
        pytest.skip(f"effect {name} parameters changed: {e}")
    plant = DeltaPlant(model.with_effects([eff]))
    X0 = np.array([0.07, -0.03, 0.05])
    r0 = inverse(plant.geometry, X0)
    x0 = plant.equilibrium(r0)
    assert np.abs(plant.rhs(x0, r0, r0)).max() < 1e-8
    A, B = _num_jacobians(plant, x0, r0)
    As, Bs, _, _ = state_space_arrays(plant.model.matrices(X0[None]))
    assert np.abs(A - As[0]).max() <= 1e-6 * np.abs(As[0]).max()
    assert np.abs(B - Bs[0]).max() <= 1e-6 * np.abs(Bs[0]).max()
    # a run at rest stays at rest, also with springs that are not belts (anchored at the start)
    t = np.arange(60) * 1e-3
    res = plant.simulate(t, np.repeat(r0[None], t.size, axis=0))
    assert np.abs(res.q_m[0] - r0).max() < 1e-11
