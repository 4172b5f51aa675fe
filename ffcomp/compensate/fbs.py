"""Windowed filtered-B-spline (FBS) least squares with limited preview.

The command is a uniform B-spline; basis ``j`` starts at sample ``j m``.  A window of ``W`` samples
starting at ``w0`` is solved for every basis that starts inside it; the bases starting in the first
``A`` samples are then committed (fixed forever) and their filtered responses, which ring on past
the window, are added to a prediction buffer that the next windows subtract from their targets.
So every window sees exactly what earlier windows did, the seams are continuous by construction,
and the cost grows linearly with the length of the print.

The kernel provider gives the filtered response of each new basis function (the response of the
model, frozen at the basis' pose or exact along the path, to that one basis).  Regularisation
pulls every coefficient towards a prior (the target itself at the basis' centre), which keeps
the solution bounded where the data do not determine it (the last bases of a window) and where
the model has a right-half-plane zero.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve

from ..errors import SolverError
from .bspline import UniformBasis

__all__ = ["FbsConfig", "fbs_solve"]

#: kernel_fn(j0, j1) -> K of shape (j1 - j0, n_in, L, n_out) for bases j0..j1-1
KernelFn = Callable[[int, int], np.ndarray]


@dataclass(frozen=True)
class FbsConfig:
    """Window settings (samples).  ``advance`` and ``window`` must be multiples of ``basis.m``.

    ``row_stride`` evaluates the residual on every ``row_stride``-th sample (the command still
    acts on every sample); ``chunk`` is the number of samples per block of the banded Gram build.
    """

    basis: UniformBasis
    window: int = 400
    advance: int = 200
    reg: float = 1e-6
    lti: bool = False  # kernels identical for every basis: factorise once
    row_stride: int = 1
    chunk: int = 60

    def __post_init__(self):
        m = self.basis.m
        if self.window % m or self.advance % m or not (0 < self.advance < self.window):
            raise ValueError(f"window ({self.window}) and advance ({self.advance}) must be multiples of the "
                             f"knot spacing ({m} samples) with 0 < advance < window")


def _normal_equations(K, starts, rows, resid, row_w, cfg):
    """Banded build of ``Phi^T Phi`` and ``Phi^T r`` chunk by chunk.

    K : (nJ, n_in, L, n_out) kernels; starts : (nJ,) start sample of each basis (window-relative);
    resid : (rows, n_out); row_w : (rows, n_out, n_out) or None.
    """
    nJ, n_in, L, n_out = K.shape
    n = nJ * n_in
    G = np.zeros((n, n))
    g = np.zeros(n)
    t_all = np.arange(0, rows, cfg.row_stride)
    for a in range(0, len(t_all), cfg.chunk):
        ts = t_all[a:a + cfg.chunk]
        act = np.nonzero((starts <= ts[-1]) & (starts + L > ts[0]))[0]
        if act.size == 0:
            continue
        offs = ts[:, None] - starts[None, act]  # (T, A)
        valid = (offs >= 0) & (offs < L)
        oc = np.clip(offs, 0, L - 1)
        Phi = K[act[None, :], :, oc, :] * valid[:, :, None, None]  # (T, A, n_in, n_out)
        Phi = Phi.transpose(0, 3, 1, 2)  # (T, n_out, A, n_in)
        r = resid[ts]
        if row_w is not None:
            Phi = np.einsum("tab,tbji->taji", row_w[ts], Phi)
            r = np.einsum("tab,tb->ta", row_w[ts], r)
        P2 = Phi.reshape(len(ts) * n_out, act.size * n_in)
        cols = (act[:, None] * n_in + np.arange(n_in)[None, :]).ravel()
        G[np.ix_(cols, cols)] += P2.T @ P2
        g[cols] += P2.T @ r.reshape(-1)
    return G, g


def _cholesky(G, w0):
    try:
        return cho_factor(G, lower=True, check_finite=False)
    except LinAlgError as e:
        raise SolverError(f"FBS normal equations not positive definite in window at sample {w0}: {e}") from e


def _dense_basis(K, starts, rows, row_stride):
    """Dense filtered basis ``Phi`` (rows/stride * n_out, nJ * n_in) of one window."""
    nJ, n_in, L, n_out = K.shape
    ts = np.arange(0, rows, row_stride)
    Phi = np.zeros((len(ts), n_out, nJ, n_in))
    for jj in range(nJ):
        sel = (ts >= starts[jj]) & (ts < starts[jj] + L)
        if sel.any():
            Phi[sel, :, jj, :] = K[jj][:, ts[sel] - starts[jj], :].transpose(1, 2, 0)
    return Phi.reshape(len(ts) * n_out, nJ * n_in)


def fbs_solve(target: np.ndarray, kernel_fn: KernelFn, L: int, cfg: FbsConfig,
              row_weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Solve for B-spline coefficients whose filtered output tracks ``target``.

    Parameters
    ----------
    target : ndarray, shape (N, n_out)
        Desired outputs at every sample (relative to the rest position, so the pre-history is 0).
    kernel_fn : callable
        Filtered basis kernels, see :data:`KernelFn`; length ``L`` samples.  Called once per basis.
    row_weights : ndarray, shape (N, n_out, n_out), optional
        Per-sample output weighting ``W_k`` (the residual is ``W_k (y_k - target_k)``), e.g. the
        Jacobian so that the error is measured at the nozzle.

    Returns
    -------
    coef : ndarray, shape (J, n_in)
        Coefficients of bases ``j = 0 .. J-1`` (``J = ceil(N / m)``).
    predicted : ndarray, shape (N, n_out)
        The model's prediction for the committed command.
    """
    N, n_out = target.shape
    m, W, A = cfg.basis.m, cfg.window, cfg.advance
    J = -(-N // m)
    pred = np.zeros((N + L + W, n_out))
    coef = None
    centre = cfg.basis.greville_offset()
    lti_factor: dict = {}
    Kbuf = None  # kernels of bases [kb0, kb1)
    kb0 = kb1 = 0
    w0 = 0
    while w0 < N:
        j0, j1 = w0 // m, min(J, (w0 + W) // m)
        rows = min(W, N - w0)
        if Kbuf is None:
            Kbuf = kernel_fn(j0, j1)
            kb0, kb1 = j0, j1
        elif j1 > kb1:
            Knew = kernel_fn(kb1, j1)
            Kbuf = np.concatenate([Kbuf[j0 - kb0:], Knew])
            kb0, kb1 = j0, j1
        else:
            Kbuf = Kbuf[j0 - kb0:j1 - kb0]
            kb0 = j0
        K = Kbuf
        nJ, n_in = K.shape[0], K.shape[1]
        if coef is None:
            coef = np.zeros((J, n_in))
        starts = np.arange(j0, j1) * m - w0
        resid = target[w0:w0 + rows] - pred[w0:w0 + rows]
        rw = None if row_weights is None else row_weights[w0:w0 + rows]
        key = (nJ, rows)
        if cfg.lti and rw is None:
            # identical kernels: one dense filtered basis and one factorisation per window shape
            if key not in lti_factor:
                Phi2 = _dense_basis(K, starts, rows, cfg.row_stride)
                G = Phi2.T @ Phi2
                lam = cfg.reg * max(float(np.mean(np.diag(G))), 1e-30)
                G[np.diag_indices_from(G)] += lam
                lti_factor[key] = (_cholesky(G, w0), lam, Phi2)
            factor, lam, Phi2 = lti_factor[key]
            g = Phi2.T @ resid[:: cfg.row_stride].reshape(-1)
        else:
            G, g = _normal_equations(K, starts, rows, resid, rw, cfg)
            lam = cfg.reg * max(float(np.mean(np.diag(G))), 1e-30)
            G[np.diag_indices_from(G)] += lam
            factor = _cholesky(G, w0)
        # prior: each coefficient near the target at its basis' centre
        idx = np.clip(np.arange(j0, j1) * m + centre, 0, N - 1)
        prior = target[idx][:, :n_in] if n_in == n_out else np.zeros((nJ, n_in))
        c = cho_solve(factor, g + lam * prior.reshape(-1), check_finite=False).reshape(nJ, n_in)
        if not np.all(np.isfinite(c)):
            raise SolverError(f"FBS solution not finite in window at sample {w0}")
        # commit the bases starting in the first `advance` samples (all of them in the last window)
        last = w0 + W >= N
        n_commit = nJ if last else min(nJ, A // m)
        coef[j0:j0 + n_commit] = c[:n_commit]
        s0 = j0 * m
        if cfg.lti:
            # identical kernels: overlap-add is a convolution of the upsampled coefficients
            up = np.zeros((n_commit * m, n_in))
            up[::m] = c[:n_commit]
            for i in range(n_in):
                for o in range(n_out):
                    y = np.convolve(up[:, i], K[0, i, :, o])
                    pred[s0:s0 + len(y), o] += y
        else:
            contrib = np.einsum("jilo,ji->jlo", K[:n_commit], c[:n_commit])
            for jj in range(n_commit):
                s = s0 + jj * m
                pred[s:s + L] += contrib[jj]
        if last:
            break
        w0 += A
    return coef, pred[:N]
