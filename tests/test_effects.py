"""The effects library: physics of each effect, composition, profile round trip, state space."""

from dataclasses import replace

import numpy as np
import pytest

from ffcomp.errors import ProfileError
from ffcomp.kinematics import inverse
from ffcomp.model import LpvModel, frequency_response, state_space
from ffcomp.model.effects import EFFECTS, build_effects, load_library
from ffcomp.model.effects.belt_span import stiffness_ratio
from ffcomp.model.effects.forearm_inertia import mass_correction
from ffcomp.model.effects.frame_coupling import LAPLACIAN

NAMES = ("belt_span", "tower_scale", "forearm_inertia", "frame_coupling", "drive_delay")
load_library()  # the registry fills as the effect modules are imported: not only by tests run before
POSES = np.array([[0, 0, 30], [100, 0, 30], [-70, 60, 130], [0, -100, 200]]) * 1e-3


def test_library_has_the_five_effects_documented():
    lib = load_library()
    for name in NAMES:
        cls = lib[name]
        doc = __import__(cls.__module__, fromlist=["x"]).__doc__
        assert "Physics" in doc and "Signature in the FRFs" in doc, name
        assert cls.summary and cls.fit_params() and set(cls.fit_params()) <= set(cls.params)
        for k, p in cls.params.items():
            assert p.lo <= p.default <= p.hi and p.doc, (name, k)
            lo, hi = p.fit_range
            assert np.isfinite(lo) and np.isfinite(hi) and p.lo <= lo < hi <= p.hi, (name, k)


@pytest.mark.parametrize("name", NAMES)
def test_default_effect_keeps_shapes_and_symmetry(model, name):
    mats = model.with_effects([EFFECTS[name]()]).matrices(POSES)
    base = model.matrices(POSES)
    for f in ("M", "C", "K", "B_c", "B_k"):
        assert getattr(mats, f).shape == getattr(base, f).shape
    np.testing.assert_allclose(mats.M, np.swapaxes(mats.M, 1, 2), atol=1e-15)
    np.testing.assert_allclose(mats.K, np.swapaxes(mats.K, 1, 2), atol=1e-9)
    assert np.all(np.linalg.eigvalsh(mats.M) > 0) and np.all(np.linalg.eigvalsh(mats.K) > 0)


def test_belt_span_two_springs_in_parallel(model):
    eff = EFFECTS["belt_span"](l1_ref_mm=300.0, loop_mm=1500.0, z_ref_mm=30.0)
    q_ref = inverse(model.geometry, np.array([0, 0, 0.03]))
    mats = model.with_effects([eff]).matrices(POSES)
    EA = 1.0  # any: the ratio is geometric
    l1 = 0.3 + (mats.q_m - q_ref)
    k_expect = (EA / l1 + EA / (1.5 - l1)) / (EA / 0.3 + EA / 1.2) * model.carriage.k
    np.testing.assert_allclose(mats.B_k, k_expect, rtol=1e-12)
    np.testing.assert_allclose(np.diagonal(mats.K, axis1=1, axis2=2), k_expect, rtol=1e-12)
    np.testing.assert_allclose(mats.B_k[0], model.carriage.k, rtol=1e-12)  # unchanged at the identification pose
    # belt damping follows the stiffness (tau = c / k constant)
    np.testing.assert_allclose(mats.B_c / mats.B_k, np.broadcast_to(model.carriage.c / model.carriage.k, (4, 3)),
                               rtol=1e-12)
    # stiffness is lowest mid-loop
    q = np.linspace(-0.5, 0.5, 101)
    r = stiffness_ratio(q, 0.0, 0.3, 1.5)
    assert abs(q[np.argmin(r)] - 0.45) < 0.011
    with pytest.raises(ValueError, match="shorter than loop_mm"):
        EFFECTS["belt_span"](l1_ref_mm=1500.0, loop_mm=1400.0)


@pytest.mark.parametrize("spec", [{"name": "belt_span", "l1_ref_mm": 250.0}, {"name": "tower_scale", "k_scale_B": 0.7,
                                  "m_scale_C": 1.3, "c_scale_A": 2.0}])
def test_belt_force_keeps_static_gain_one(model, spec):
    m = model.with_effects(build_effects([spec]))
    H = frequency_response(m, POSES, [1e-3], frame="task")[..., 0]
    np.testing.assert_allclose(H, np.broadcast_to(np.eye(3), H.shape), atol=1e-4)


def test_tower_scale_moves_one_carriage_mode(model):
    from ffcomp.measure.predict import detached

    eff = EFFECTS["tower_scale"](k_scale_B=0.64, m_scale_B=1.0)
    d0, d1 = detached(model), detached(model.with_effects([eff]))
    mats0, mats1 = d0.matrices(POSES[:1]), d1.matrices(POSES[:1])
    w0 = np.sqrt(np.diagonal(mats0.K, axis1=1, axis2=2) / np.diagonal(mats0.M, axis1=1, axis2=2))[0]
    w1 = np.sqrt(np.diagonal(mats1.K, axis1=1, axis2=2) / np.diagonal(mats1.M, axis1=1, axis2=2))[0]
    np.testing.assert_allclose(w1 / w0, [1.0, 0.8, 1.0], rtol=1e-12)
    assert "tower B" in eff.explain(model) and "low" in eff.explain(model)


def test_forearm_rod_kinetic_energy_derivation(model, rng):
    """Integrate the kinetic energy of uniform rods exactly and compare with lumped + correction."""
    m_f = model.m_f
    J = model.matrices(POSES).J
    dM = mass_correction(J, m_f)
    t = np.linspace(0.0, 1.0, 2001)
    for p in range(len(POSES)):
        qd = rng.standard_normal(3)
        vb = J[p] @ qd
        T_rod = T_lumped = 0.0
        for i in range(3):
            va = np.array([0.0, 0.0, qd[i]])
            v = va[None] + t[:, None] * (vb - va)[None]
            T_rod += 0.5 * m_f * np.trapezoid(np.sum(v**2, 1), t)  # the pair: total mass m_f along the rods
            T_lumped += 0.25 * m_f * (va @ va + vb @ vb)  # m_f/2 at each end
        assert T_rod - T_lumped == pytest.approx(0.5 * qd @ dM[p] @ qd, rel=1e-6, abs=1e-12)
    # pure vertical motion at the centre: no correction
    qd = np.ones(3)
    assert qd @ dM[0] @ qd == pytest.approx(0.0, abs=1e-12)
    eff = EFFECTS["forearm_inertia"](scale=0.5)
    mats = model.with_effects([eff]).matrices(POSES)
    np.testing.assert_allclose(mats.M - model.matrices(POSES).M, 0.5 * dM, atol=1e-15)
    # effector detached (the carriage sweep; also the simulator's carriage_only, which keeps m_f): no rods
    bare = replace(model, m_nt=0.0, b_nt=0.0)
    np.testing.assert_array_equal(bare.with_effects([eff]).matrices(POSES).M, bare.matrices(POSES).M)


def test_frame_coupling_common_mode_untouched(model):
    eff = EFFECTS["frame_coupling"](coupling=0.1)
    m = model.with_effects([eff])
    mats = m.matrices(POSES)
    np.testing.assert_allclose(mats.K - model.matrices(POSES).K, 0.1 * model.carriage.k.mean() * LAPLACIAN[None]
                               * np.ones((len(POSES), 1, 1)))
    H = frequency_response(m, POSES[:1], [0.01], frame="task")[0, :, :, 0]
    assert abs(H[2, 2]) == pytest.approx(1.0, abs=1e-5)  # vertical (all carriages together)
    assert abs(H[0, 0]) == pytest.approx(1 / 1.3, rel=1e-4)  # lateral static gain k / (k + 3 k_c)


def test_drive_delay_is_exact_in_frequency_response(model):
    f = np.geomspace(5, 300, 40)
    eff = EFFECTS["drive_delay"](delay_ms=1.5, lag_ms=0.4)
    H0 = frequency_response(model, POSES[:2], f, frame="joint")
    H1 = frequency_response(model.with_effects([eff]), POSES[:2], f, frame="joint")
    s = 2j * np.pi * f
    np.testing.assert_allclose(H1, H0 * np.exp(-1.5e-3 * s) / (1 + 0.4e-3 * s), rtol=1e-10)
    assert "1.500 ms" in eff.explain(model)


def test_drive_lag_in_state_space(model):
    m = model.with_effects([EFFECTS["drive_delay"](lag_ms=0.4)])
    f = np.geomspace(5, 300, 30)
    ss = state_space(m, POSES[:1], frame="task")
    np.testing.assert_allclose(np.asarray(ss.frequency_response(2 * np.pi * f).complex),
                               frequency_response(m, POSES[:1], f, frame="task")[0], rtol=1e-7, atol=1e-9)


def test_drive_delay_in_state_space_matches_pade(model):
    m = model.with_effects([EFFECTS["drive_delay"](delay_ms=1.5)])
    f = np.geomspace(5, 150, 20)
    ss = state_space(m, POSES[:1], frame="task", pade_order=6)
    np.testing.assert_allclose(np.asarray(ss.frequency_response(2 * np.pi * f).complex),
                               frequency_response(m, POSES[:1], f, frame="task", delay="pade:6")[0], rtol=1e-6,
                               atol=1e-9)


def test_effects_compose_and_commute(model):
    a = {"name": "belt_span", "l1_ref_mm": 300.0}
    b = {"name": "tower_scale", "k_scale_A": 1.2, "k_scale_C": 0.9}
    m1 = model.with_effects(build_effects([a, b])).matrices(POSES)
    m2 = model.with_effects(build_effects([b, a])).matrices(POSES)
    for f in ("M", "C", "K", "B_c", "B_k"):
        np.testing.assert_allclose(getattr(m1, f), getattr(m2, f), rtol=1e-12)


def test_state_space_honours_stiffness_effects(model):
    effs = build_effects([{"name": "frame_coupling", "coupling": 0.2}, {"name": "tower_scale", "k_scale_B": 0.8},
                          {"name": "forearm_inertia"}])
    m = model.with_effects(effs)
    f = np.geomspace(5, 300, 30)
    ss = state_space(m, POSES[1:2], frame="task")
    np.testing.assert_allclose(np.asarray(ss.frequency_response(2 * np.pi * f).complex),
                               frequency_response(m, POSES[1:2], f, frame="task")[0], rtol=1e-8, atol=1e-12)


def test_profile_round_trip_with_effects(tmp_path, profile):
    from ffcomp.profile import load_profile, save_profile

    prof = profile.with_(effects=({"name": "drive_delay", "delay_ms": 0.7}, {"name": "tower_scale", "k_scale_C": 0.9}))
    save_profile(prof, tmp_path / "p.toml")
    back = load_profile(tmp_path / "p.toml")
    assert [e["name"] for e in back.effects] == ["drive_delay", "tower_scale"]
    m = LpvModel.from_profile(back)
    assert [e.name for e in m.effects] == ["drive_delay", "tower_scale"]
    assert m.matrices(POSES[:1]).delay_s[0] == pytest.approx(0.7e-3)
    text = (tmp_path / "p.toml").read_text().replace("k_scale_C = 0.9", "k_scale_C = 9.0")
    (tmp_path / "q.toml").write_text(text)
    with pytest.raises(ProfileError, match="k_scale_C"):
        load_profile(tmp_path / "q.toml")


def test_effects_cli_lists_library(capsys):
    from cli_util import run_json

    cat = run_json(capsys, "effects")
    names = {e["name"] for e in cat}
    assert set(NAMES) <= names
    belt = next(e for e in cat if e["name"] == "belt_span")
    assert any(p["name"] == "l1_ref_mm" and p["fitted"] for p in belt["params"])
