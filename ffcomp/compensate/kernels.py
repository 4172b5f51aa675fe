"""Filtered B-spline kernels: the response of the model to one basis function.

The model is split where it is exact to split it: ``q = G_m(X) u`` and ``u = F(s) q_d``, with
``F`` each tower's drive filter (pose independent, SISO, lightly damped, non-minimum phase) and
``G_m(X)`` the coupled carriage/effector mechanics (pose dependent, 3x3, minimum phase, well
damped).  The mechanics state is ``(q, q_dot)`` and its input ``(u, u_dot)``:

    M q'' + C q' + K q = B_c u' + B_k u.

Discretisation is exact for inputs linear between samples (first-order hold), done in modal
coordinates so that thousands of poses discretise in one batched eigen-decomposition.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import cont2discrete, lfilter, lfilter_zi, ss2tf

from ..model.lpv import PoseMatrices, drive_filter_ss, mech_arrays
from .bspline import UniformBasis

__all__ = [
    "mech_arrays",
    "ModalFoh",
    "modal_foh",
    "mech_kernels",
    "drive_kernel",
    "mech_tail_samples",
    "drive_tail_samples",
    "ltv_mech_response",
    "DriveFilter",
]


def _phi1(z):
    small = np.abs(z) < 1e-6
    zs = np.where(small, 1.0, z)
    return np.where(small, 1 + z / 2 + z**2 / 6, np.expm1(zs) / zs)


def _phi2(z):
    small = np.abs(z) < 1e-4
    zs = np.where(small, 1.0, z)
    return np.where(small, 0.5 + z / 6 + z**2 / 24, (np.expm1(zs) - zs) / zs**2)


@dataclass(frozen=True)
class ModalFoh:
    """Batched first-order-hold discretisation in modal coordinates.

    ``z_{k+1} = e^{lam dt} z_k + g1 w_k + g2 (w_{k+1} - w_k)``, ``x = V z`` (real part).
    Shapes: lam (P, n), V (P, n, n), g1/g2 (P, n, m).
    """

    lam: np.ndarray
    V: np.ndarray
    g1: np.ndarray
    g2: np.ndarray
    dt_s: float

    def dense(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Real ``(Phi, G1, G2)`` with ``x_{k+1} = Phi x_k + G1 w_k + G2 (w_{k+1} - w_k)``."""
        e = np.exp(self.lam * self.dt_s)
        Phi = (self.V * e[:, None, :]) @ np.linalg.inv(self.V)
        return Phi.real, (self.V @ self.g1).real, (self.V @ self.g2).real


def modal_foh(A: np.ndarray, B: np.ndarray, dt_s: float) -> ModalFoh:
    """Diagonalise ``A`` (P, n, n) and discretise ``(A, B)`` with a first-order hold."""
    lam, V = np.linalg.eig(A)
    Vinv = np.linalg.inv(V)
    Bm = Vinv @ B
    z = lam * dt_s
    g1 = dt_s * _phi1(z)[:, :, None] * Bm
    g2 = dt_s * _phi2(z)[:, :, None] * Bm
    return ModalFoh(lam, V, g1, g2, dt_s)


def mech_tail_samples(mats: PoseMatrices, dt_s: float, tol: float = 1e-4) -> int:
    """Samples until the slowest mechanical mode decays to ``tol`` of its start (at these poses)."""
    A, _ = mech_arrays(mats)
    sigma = -np.linalg.eigvals(A).real
    return int(np.ceil(np.log(1.0 / tol) / max(float(sigma.min()), 1e-3) / dt_s))


def mech_kernels(mats: PoseMatrices, basis: UniformBasis, length: int, substeps: int = 8) -> np.ndarray:
    """Response of the frozen-pose mechanics to one basis function on each tower's drive.

    The drive position ``u`` is the continuous spline itself, so the recursion runs ``substeps``
    times per sample over the basis' support (first-order hold on the fine grid: error
    ``O((dt/substeps)^2)``); after the support the response is each mode's free decay, exact.

    Returns
    -------
    K : ndarray, shape (P, 3, length, 3)
        ``K[p, i, t, o]``: carriage ``o`` at sample ``t`` after basis start, basis on drive ``i``,
        model frozen at pose ``p``.
    """
    A, B = mech_arrays(mats)
    ns = int(substeps)
    dtf = basis.dt_s / ns
    foh = modal_foh(A, B, dtf)
    P, n = foh.lam.shape
    n_sup = min(basis.support, length - 1)
    fine = UniformBasis(basis.degree, basis.m * ns, dtf)
    nf = n_sup * ns
    b = np.zeros(nf + 1)
    bd = np.zeros(nf + 1)
    sup_f = min(fine.support, nf + 1)
    b[:sup_f] = fine.shape(0)[:sup_f]
    bd[:sup_f] = fine.shape(1)[:sup_f]
    gb1, gd1 = foh.g1[:, :, :3], foh.g1[:, :, 3:]  # (P, n, 3): input on drive i
    gb2, gd2 = foh.g2[:, :, :3], foh.g2[:, :, 3:]
    ee = np.exp(foh.lam * dtf)[:, :, None]
    z = np.zeros((P, n, 3), complex)
    Zs = np.empty((n_sup + 1, P, n, 3), complex)
    for k in range(nf + 1):
        if k % ns == 0:
            Zs[k // ns] = z
        if k < nf:
            z = ee * z + gb1 * b[k] + gd1 * bd[k] + gb2 * (b[k + 1] - b[k]) + gd2 * (bd[k + 1] - bd[k])
    Vq = foh.V[:, :3, :]  # (P, 3, n): q = first three states
    K = np.empty((P, 3, length, 3))
    K[:, :, : n_sup + 1] = np.einsum("pon,kpni->piko", Vq, Zs).real
    if length > n_sup + 1:
        # after the support the input is zero: free decay of each mode from z(n_sup)
        steps = np.arange(1, length - n_sup)
        decay = np.exp(foh.lam[:, :, None] * basis.dt_s * steps[None, None, :])  # (P, n, T)
        W = (Vq[:, :, :, None] * Zs[n_sup][:, None, :, :]).transpose(0, 1, 3, 2).reshape(P, 9, n)
        K[:, :, n_sup + 1:] = (W @ decay).reshape(P, 3, 3, -1).transpose(0, 2, 3, 1).real
    return K


def drive_kernel(d0: float, d1: float, d2: float, lag_s: float, delay_s: float, basis: UniformBasis,
                 length: int, pade_order: int = 6) -> np.ndarray:
    """Response ``u`` of one tower's drive filter to one basis function (length samples)."""
    a, bvec, c = drive_filter_ss(d0, d1, d2, lag_s, delay_s, pade_order)
    foh = modal_foh(a[None], bvec[None, :, None], basis.dt_s)
    w = np.zeros(length + 1)
    sup = min(basis.support, length + 1)
    w[:sup] = basis.shape(0)[:sup]
    e = np.exp(foh.lam[0] * basis.dt_s)
    g1, g2 = foh.g1[0, :, 0], foh.g2[0, :, 0]
    cV = c @ foh.V[0]
    z = np.zeros(len(e), complex)
    out = np.empty(length)
    for k in range(length):
        out[k] = (cV @ z).real
        z = e * z + g1 * w[k] + g2 * (w[k + 1] - w[k])
    return out


def drive_tail_samples(d0: float, d2: float, lag_s: float, dt_s: float, tol: float = 1e-4) -> int:
    """Samples until the drive's slowest pole decays to ``tol``."""
    sigma = d2 / 2.0
    if lag_s > 0:
        sigma = min(sigma, 1.0 / lag_s)
    return int(np.ceil(np.log(1.0 / tol) / sigma / dt_s))


def ltv_mech_response(mats_per_sample: PoseMatrices, w: np.ndarray, dt_s: float) -> np.ndarray:
    """Exact LTV response of the mechanics to inputs ``w`` (N, 6, J) with the model at every sample.

    ``mats_per_sample`` holds the pose matrices at each of the N samples.  Returns q (N, 3, J).
    Used for the exact-LPV filtered basis and for checking the frozen-pose approximation.
    """
    A, B = mech_arrays(mats_per_sample)
    Phi, G1, G2 = modal_foh(A, B, dt_s).dense()
    N, _, J = w.shape
    x = np.zeros((6, J))
    out = np.empty((N, 3, J))
    for k in range(N):
        out[k] = x[:3]
        if k + 1 < N:
            x = Phi[k] @ x + G1[k] @ w[k] + G2[k] @ (w[k + 1] - w[k])
    return out


class DriveFilter:
    """A tower's drive filter applied to a stream of samples (first-order hold, state carried).

    ``derivative=True`` gives the drive velocity ``s F(s)`` instead of the drive position.
    """

    def __init__(self, d0, d1, d2, lag_s, delay_s, dt_s, derivative: bool = False):
        a, b, c = drive_filter_ss(d0, d1, d2, lag_s, delay_s)
        d = np.zeros((1, 1))
        if derivative:  # y' = c x' = c a x + c b u
            c, d = c @ a, np.array([[c @ b]])
        ad, bd, cd, dd, _ = cont2discrete((a, b[:, None], c[None, :], d), dt_s, method="foh")
        num, den = ss2tf(ad, bd, cd, dd)
        self.b, self.a = num[0], den
        self.zi = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        if self.zi is None:
            self.zi = lfilter_zi(self.b, self.a) * 0.0  # at rest at 0 (inputs are relative)
        if len(x) == 0:  # scipy's lfilter returns an uninitialised state for empty input
            return np.zeros(0)
        y, self.zi = lfilter(self.b, self.a, x, zi=self.zi)
        return y
