"""Compensation building blocks against independent computations."""

import control
import numpy as np

from ffcomp.compensate.bspline import UniformBasis
from ffcomp.compensate.fbs import FbsConfig, fbs_solve
from ffcomp.compensate.kernels import drive_kernel, mech_arrays, mech_kernels, modal_foh
from ffcomp.compensate.ltv import simulate_lti, simulate_piecewise
from ffcomp.compensate.stream import FbsStream
from ffcomp.model import state_space_arrays


def test_bspline_partition_of_unity_and_derivative():
    b = UniformBasis(5, 5, 1e-3)
    v = b.evaluate(np.ones(60), 300)
    np.testing.assert_allclose(v[40:250], 1.0, atol=1e-12)
    c = np.sin(np.arange(80) * 0.3)
    y = b.evaluate(c, 400)
    yd = b.evaluate(c, 400, deriv=1)
    fd = np.gradient(y, 1e-3)
    np.testing.assert_allclose(yd[50:350], fd[50:350], atol=2e-3 * np.max(np.abs(yd)))


def test_foh_discretisation_is_exact_for_piecewise_linear_input():
    A = np.array([[0.0, 1.0], [-(2 * np.pi * 60) ** 2, -36.0]])
    B = np.array([[0.0], [(2 * np.pi * 60) ** 2]])
    dt = 1e-3
    u = np.sin(np.arange(200) * 0.37) + np.arange(200) * 0.01
    x, _ = simulate_lti(A, B, u[:, None], dt)
    tf = np.arange(0, 199 * dt + 1e-12, dt / 200)
    r = control.forced_response(control.ss(A, B, np.eye(2), 0), T=tf, U=np.interp(tf, np.arange(200) * dt, u))
    np.testing.assert_allclose(x[:199, 0], r.outputs[0, ::200][:199], atol=2e-6 * np.max(np.abs(x)))


def test_piecewise_equals_per_sample_stepping(model):
    N = 600
    t = np.arange(N) * 1e-3
    X = np.column_stack([0.08 * np.cos(3 * t), 0.08 * np.sin(3 * t), 0.03 + 0 * t])
    A, B, _, _ = state_space_arrays(model.matrices(X))
    w = np.column_stack([np.sin(40 * t), np.cos(70 * t), t]) * 1e-3
    Phi, G1, G2 = modal_foh(A, B, 1e-3).dense()
    x = np.zeros(A.shape[1])
    ref = []
    for k in range(N):
        ref.append(x.copy())
        wn = w[k + 1] if k + 1 < N else w[k]
        x = Phi[k] @ x + G1[k] @ w[k] + G2[k] @ (wn - w[k])
    xs, _ = simulate_piecewise(A, B, w, 1e-3, 1)
    np.testing.assert_allclose(xs, np.array(ref), atol=1e-12)


def test_mech_kernel_matches_fine_simulation(model):
    mats = model.matrices(np.array([[0.05, -0.08, 0.03]]))
    b = UniformBasis()
    K = mech_kernels(mats, b, 150, substeps=16)[0]  # (3 inputs, L, 3 outputs)
    A, Bm = mech_arrays(mats)
    from scipy.interpolate import BSpline

    el = BSpline.basis_element(np.arange(7.0), extrapolate=False)
    tf = np.arange(0, 0.15, 1e-5)
    u = np.nan_to_num(el(tf / b.h_s))
    ud = np.nan_to_num(el.derivative()(tf / b.h_s)) / b.h_s
    W = np.zeros((len(tf), 6))
    W[:, 1], W[:, 4] = u, ud  # the basis on drive B
    r = control.forced_response(control.ss(A[0], Bm[0], np.eye(6)[:3], 0), T=tf, U=W.T)
    ref = r.outputs[:, ::100].T[:150]
    assert np.max(np.abs(K[1] - ref)) < 2e-3 * np.max(np.abs(ref))


def test_drive_kernel_is_the_drive_response(profile):
    d = profile.dynamics
    b = UniformBasis()
    k = drive_kernel(d.d0[0], d.d1[0], d.d2[0], 0.0, 0.0, b, 400)
    tf = np.arange(0, 0.4, 1e-5)
    shape = np.concatenate([b.shape(0), np.zeros(400 - b.support)])
    u = np.interp(tf, np.arange(400) * 1e-3, shape)  # first-order hold of the sampled basis
    r = control.forced_response(control.tf([d.d1[0], d.d0[0]], [1, d.d2[0], d.d0[0]]), T=tf, U=u)
    np.testing.assert_allclose(k, r.outputs[::100][:400], atol=1e-4)


def test_fbs_stream_equals_windowed_solve(profile):
    d = profile.dynamics
    b = UniformBasis()
    k = drive_kernel(d.d0[0], d.d1[0], d.d2[0], 0.0, 0.0, b, 300)[None, :, None]
    N = 1500
    t = np.arange(N) * 1e-3
    tgt = (np.sin(2 * np.pi * 3 * t) * (t > 0.1))[:, None]
    coef, _ = fbs_solve(tgt, lambda j0, j1: np.broadcast_to(k[None], (j1 - j0,) + k.shape), 300,
                        FbsConfig(b, 600, 300, 1e-7, lti=True))
    v = b.evaluate(coef[:, 0], N)
    s = FbsStream(k, b, 600, 300, 1e-7)
    o = np.concatenate([s.feed(tgt[a:a + 250]) for a in range(0, N, 250)] + [s.finish()])
    assert len(o) == N
    np.testing.assert_allclose(o[:900, 0], v[:900], atol=1e-6)
    # the drive inverse really inverts: filtering the command reproduces the target
    s3 = FbsStream(k, b, 600, 300, 1e-9, channels=3)
    T3 = np.column_stack([tgt[:, 0], 0.5 * tgt[:, 0], -tgt[:, 0]])
    o3 = np.concatenate([s3.feed(T3[a:a + 400]) for a in range(0, N, 400)] + [s3.finish()])
    np.testing.assert_allclose(o3[:900, 1], 0.5 * o3[:900, 0], atol=1e-9)
