"""The LPV model: batched FRF vs state space vs the paper's Eq. 20 written out literally."""

import control
import numpy as np
import pytest

from ffcomp.model import LpvModel, frequency_response, state_space
from ffcomp.model.modes import modes, workspace_grid
from ffcomp.model.submodels import g_fq, g_qd, n_fq

POSES_MM = np.array([[0, 0, 30], [-110, 0, 30], [0, -110, 30], [110, 0, 30], [40, 70, 150], [-60, -90, 5]])
F = np.geomspace(1, 400, 300)


def eq20_literal(profile, geom_model, xyz_m, freq_hz):
    """G(s) = [I - G_Fq N_Fq J^T J]^-1 G_qd, from the paper's sub-model transfer functions."""
    d = profile.dynamics
    out = np.empty((3, 3, len(freq_hz)), complex)
    J = geom_model.matrices(xyz_m[None]).J[0]
    JtJ = J.T @ J
    for f_i, f in enumerate(freq_hz):
        s = 2j * np.pi * f
        Gqd = np.diag([g_qd(s, d.m[i], d.c[i], d.b[i], d.k[i], d.d0[i], d.d1[i], d.d2[i]) for i in range(3)])
        Gfq = np.diag([g_fq(s, d.m[i], d.c[i], d.b[i], d.k[i]) for i in range(3)])
        N = n_fq(s, d.m_nt, d.b_nt)
        out[:, :, f_i] = np.linalg.solve(np.eye(3) - Gfq * N @ JtJ, Gqd)
    return out


def test_batched_frf_equals_eq20_literal(profile, model):
    H = frequency_response(model, POSES_MM * 1e-3, F, frame="joint")
    for p, x in enumerate(POSES_MM * 1e-3):
        ref = eq20_literal(profile, model, x, F)
        assert np.max(np.abs(H[p] - ref)) / np.max(np.abs(ref)) < 1e-12


@pytest.mark.parametrize("frame", ["joint", "task", "task_to_joint", "joint_to_task"])
def test_batched_frf_equals_state_space(model, frame):
    H = frequency_response(model, POSES_MM * 1e-3, F, frame=frame)
    for p, x in enumerate(POSES_MM * 1e-3):
        sys = state_space(model, x, frame=frame)
        assert isinstance(sys, control.StateSpace)
        Hs = sys(2j * np.pi * F)
        rel = np.max(np.abs(Hs - H[p])) / np.max(np.abs(H[p]))
        assert rel < 1e-9, (frame, p, rel)


def test_task_response_is_J_G_Jinv(model):
    x = POSES_MM[1] * 1e-3
    Gj = frequency_response(model, x[None], F, frame="joint")[0]
    Gt = frequency_response(model, x[None], F, frame="task")[0]
    J = model.matrices(x).J[0]
    ref = np.einsum("ij,jkf,kl->ilf", J, Gj, np.linalg.inv(J))
    np.testing.assert_allclose(Gt, ref, rtol=1e-12, atol=1e-14)


def test_centre_vertical_mode_is_loaded_carriage(profile, model):
    """At the bed centre z -> z and z -> qA equal G'_qd of Eqs. 29-32."""
    d = profile.dynamics
    m_p = d.m[0] + d.m_nt / 3
    b_p = d.c[0] + d.b[0] + d.b_nt / 3
    s = 2j * np.pi * F
    Gp = (d.c[0] * s + d.k[0]) / (m_p * s**2 + b_p * s + d.k[0]) * (d.d1[0] * s + d.d0[0]) / (
        s**2 + d.d2[0] * s + d.d0[0])
    x = np.array([[0, 0, 0.03]])
    np.testing.assert_allclose(frequency_response(model, x, F, frame="task")[0, 2, 2], Gp, rtol=1e-10)
    np.testing.assert_allclose(frequency_response(model, x, F, frame="task_to_joint")[0, 0, 2], Gp, rtol=1e-10)
    ms = modes(model, x)
    assert ms.freq_hz[0, 2] == pytest.approx(np.sqrt(d.k[0] / m_p) / (2 * np.pi), rel=1e-9)
    assert ms.damping[0, 2] == pytest.approx(b_p / (2 * np.sqrt(d.k[0] * m_p)), rel=1e-9)


def test_dc_gain_is_one_everywhere(model):
    H = frequency_response(model, POSES_MM * 1e-3, [1e-6], frame="task")
    np.testing.assert_allclose(H[..., 0], np.broadcast_to(np.eye(3), (len(POSES_MM), 3, 3)), atol=1e-6)


def test_modes_coincide_at_centre_and_split_away(model):
    ms = modes(model, POSES_MM[:4] * 1e-3)
    f = ms.freq_hz
    assert abs(f[0, 0] - f[0, 1]) < 1e-6  # x and y modes coincide at the centre
    assert set(ms.direction[0, :2]) == {"x", "y"} and ms.direction[0, 2] == "z"
    for p in (1, 2, 3):
        assert f[p, 1] - f[p, 0] > 5.0  # > 5 Hz split away from the centre (Figs. 7-8)


def test_modes_match_undamped_generalised_eigenproblem(model):
    from scipy.linalg import eigh

    mats = model.matrices(POSES_MM * 1e-3)
    ms = modes(mats)
    for p in range(len(POSES_MM)):
        w2 = eigh(mats.K[p], mats.M[p], eigvals_only=True)
        # damped natural frequency |lambda| differs from the undamped one only through damping coupling
        np.testing.assert_allclose(np.sort(ms.freq_hz[p]), np.sqrt(w2) / (2 * np.pi), rtol=0.02)


def test_discrete_state_space_matches_continuous_step(model):
    x = np.array([0.05, -0.04, 0.05])
    sysc = state_space(model, x, frame="task")
    dt = 1e-3
    sysd = state_space(model, x, frame="task", dt_s=dt)
    assert sysd.dt == dt
    t = np.arange(0, 1.0, dt)
    _, yc = control.step_response(sysc, T=t, input=0)
    _, yd = control.step_response(sysd, T=t, input=0)
    np.testing.assert_allclose(yd, yc, atol=1e-9)
    assert yd[0, 0, -1] == pytest.approx(1.0, abs=1e-4)  # x settles on a unit x step
    assert abs(yd[1, 0, -1]) < 1e-4 and abs(yd[2, 0, -1]) < 1e-4


def test_unequal_carriages_break_symmetry(profile):
    from dataclasses import replace

    dyn = replace(profile.dynamics, k=(9.44e4, 8.0e4, 9.44e4))
    m = LpvModel.from_profile(replace(profile, dynamics=dyn))
    ms = modes(m, np.array([[0, 0, 0.03]]))
    assert ms.freq_hz[0, 1] - ms.freq_hz[0, 0] > 0.5  # centre modes no longer coincide


def test_workspace_grid_inside_print_radius(geom):
    g = workspace_grid(geom, 0.03, 0.01)
    assert np.all(np.hypot(g[:, 0], g[:, 1]) <= geom.print_radius_m + 1e-12)
    assert len(g) > 500


def test_unreachable_pose_raises(model):
    from ffcomp.errors import KinematicsError

    with pytest.raises(KinematicsError):
        model.matrices([0.2, 0, 0.03])
