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
    """Window settings (samples).  ``advance`` and ``window`` must be multiples of ``basis.m``."""

    basis: UniformBasis
    window: int = 400
    advance: int = 200
    reg: float = 1e-6
    lti: bool = False  # kernels identical for every basis: factorise once

    def __post_init__(self):
        m = self.basis.m
        if self.window % m or self.advance % m or not (0 < self.advance < self.window):
            raise ValueError(f"window ({self.window}) and advance ({self.advance}) must be multiples of the "
                             f"knot spacing ({m} samples) with 0 < advance < window")


def fbs_solve(target: np.ndarray, kernel_fn: KernelFn, L: int, cfg: FbsConfig,
              row_weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Solve for B-spline coefficients whose filtered output tracks ``target``.

    Parameters
    ----------
    target : ndarray, shape (N, n_out)
        Desired outputs at every sample (relative to the rest position, so the pre-history is 0).
    kernel_fn : callable
        Filtered basis kernels, see :data:`KernelFn`; length ``L`` samples.
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
    lti_cache: dict = {}
    w0 = 0
    while w0 < N:
        j0, j1 = w0 // m, min(J, (w0 + W) // m)
        rows = min(W, N - w0)
        K = kernel_fn(j0, j1)  # (nJ, n_in, L, n_out)
        nJ, n_in = K.shape[0], K.shape[1]
        if coef is None:
            coef = np.zeros((J, n_in))
        # dense filtered basis for this window: Phi[t, o, j, i]
        key = (nJ, rows)
        if cfg.lti and key in lti_cache and row_weights is None:
            Phi2, factor, lam = lti_cache[key]
        else:
            Phi = np.zeros((rows, n_out, nJ, n_in))
            for jj in range(nJ):
                s = (j0 + jj) * m - w0
                n = min(L, rows - s)
                if n > 0:
                    Phi[s:s + n, :, jj, :] = K[jj, :, :n, :].transpose(1, 2, 0)
            if row_weights is not None:
                Phi = np.einsum("tab,tbji->taji", row_weights[w0:w0 + rows], Phi)
            Phi2 = Phi.reshape(rows * n_out, nJ * n_in)
            G = Phi2.T @ Phi2
            lam = cfg.reg * max(float(np.mean(np.diag(G))), 1e-30)
            G[np.diag_indices_from(G)] += lam
            try:
                factor = cho_factor(G, lower=True, check_finite=False)
            except LinAlgError as e:
                raise SolverError(f"FBS normal equations not positive definite in window at sample {w0}: {e}") from e
            if cfg.lti and row_weights is None:
                lti_cache[key] = (Phi2, factor, lam)
        resid = target[w0:w0 + rows] - pred[w0:w0 + rows]
        if row_weights is not None:
            resid = np.einsum("tab,tb->ta", row_weights[w0:w0 + rows], resid)
        # prior: each coefficient near the target at its basis' centre
        idx = np.clip(np.arange(j0, j1) * m + centre, 0, N - 1)
        prior = target[idx][:, :n_in] if n_in == n_out else np.zeros((nJ, n_in))
        rhs = Phi2.T @ resid.reshape(-1) + lam * prior.reshape(-1)
        c = cho_solve(factor, rhs, check_finite=False).reshape(nJ, n_in)
        if not np.all(np.isfinite(c)):
            raise SolverError(f"FBS solution not finite in window at sample {w0}")
        # commit the bases starting in the first `advance` samples (all of them in the last window)
        last = w0 + W >= N
        n_commit = nJ if last else min(nJ, A // m)
        coef[j0:j0 + n_commit] = c[:n_commit]
        for jj in range(n_commit):
            s = (j0 + jj) * m
            pred[s:s + L] += np.einsum("ilo,i->lo", K[jj], c[jj])
        if last:
            break
        w0 += A
    return coef, pred[:N]
