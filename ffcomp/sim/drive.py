"""The drive (electrical) filters of the simulator, run exactly on a fine time grid, block by block.

Each tower's drive filter ``F_i(s)`` (the realisation ``(a, b, c)`` of
:func:`~ffcomp.model.lpv.drive_filter_ss`) turns the carriage command ``r_i`` into the drive position
``u_i = c z`` with ``z' = a z + b r``; the mechanics also need ``u_i' = c a z + c b r``.  The filter is
linear and pose independent, so it is balanced and discretised once, exactly, for the command
interpolation in use (``zoh``: held, ``foh``: linear between grid points) and run as first-order modal
recursions
(``scipy.signal.lfilter`` per eigenvalue, complex): well conditioned even with poles close to
``z = 1``, where transfer-function or second-order-section forms lose digits.

The state is carried from block to block, so a run of any length needs memory for one block only.
Units: SI (m, m/s, s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg, signal

__all__ = ["DriveGrid", "upsample"]


@dataclass
class _Tower:
    lam: np.ndarray  # (n,) discrete modal poles
    bm: np.ndarray  # (n,) modal input gains
    cm: np.ndarray  # (2, n) modal output gains (u, u')
    d: np.ndarray  # (2,) direct feedthrough of the discretised filter to (u, u')


class DriveGrid:
    """Drive filters of the three towers discretised with step ``h_s`` for ``hold`` ("zoh"/"linear").

    Use :meth:`start` for the state at rest, then :meth:`run` on consecutive blocks of command
    *deviations* from the starting command (the filters have unit DC gain, so the run starts at
    steady state).
    """

    def __init__(self, filters, h_s: float, hold: str):
        self.hold = hold
        method = "zoh" if hold == "zoh" else "foh"
        self.towers = []
        for a0, b0, c0 in filters:
            # balance first: Pade realisations come with states scaled over ~40 decades
            a, Tb = linalg.matrix_balance(a0)
            b, c = np.linalg.solve(Tb, b0), c0 @ Tb
            C2 = np.stack([c, c @ a])
            D2 = np.array([[0.0], [float(c @ b)]])
            Ad, Bd, Cd, Dd, _ = signal.cont2discrete((a, b[:, None], C2, D2), h_s, method=method)
            lam, V = np.linalg.eig(Ad)
            bm = np.linalg.solve(V, Bd[:, 0].astype(complex))
            self.towers.append(_Tower(lam, bm, Cd @ V, Dd[:, 0].copy()))
        self._d_zoh = np.array([float(c @ b) for a, b, c in filters]) if hold == "zoh" else np.zeros(3)

    def start(self, R: int) -> dict:
        """State at rest for ``R`` runs."""
        return {"z": [np.zeros((R, t.lam.shape[0]), complex) for t in self.towers], "x_prev": None}

    def run(self, x: np.ndarray, state: dict):
        """Filter one block of grid samples.

        Parameters
        ----------
        x : ndarray, shape (R, T + 1, 3)
            Command deviations at grid points ``j0 .. j0 + T`` (the last one is the first of the
            next block).
        state : dict
            From :meth:`start` or the previous call; updated in place.

        Returns
        -------
        u, ud, ud_left : ndarray, shape (R, T + 1, 3)
            Drive position deviation (m) and velocity (m/s) at the grid points; ``ud`` is the
            right limit, ``ud_left`` the left limit (they differ where a held command steps).
        """
        R, T1, _ = x.shape
        u = np.empty_like(x)
        ud = np.empty_like(x)
        for i, tw in enumerate(self.towers):
            xi = x[:, :-1, i]
            z = np.empty((tw.lam.shape[0], R, T1), complex)
            for k in range(tw.lam.shape[0]):
                # z[n+1] = lam z[n] + bm x[n]: y[n] = z[n] for n < T; the final state is z[T]
                zk, zf = signal.lfilter([0.0, tw.bm[k]], [1.0, -tw.lam[k]], xi, axis=-1,
                                        zi=state["z"][i][:, k:k + 1])
                z[k, :, :-1] = zk
                z[k, :, -1] = zf[:, 0]
                state["z"][i][:, k] = zf[:, 0]
            y = np.einsum("pk,krt->prt", tw.cm, z).real
            u[:, :, i] = y[0] + tw.d[0] * x[:, :, i]
            ud[:, :, i] = y[1] + tw.d[1] * x[:, :, i]
        ud_left = ud.copy()
        if self.hold == "zoh" and np.any(self._d_zoh):
            prev = x[:, :1] if state["x_prev"] is None else state["x_prev"]
            jump = np.diff(np.concatenate([prev, x], axis=1), axis=1)
            ud_left -= self._d_zoh * jump
        state["x_prev"] = x[:, -2:-1].copy() if T1 > 1 else x[:, -1:].copy()
        return u, ud, ud_left


def upsample(r: np.ndarray, k0: int, k1: int, n2: int, hold: str) -> np.ndarray:
    """Commands ``r`` (R, N, 3) at grid points ``j = k0 n2 .. k1 n2`` (``n2`` per sample), (R, M, 3).

    ``zoh``: the sample is held until the next one; ``linear``: linear interpolation.
    """
    j = np.arange(k0 * n2, k1 * n2 + 1)
    k = np.minimum(j // n2, r.shape[1] - 1)
    if hold == "zoh":
        return r[:, k]
    frac = ((j - k * n2) / n2)[None, :, None]
    k_next = np.minimum(k + 1, r.shape[1] - 1)
    return r[:, k] + frac * (r[:, k_next] - r[:, k])
