"""Velocities and accelerations of a sampled reference: the derivatives of its cubic interpolant.

The inverse needs the reference's velocity and acceleration at every sample.  The firmware follows
the *samples*, so the derivatives must be the samples' own: a planner's exact derivatives leave out
the velocity jumps at corners (a square corner, every vertex of a sliced circle), which then never
reach the inverse.  Finite differences see them, but the plain ones are not mutually consistent:
the inverse interpolates its forcing linearly between samples, and central velocities with a
compact second difference describe no single curve.  The natural choice is the C2 cubic spline
through the samples: its second derivatives ``m`` solve ``(m- + 4 m + m+) / 6 = (q+ - 2 q + q-) /
dt^2`` and its velocities are ``(q+ - q-) / 2 dt - dt (m+ - m-) / 12``.

The tridiagonal solve is two first-order recursions, ``6 a / ((1 + a z^-1)(1 + a z))`` with
``a = 2 - sqrt(3)``; the backward one is cut after ``lookahead`` samples (``a^24 ~ 2e-14``), so the
derivatives stream with a fixed delay of ``lookahead + 2`` samples.  :func:`spline_derivatives`
(a whole array) runs the same streaming code, so both agree to rounding.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter

__all__ = ["SplineDerivatives", "spline_derivatives", "LOOKAHEAD"]

#: samples of look-ahead of the backward recursion (its tail a^LOOKAHEAD ~ 2e-14 is dropped)
LOOKAHEAD = 24
_A = 2.0 - math.sqrt(3.0)


class SplineDerivatives:
    """Streaming derivatives of the cubic interpolant of samples ``q`` (at rest before the first).

    Feed chunks with :meth:`push` (rows of ``q`` (n, 3) plus any aligned per-row arrays); each call
    returns the rows whose derivatives are final, ``(q, qd, qdd, *extras)``, ``lookahead + 2``
    samples behind.  :meth:`finish` returns the rest, the reference held at rest after its end.
    """

    def __init__(self, q_rest: np.ndarray, dt_s: float, lookahead: int = LOOKAHEAD):
        self.dt = float(dt_s)
        self.D = int(lookahead)
        self.taps = 6.0 * _A * (-_A) ** np.arange(self.D + 1)
        q_rest = np.asarray(q_rest, float)
        self.q = q_rest[None].copy()  # raw samples from global index k_q (k_q = -1: the rest before)
        self.k_q = -1
        self.y = np.zeros((0, q_rest.shape[0]))  # forward recursion from global index k_y
        self.k_y = 0
        self.zi = np.zeros((1, q_rest.shape[0]))  # its state (0: at rest)
        self.m = np.zeros((1, q_rest.shape[0]))  # spline second derivatives from k_m (m_-1 = 0: at rest)
        self.k_m = -1
        self.extras: list[np.ndarray] | None = None  # pending per-row arrays, from global index k_e
        self.k_e = 0
        self.n = 0  # samples received

    def push(self, q: np.ndarray, *extras: np.ndarray) -> tuple:
        q = np.asarray(q, float)
        ex = [np.asarray(e) for e in extras]
        self.extras = ex if self.extras is None else [np.concatenate([a, b]) for a, b in zip(self.extras, ex)]
        self.q = np.concatenate([self.q, q])
        self.n += len(q)
        return self._advance(self.n)

    def finish(self) -> tuple:
        """The remaining rows: the reference stays at its last sample after the end."""
        last = self.q[-1:]
        self.q = np.concatenate([self.q, np.repeat(last, self.D + 3, 0)])
        return self._advance(self.n + self.D + 3, limit=self.n)

    def _advance(self, n_avail: int, limit: int | None = None) -> tuple:
        dt = self.dt
        # compact second differences c_k for k in [k_y + len(y), n_avail - 1): need q_{k+1}
        kc0, kc1 = self.k_y + len(self.y), n_avail - 1
        if kc1 > kc0:
            i = kc0 - self.k_q  # index of q_k in the buffer
            qq = self.q[i - 1:kc1 - self.k_q + 1]
            c = (qq[2:] - 2.0 * qq[1:-1] + qq[:-2]) / dt**2
            y, self.zi = lfilter([1.0], [1.0, _A], c, axis=0, zi=self.zi)
            self.y = np.concatenate([self.y, y])
        # m_k = sum_j taps_j y_{k+j}: need y up to k + D
        km1 = self.k_y + len(self.y) - self.D
        km0 = self.k_m + len(self.m)
        if km1 > km0:
            j0 = km0 - self.k_y
            seg = self.y[j0:km1 - self.k_y + self.D]
            L = km1 - km0
            mm = np.zeros((L, seg.shape[1]))
            for j, t in enumerate(self.taps):
                mm += t * seg[j:j + L]
            self.m = np.concatenate([self.m, mm])
        # rows k ready when m_{k+1} is known
        ke1 = self.k_m + len(self.m) - 1
        if limit is not None:
            ke1 = min(ke1, limit)
        ke0 = self.k_e
        if ke1 <= ke0:
            return self._empty()
        iq = ke0 - self.k_q
        qk = self.q[iq:iq + ke1 - ke0]
        qp, qn = self.q[iq - 1:iq - 1 + ke1 - ke0], self.q[iq + 1:iq + 1 + ke1 - ke0]
        im = ke0 - self.k_m
        mk = self.m[im:im + ke1 - ke0]
        mn = self.m[im + 1:im + 1 + ke1 - ke0]
        mp = self.m[im - 1:im - 1 + ke1 - ke0]
        qd = (qn - qp) / (2.0 * dt) - dt * (mn - mp) / 12.0
        out = (qk.copy(), qd, mk.copy(), *[e[:ke1 - ke0] for e in self.extras])
        # forget what no later row needs
        self.extras = [e[ke1 - ke0:] for e in self.extras]
        self.k_e = ke1
        keep_q = ke1 - 1 - self.k_q
        self.q = self.q[keep_q:]
        self.k_q = ke1 - 1
        drop_m = ke1 - 1 - self.k_m
        if drop_m > 0:
            self.m = self.m[drop_m:]
            self.k_m = ke1 - 1
        drop_y = self.k_m + len(self.m) - self.k_y
        if drop_y > 0:
            self.y = self.y[drop_y:]
            self.k_y += drop_y
        return out

    def _empty(self) -> tuple:
        z = np.zeros((0, self.q.shape[1]))
        return (z, z, z, *[e[:0] for e in (self.extras or [])])


def spline_derivatives(q: np.ndarray, dt_s: float, lookahead: int = LOOKAHEAD) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and acceleration (N, 3) of the cubic interpolant of ``q`` (N, 3), at rest outside."""
    q = np.asarray(q, float)
    s = SplineDerivatives(q[0], dt_s, lookahead)
    a = s.push(q)
    b = s.finish()
    return np.concatenate([a[1], b[1]]), np.concatenate([a[2], b[2]])
