"""Fast simulation of a linear system whose matrices change along the path (piecewise frozen).

The path is cut into segments of ``seg`` samples; within a segment the system is LTI at the
segment's pose and is solved exactly in modal coordinates for inputs linear between samples
(first-order hold), vectorised over all segments at once.  Only the hand-over of the state from
one segment to the next is a loop (one 6x6 or 12x12 product per segment), so a second of print
at 1 kHz with 5-sample segments costs ~200 small products instead of 1,000 Python steps.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .kernels import modal_foh

__all__ = ["simulate_piecewise"]


def simulate_piecewise(A: np.ndarray, B: np.ndarray, w: np.ndarray, dt_s: float, seg: int,
                       x0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Simulate ``x' = A_s x + B_s w`` with ``A_s, B_s`` frozen on each segment of ``seg`` samples.

    Parameters
    ----------
    A : ndarray, shape (S, n, n)
        One matrix per segment (``S = ceil(N / seg)``).
    B : ndarray, shape (S, n, m)
    w : ndarray, shape (N, m) or (N, m, R)
        Inputs at the samples, linear in between; a third axis runs R simulations through the same
        (once diagonalised) matrices.
    x0 : ndarray, shape (n,) or (n, R), optional
        Initial state (zero by default).

    Returns
    -------
    x : ndarray, shape (N, n)
        States at the samples.
    x_end : ndarray, shape (n,)
        State one sample after the last (to continue the simulation).
    """
    one = w.ndim == 2  # (N, m); several runs through the same matrices: (N, m, R)
    w = w[:, :, None] if one else w
    N, m_in, R = w.shape
    S = -(-N // seg)
    if A.shape[0] != S:
        raise ValueError(f"need {S} segment matrices for {N} samples in segments of {seg}, got {A.shape[0]}")
    n = A.shape[1]
    foh = modal_foh(A, B, dt_s)
    Vinv = np.linalg.inv(foh.V)
    # one mode of each complex-conjugate pair, doubled (see _upper_modes)
    lam, Vfull, g1, g2 = foh.lam, foh.V, foh.g1, foh.g2
    scale = 1.0
    sel = _upper_modes(lam)
    if sel is not None:
        take = lambda a: np.take_along_axis(a, sel[:, :, None], axis=1)  # noqa: E731
        lam = np.take_along_axis(lam, sel, axis=1)
        Vfull = np.take_along_axis(Vfull, sel[:, None, :], axis=2)
        Vinv, g1, g2 = take(Vinv), take(g1), take(g2)
        scale = 2.0
    n_m = lam.shape[1]
    # the samples run along the last axes (segment, mode or channel, sample, run): few, wide
    # products instead of one tiny product per sample.  Inputs per segment incl. the first sample
    # of the next one (held at the end of the data), k and k + 1
    wp = np.concatenate([w, np.repeat(w[-1:], S * seg + 1 - N, 0)])

    def per_segment(a):  # (S * seg, m, R) -> (S, m, seg * R)
        return a.reshape(S, seg, m_in, R).transpose(0, 2, 1, 3).reshape(S, m_in, seg * R)

    # modal forcing v_k = g1 w_k + g2 (w_{k+1} - w_k), k = 0..seg-1: real products with the real
    # and imaginary parts stacked
    GA = np.concatenate([(g1 - g2).real, (g1 - g2).imag], axis=1)  # (S, 2 n_m, m)
    GB = np.concatenate([g2.real, g2.imag], axis=1)
    vri = np.matmul(GA, per_segment(wp[:-1]))
    vri += np.matmul(GB, per_segment(wp[1:]))
    vri = vri.reshape(S, 2 * n_m, seg, R)
    v = vri[:, :n_m] + 1j * vri[:, n_m:]  # (S, n_m, seg, R)
    e = np.exp(lam * dt_s)  # (S, n_m)
    # powers e^k, k = 0..seg, by repeated products
    powers = np.empty((S, n_m, seg + 1), complex)
    powers[:, :, 0] = 1.0
    powers[:, :, 1:] = e[:, :, None]
    np.cumprod(powers, axis=2, out=powers)
    # zero-state response z_k = sum_{j<k} e^(k-1-j) v_j = e^(k-1) sum_{j<k} v_j e^(-j), k = 0..seg:
    # one running sum (a mode decays by at most exp(-sigma seg dt) over a segment: within range)
    zs = np.empty((S, n_m, seg + 1, R), complex)
    zs[:, :, 0] = 0.0
    np.cumsum(v / powers[:, :, :seg, None], axis=2, out=zs[:, :, 1:])
    zs[:, :, 1:] *= powers[:, :, :seg, None]
    # hand the physical state from segment to segment
    xs = np.empty((S, n, R))
    if x0 is None:
        x = np.zeros((n, R))
    else:
        x = np.asarray(x0, float).reshape(n, -1) * np.ones((1, R))
    Ve = Vfull * scale
    p_end, z_end = powers[:, :, seg, None], zs[:, :, seg]
    for s_ in range(S):
        xs[s_] = x
        x = (Ve[s_] @ (p_end[s_] * (Vinv[s_] @ x) + z_end[s_])).real
    z0 = np.einsum("snm,smr->snr", Vinv, xs)  # modal start states
    Z = powers[..., None] * z0[:, :, None] + zs  # (S, n_m, seg+1, R)
    # the real part of V Z, as one real product: [Re V, -Im V] [Re Z; Im Z]
    Vri = np.concatenate([Ve.real, -Ve.imag], axis=2)  # (S, n, 2 n_m)
    Zri = np.concatenate([Z[:, :, :seg].real, Z[:, :, :seg].imag], axis=1).reshape(S, 2 * n_m, seg * R)
    X = np.matmul(Vri, Zri).reshape(S, n, seg, R).transpose(0, 2, 1, 3).reshape(S * seg, n, R)
    k_end = N - (S - 1) * seg  # sample N inside the last segment (input held after the data)
    x_end = (Ve[-1] @ Z[-1, :, k_end]).real
    if one:
        return X[:N, :, 0], x_end[:, 0]
    return X[:N], x_end


def _upper_modes(lam: np.ndarray) -> np.ndarray | None:
    """Indices (P, n/2) of the modes with ``Im > 0`` when every mode of every system (rows of
    ``lam``, (P, n)) is one of a complex-conjugate pair; None otherwise.

    A real system driven by real inputs has conjugate states in conjugate modes, so one mode of
    each pair, doubled in the real part of the output, carries the whole response at half the work.
    """
    n = lam.shape[1]
    up = lam.imag > 0
    if n % 2 or not np.all(up.sum(axis=1) == n // 2) or np.any(lam.imag == 0):
        return None
    return np.argsort(~up, axis=1, kind="stable")[:, : n // 2]


@lru_cache(maxsize=32)
def _mode_powers(lam_dt: complex, n: int) -> np.ndarray:
    """``exp(lam_dt k)`` for k = 1 .. n - 1 (read-only): a streamed system meets the same modes and
    chunk lengths over and over."""
    out = np.exp(lam_dt * np.arange(1, n))
    out.flags.writeable = False
    return out


def simulate_lti(A: np.ndarray, B: np.ndarray, w: np.ndarray, dt_s: float,
                 z0: np.ndarray | None = None, foh=None) -> tuple[np.ndarray, np.ndarray]:
    """LTI ``x' = A x + B w`` with first-order-hold inputs, by per-mode recursive filters.

    Each mode is a complex first-order recursion run by :func:`scipy.signal.lfilter`, so a long
    signal costs a few vectorised passes.  ``z0`` / the second return value are the modal states
    (to continue the simulation over the next chunk; the chunk must then begin with the sample
    that ended the previous one).

    Returns
    -------
    x : ndarray, shape (N, n)
    z_end : ndarray, shape (n,), complex
        Modal state at the last sample.
    """
    from scipy.signal import lfilter

    if foh is None:  # callers that stream one system pass its discretisation back in
        foh = modal_foh(A[None], B[None], dt_s)
    lam, V = foh.lam[0], foh.V[0]
    g1, g2 = foh.g1[0], foh.g2[0]
    n_all = len(lam)
    z_init = np.zeros(n_all, complex) if z0 is None else np.asarray(z0, complex)
    # one mode of each complex-conjugate pair, doubled (see _upper_modes); the state handed back
    # holds every mode, the conjugates' rebuilt from their partners
    sel = _upper_modes(lam[None])
    paired = sel is not None
    if paired:
        up = sel[0]
        lo = np.nonzero(lam.imag < 0)[0]
        partner = up[np.argmin(np.abs(lam[lo][:, None] - np.conj(lam[up])[None, :]), axis=1)]
        lam, V, g1, g2, z_init = lam[up], V[:, up], g1[up], g2[up], z_init[up]
    e = np.exp(lam * dt_s)
    wn = np.concatenate([w[1:], w[-1:]])
    v = w @ (g1 - g2).T + wn @ g2.T  # (N, n): forcing of step k -> k+1
    n = len(lam)
    Z = np.empty((len(w), n), complex)
    # z_k = e^k z0 + sum_{j<k} e^{k-1-j} v_j
    for i in range(n):
        forced = lfilter([1.0], [1.0, -e[i]], v[:, i])  # y_k = sum_{j<=k} e^{k-j} v_j
        Z[1:, i] = forced[:-1]
        if z_init[i] != 0:
            Z[1:, i] += z_init[i] * _mode_powers(lam[i] * dt_s, len(w))
        Z[0, i] = z_init[i]
    if not paired:
        return (Z @ V.T).real, Z[-1]
    x = 2.0 * (Z @ V.T).real
    z_end = np.empty(n_all, complex)  # every mode's state (the conjugates' too), to continue with
    z_end[up] = Z[-1]
    z_end[lo] = np.conj(z_end[partner])
    return x, z_end
