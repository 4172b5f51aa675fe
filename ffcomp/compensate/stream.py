"""The streaming windowed solver of the inverse, with its bounds.

:class:`FbsStream` is the windowed solver of :mod:`.fbs` turned inside out: targets are fed in
chunks, windows are solved as soon as their data (plus preview) is there, committed coefficients
are turned into final spline values, and everything older than one kernel length is dropped.
Where the least-squares solution breaks the command's bounds (deviation, carriage velocity and
acceleration, Klipper's delta cap near z moves) the window is solved again as a QP (:mod:`.qp`).
:class:`~ffcomp.compensate.stream_inverse.StreamingInverse` chains the mechanics stage and the
three drive stages on top of it.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from scipy.fft import irfft, next_fast_len, rfft
from scipy.linalg import cho_factor, cho_solve

from ..errors import SolverError
from .bspline import UniformBasis
from .fbs import _dense_basis
from .qp import active_set_qp, osqp_solve

__all__ = ["FbsStream"]

#: ``FbsStream._surely_within``'s default: the window's common-mode band is computed there
_OWN = object()


def _command_shapes(basis: UniformBasis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Value, velocity and acceleration of one basis function as the firmware moves the command.

    Splines of degree >= 2 have continuous velocity and acceleration (their analytic derivatives).
    A linear spline's samples are joined by straight segments: its velocity is the central
    difference and its acceleration the second difference of the samples (the change of segment
    velocity over one sample), one sample beyond the support on either side.
    """
    if basis.degree >= 2:
        return basis.shape(0), basis.shape(1), basis.shape(2)
    dt = basis.dt_s
    s = np.concatenate([[0.0], basis.shape(0), [0.0, 0.0]])  # samples -1 .. support + 1
    v = (s[2:] - s[:-2]) / (2.0 * dt)
    a = (s[2:] - 2.0 * s[1:-1] + s[:-2]) / dt**2
    return s[1:-1], v, a


class FbsStream:
    """Windowed LTI filtered-B-spline least squares, fed in chunks.

    Parameters
    ----------
    kernel : ndarray, shape (n_in, L, n_out)
        The filtered response of one basis function (identical for every basis).
    basis : UniformBasis
    window, advance : int
        Samples; multiples of ``basis.m``.
    reg : float
        Relative Tikhonov weight towards the target at each basis' centre.
    row_stride : int
        Residual evaluated on every ``row_stride``-th sample.
    channels : int
        Independent signals through the same (single-input single-output) kernel, solved together.
    lam_fn : callable, optional
        ``lam_fn(rows)``: the Tikhonov weight of a window of ``rows`` samples (default: ``reg``
        times the mean diagonal of the window's Gram matrix; :class:`.modal_fbs.ModalFbs` passes
        the coupled problem's).
    """

    def __init__(self, kernel: np.ndarray, basis: UniformBasis, window: int, advance: int, reg: float,
                 row_stride: int = 1, channels: int = 1, lam_fn=None):
        self.K = np.asarray(kernel, float)
        self.n_in, self.L, self.n_out = self.K.shape
        if channels > 1 and (self.n_in != 1 or self.n_out != 1):
            raise ValueError("several channels need a single-input single-output kernel")
        self.C = channels  # independent signals through the same kernel (solved together)
        self.basis, self.W, self.A, self.reg, self.rs = basis, window, advance, reg, row_stride
        m = basis.m
        if window % m or advance % m or not (0 < advance < window):
            raise ValueError("window and advance must be multiples of the knot spacing, 0 < advance < window")
        self.m = m
        self.nJ = window // m
        starts = np.arange(self.nJ) * m
        Kb = np.broadcast_to(self.K[None], (self.nJ,) + self.K.shape)
        self.Phi = _dense_basis(Kb, starts, window, row_stride)
        G = self.Phi.T @ self.Phi
        self.lam_fn = lam_fn
        self.lam = lam_fn(window) if lam_fn is not None else reg * max(float(np.mean(np.diag(G))), 1e-30)
        G[np.diag_indices_from(G)] += self.lam
        self.factor = cho_factor(G, lower=True, check_finite=False)
        self._tail_cache: dict[int, tuple] = {}
        self._op_cache: dict[int, tuple] = {}
        self._fft_cache: dict[int, tuple] = {}
        self._idx_cache: dict[int, np.ndarray] = {}
        # buffers indexed from sample `off`
        self.off = 0
        self.tgt = np.zeros((0, self.n_out * self.C))
        self.pin = np.zeros(0, bool)  # rows where the spline itself must be zero
        self.pin_weight = 1e3
        self.bounds = None  # (deviation m, velocity m/s, acceleration m/s^2) of the command, see set_bounds
        self.rvel = np.zeros((0, self.C))  # reference velocity and acceleration of each row (for the bounds)
        self.racc = np.zeros((0, self.C))
        self.cacc = np.zeros(0)  # reference acceleration of the common mode (z) of each row, see set_common_accel_bound
        self.cbound = None  # (limit m/s^2, share, reach samples)
        # per row: matrices (3, C) from the channels' accelerations to constrained nozzle components
        # (z and the two normals of the path) and their limits (m/s^2), see set_common_accel_bound
        self.cpos = np.zeros((0, 3))  # the reference's nozzle position of each row (m), for comp_fn
        self.comp_fn = None
        self.band_dropped = 0  # QPs where the common-mode band could not be kept (solved without it)
        self.qp_windows = 0  # windows where the bounds were active (solved by OSQP)
        self.qp_redirected = 0  # of those, solved again along the solution's own direction
        self.qp_exact = 0  # joint QPs solved exactly by the active-set method (the rest: OSQP)
        self._qp_cache: dict = {}
        self._abox_cache: dict = {}  # the joint QP's box rows per window shape (sparse)
        self._rows_cache: dict = {}
        self.pred = np.zeros((window + self.L + 1, self.n_out * self.C))
        self.w0 = 0
        self.coef = np.zeros((0, self.n_in * self.C))  # committed coefficients of bases [cj0, cj0 + len)
        self.cj0 = 0
        self.done = 0  # samples whose spline value has been returned
        self.shape = basis.shape(0)

    def _solve_window(self, rows: int, final: bool) -> None:
        m, W = self.m, self.W
        a = self.w0 - self.off
        need = a + rows + self.L + W
        if need > len(self.pred):  # grown a few windows at a time (rows past `need` stay zero)
            self.pred = np.concatenate([self.pred, np.zeros((need - len(self.pred) + 4 * W, self.pred.shape[1]))])
        resid = self.tgt[a:a + rows] - self.pred[a:a + rows]
        if rows == W:
            Phi, factor, lam = self.Phi, self.factor, self.lam
        else:  # the last, shorter window
            if rows not in self._tail_cache:
                nJ = -(-rows // m)
                Kb = np.broadcast_to(self.K[None], (nJ,) + self.K.shape)
                Ph = _dense_basis(Kb, np.arange(nJ) * m, rows, self.rs)
                G = Ph.T @ Ph
                lam_t = (self.lam_fn(rows) if self.lam_fn is not None
                         else self.reg * max(float(np.mean(np.diag(G))), 1e-30))
                G[np.diag_indices_from(G)] += lam_t
                self._tail_cache[rows] = (Ph, cho_factor(G, lower=True, check_finite=False), lam_t)
            Phi, factor, lam = self._tail_cache[rows]
        nJ = Phi.shape[1] // self.n_in
        pins = np.nonzero(self.pin[a:a + rows])[0] if len(self.pin) else np.zeros(0, int)
        if pins.size:
            # the command must equal the reference here (the planned nozzle stands still): penalise
            # the spline's value at these samples; such windows are factorised on their own
            B = np.zeros((pins.size, nJ))
            for jj in range(nJ):
                off = pins - jj * m
                ok = (off >= 0) & (off < self.basis.support)
                B[ok, jj] = self.shape[off[ok]]
            Bk = np.kron(B, np.eye(self.n_in))
            G = Phi.T @ Phi
            G[np.diag_indices_from(G)] += lam
            wgt = self.pin_weight**2 * max(float(np.mean(np.diag(G))), 1e-30)
            G += wgt * Bk.T @ Bk
            factor = cho_factor(G, lower=True, check_finite=False)
        gi = self._idx_cache.get(rows)
        if gi is None:  # each basis' Greville sample (where the prior acts)
            gi = self._idx_cache[rows] = np.clip(np.arange(nJ) * m + self.basis.greville_offset(), 0, rows - 1)
        idx = gi + a
        bounded = self.bounds is not None and self.n_in == 1 and self.n_out == 1
        n_commit = nJ if final else self.A // m
        r = resid[:: self.rs]
        if self.C > 1:  # one kernel, several signals: a matrix right-hand side
            prior = self.tgt[idx]
        else:
            prior = self.tgt[idx][:, : self.n_in] if self.n_in == self.n_out else np.zeros((nJ, self.n_in))
            r, prior = r.reshape(-1), prior.reshape(-1)

        def rhs():
            return Phi.T @ r + lam * prior

        if pins.size:
            c = cho_solve(factor, rhs(), check_finite=False)
        else:
            # the solution operators of this window shape, G^-1 Phi^T and lam G^-1 (the same in every
            # window): two products instead of forming Phi^T r and a Cholesky solve; only the
            # committed bases are needed unless the bounds are checked
            Mop, Nop = self._operators(rows, Phi, factor, lam)
            k = (nJ if bounded else n_commit) * self.n_in
            c = Mop[:k] @ r + Nop[:k] @ prior
        c = c.reshape(-1, self.n_in * self.C) if self.C == 1 else c
        if not np.isfinite(c).all():
            raise SolverError(f"FBS solution not finite in the window at sample {self.w0}")
        if bounded:
            c = self._bounded(c, rows, nJ, a, rhs, factor, pins)
        c = c[:n_commit]
        # predicted output of the committed bases: the overlap-add of identical kernels, by FFT
        n_y = n_commit * m + self.L - 1
        nfft, Khat = self._kernel_fft(n_y)
        up = np.zeros((nfft, c.shape[1]))
        up[: n_commit * m: m] = c
        U = rfft(up, axis=0)
        if self.C > 1:
            Y = U * Khat[:, 0, :1]
        else:
            Y = np.einsum("fi,fio->fo", U, Khat)
        self.pred[a:a + n_y] += irfft(Y, nfft, axis=0)[:n_y]
        self.coef = np.concatenate([self.coef, c])
        self.w0 += n_commit * m

    def _kernel_fft(self, n: int) -> tuple:
        """FFT length for ``n`` output samples and the kernel's transform at it, (F, n_in, n_out)."""
        hit = self._fft_cache.get(n)
        if hit is None:
            nfft = next_fast_len(n, real=True)
            hit = self._fft_cache[n] = (nfft, rfft(self.K, nfft, axis=1).transpose(1, 0, 2).copy())
        return hit

    def _operators(self, rows: int, Phi: np.ndarray, factor, lam: float) -> tuple:
        ops = self._op_cache.get(rows)
        if ops is None:
            Mop = cho_solve(factor, Phi.T, check_finite=False)
            Nop = lam * cho_solve(factor, np.eye(Phi.shape[1]), check_finite=False)
            # (in double precision: single precision halves the time of the products, but its sums
            # cancel; on the fidelity bench's z travel on other_delta the G-code's contour ratio went
            # from 0.014 to 0.025)
            ops = self._op_cache[rows] = (np.ascontiguousarray(Mop), np.ascontiguousarray(Nop))
        return ops

    # ------------------------------------------------------------------ bounds (OSQP)
    def set_bounds(self, deviation: float, velocity: float, acceleration: float, stride: int = 2) -> None:
        """Bound the command ``reference + spline``: ``|spline| <= deviation`` (m), ``|velocity| <=
        velocity`` (m/s), ``|acceleration| <= acceleration`` (m/s^2), checked every ``stride`` samples.
        Windows whose least-squares solution breaks a bound are re-solved as a QP with OSQP
        (warm-started).  A bound the reference itself breaks is relaxed to the reference's value there.
        """
        self.bounds = (float(deviation), float(velocity), float(acceleration))
        self.cstride = int(stride)

    def set_common_accel_bound(self, limit: float, share: float = 0.3, reach: int = 40, components=None) -> None:
        """Bound the acceleration of the command's common mode where its reference comes near ``limit``.

        A delta moves its nozzle in z by moving the three carriages together: the nozzle's z
        acceleration is ``sum_i w_i q_i''`` with ``w`` the z row of ``dX/dq`` (``w_i >= 0``,
        ``sum w_i = 1``), and Klipper caps it on every segment at ``max_z_accel``
        (``max_z_accel * d/|dz|`` on the path acceleration).  The rows fed with ``common_acc``
        (the reference's z acceleration, m/s^2) carry that rule: within ``reach`` samples of a row
        whose ``|common_acc| >= share * limit`` (m/s^2), the rule applies:

        * with several channels, ``components`` (called as ``components(pos, vel, acc)`` with the
          rows' nozzle positions fed as ``poses`` (m) and the reference's channel velocities and
          accelerations; returns the rows' matrices (R, K, C) and limits (R, K), m/s^2, e.g.
          :func:`~ffcomp.compensate.nozzle_limits.nozzle_components`: the nozzle's acceleration
          along and across the path, with Klipper's ``max_z_accel / |u_z|``) and the rows' poses:
          those components of the command stay within their limits (or the reference's own value
          where it exceeds them), one QP over the channels;
        * otherwise every channel's spline acceleration ``s''`` is kept in ``[-A - a_z, A - a_z]``
          with ``A = max(limit, |a_z|)``, which keeps the command's z acceleration
          ``a_z + sum_i w_i s_i''`` within ``A`` whatever the weights (stricter: it also holds
          back the differential, XY, corrections).

        Elsewhere only :meth:`set_bounds` applies; needs :meth:`set_bounds` (the same OSQP solve).
        """
        self.cbound = (float(limit), float(share), int(reach))
        self.comp_fn = components

    def _basis_rows(self, starts: np.ndarray, rows: np.ndarray) -> tuple:
        """Values, first and second derivatives of bases starting at ``starts`` at sample ``rows``."""
        if not hasattr(self, "_shapes"):
            self._shapes = _command_shapes(self.basis)
            self._sup_rows = len(self._shapes[0])
        sup = self._sup_rows
        off = rows[:, None] - starts[None, :]
        ok = (off >= 0) & (off < sup)
        oc = np.clip(off, 0, sup - 1)
        return tuple(np.where(ok, sh[oc], 0.0) for sh in self._shapes)

    def _common_band(self, a: int, rows: int):
        """The common-mode band of the window's rows ``[a, a + rows)`` (see
        :meth:`set_common_accel_bound`): ``(lo, hi)`` (rows,) limits on the spline's acceleration
        (m/s^2, +-inf where it does not apply), or None where no row of the window is near the limit."""
        if self.cbound is None or rows <= 0:
            return None
        lim, share, reach = self.cbound
        n = len(self.cacc)
        i0, i1 = max(0, a - reach), min(n, a + rows + reach)
        big = np.abs(self.cacc[i0:i1]) >= share * lim
        if not big.any():
            return None
        cs = np.concatenate([[0], np.cumsum(big)])
        i = np.arange(a, a + rows) - i0
        act = cs[np.clip(i + reach + 1, 0, len(big))] - cs[np.clip(i - reach, 0, len(big))] > 0
        az = self.cacc[a:a + rows]
        A = np.maximum(lim, np.abs(az) * 1.0001)
        return np.where(act, -A - az, -np.inf), np.where(act, A - az, np.inf)

    def _surely_within(self, cp: np.ndarray, c: np.ndarray, a: int, rows: int, band=_OWN) -> bool:
        """A cheap sufficient test that the window's command keeps its bounds.

        The spline on the window's rows is ``sum c_j B_j`` over the bases still acting there (the
        committed ones, ``cp``, and the window's, ``c``); padded with zero coefficients it is the
        same spline.  Uniform B-splines are a partition of unity and their derivatives are
        B-splines of differenced coefficients (``s' = sum (c_j - c_{j-1}) N_j / h``), so
        ``|s| <= max|c|``, ``|s'| <= max|dc| / h`` and ``|s''| <= max|d2c| / h^2`` everywhere.
        When these bounds, plus the reference's own velocity and acceleration, are inside the
        limits, no row can break them and the exact check is skipped.  ``band``: the window's
        :meth:`_common_band` when the caller has it already.
        """
        D, V, Acc = self.bounds
        h = self.m * self.basis.dt_s
        # a linear spline's acceleration is its samples' second difference: d2c / (m dt^2) at a knot
        h2 = h * h if self.basis.degree >= 2 else self.m * self.basis.dt_s**2
        z = np.zeros((2, c.shape[1]))
        call = np.concatenate([z, cp, c, z])
        d1 = np.diff(call, axis=0)
        d2 = np.diff(d1, axis=0)
        vmax = float(np.max(np.abs(self.rvel[a:a + rows]))) if rows else 0.0
        amax = float(np.max(np.abs(self.racc[a:a + rows]))) if rows else 0.0
        if band is _OWN:
            band = FbsStream._common_band(self, a, rows) if getattr(self, "cbound", None) is not None else None
        smax = np.max(np.abs(d2)) / h2
        if band is not None and smax > float(np.min(np.minimum(-band[0], band[1]))):
            return False
        return bool(np.max(np.abs(call)) <= D and np.max(np.abs(d1)) / h + vmax <= V
                    and smax + amax <= Acc)

    def _bounded(self, c, rows, nJ, a, rhs, factor, pins):
        import osqp
        import scipy.sparse as sp

        m, dt = self.m, self.basis.dt_s
        D, V, Acc = self.bounds
        # committed bases still acting on the window's rows
        sup_j = self.basis.support // m + 1
        jp = np.arange(max(self.cj0, self.w0 // m - sup_j), self.w0 // m)
        cp = self.coef[jp - self.cj0] if len(jp) else np.zeros((0, self.C))
        band = self._common_band(a, rows)
        if self._surely_within(cp, c, a, rows, band=band):
            return c
        ckey = (nJ, rows, len(jp))
        if ckey not in self._rows_cache:  # the same for every full window
            r = np.arange(0, rows, self.cstride)
            B0, B1, B2 = self._basis_rows(np.arange(nJ) * m, r)
            live = np.abs(B0).sum(1) + np.abs(B2).sum(1) > 0  # rows the new bases can still change
            r, B0, B1, B2 = r[live], B0[live], B1[live], B2[live]
            # the committed bases' rows, stacked like B0, B1, B2 (banded: sparse products, a tenth
            # of the dense ones' time)
            Ps = sp.csr_matrix(np.vstack(self._basis_rows(np.arange(-len(jp), 0) * m, r))) if len(jp) else None
            self._rows_cache[ckey] = (r, B0, B1, B2, sp.csr_matrix(np.vstack([B0, B1, B2])), Ps)
        r, B0, B1, B2, Bs, Ps = self._rows_cache[ckey]
        R = len(r)
        e0, e1, e2 = np.split(Ps @ cp, 3) if Ps is not None else (np.zeros((R, self.C)),) * 3  # (R, C)
        vref, aref = self.rvel[a + r], self.racc[a + r]
        # never demand more than the reference or the committed past allow
        Vb = np.maximum(V, np.abs(vref) * 1.0001)
        Ab = np.maximum(Acc, np.abs(aref) * 1.0001)
        # the command's acceleration a_ref + s'' within +-Ab, and s'' within the common-mode band
        a_lo, a_hi = -Ab - aref, Ab - aref
        if band is not None and self.C > 1 and self.comp_fn is not None and len(self.cpos) >= a + rows:
            return self._bounded_joint(c, a, r, B2, Bs, e0, e1, e2, vref, aref, Vb, Ab, band, nJ, rhs,
                                       factor, rows == self.W and pins.size == 0)
        b0, b1, b2 = np.split(Bs @ c, 3)
        val, vel, acc = b0 + e0, b1 + e1 + vref, b2 + e2 + aref
        if band is not None:
            a_lo = np.maximum(a_lo, band[0][r][:, None])
            a_hi = np.minimum(a_hi, band[1][r][:, None])
        s2 = acc - aref
        bad = (np.abs(val) > D) | (np.abs(vel) > Vb) | (s2 < a_lo) | (s2 > a_hi)
        chans = np.nonzero(bad.any(axis=0))[0]
        if chans.size == 0:
            return c
        self.qp_windows += 1
        g = rhs().reshape(nJ, -1)
        # OSQP works on a scaled problem: coefficients in units of 0.1 mm, the objective normalised,
        # every constraint row normalised to unit size (values, velocities, accelerations differ by
        # orders of magnitude)
        sc = 1e-4
        key = (nJ, rows, pins.size == 0)
        if key not in self._qp_cache or pins.size:
            G = self._gram_of(rows == self.W and pins.size == 0, factor)
            gn = float(np.mean(np.diag(G))) * sc * sc
            Araw = np.vstack([B0, B1, B2]) * sc
            rn = np.maximum(np.max(np.abs(Araw), axis=1), 1e-300)
            solver = osqp.OSQP()
            solver.setup(P=sp.triu(sp.csc_matrix(G * sc * sc / gn), format="csc"), q=np.zeros(nJ),
                         A=sp.csc_matrix(Araw / rn[:, None]), l=-np.ones(len(rn)), u=np.ones(len(rn)),
                         verbose=False, warm_starting=True, eps_abs=1e-5, eps_rel=1e-5, max_iter=4000,
                         polishing=False)
            entry = (solver, gn, rn)
            if pins.size == 0:
                self._qp_cache[key] = entry
        else:
            entry = self._qp_cache[key]
        solver, gn, rn = entry
        out = c.copy()
        for ch in chans:
            v0 = vref[:, ch] + e1[:, ch]
            lo = np.concatenate([-D - e0[:, ch], -Vb[:, ch] - v0, a_lo[:, ch] - e2[:, ch]])
            hi = np.concatenate([D - e0[:, ch], Vb[:, ch] - v0, a_hi[:, ch] - e2[:, ch]])
            solver.update(q=-g[:, ch] * sc / gn, l=lo / rn, u=hi / rn)
            solver.warm_start(x=c[:, ch] / sc)
            res = osqp_solve(solver)
            ok = res.info.status in ("solved", "solved inaccurate", "maximum iterations reached")
            if band is not None and (not ok or res.x is None or not np.all(np.isfinite(res.x))):
                # the committed past leaves no room for the common-mode band: the plain bounds only
                self.band_dropped += 1
                lo[2 * R:] = -Ab[:, ch] - aref[:, ch] - e2[:, ch]
                hi[2 * R:] = Ab[:, ch] - aref[:, ch] - e2[:, ch]
                solver.update(l=lo / rn, u=hi / rn)
                solver.warm_start(x=c[:, ch] / sc)
                res = osqp_solve(solver)
                ok = res.info.status in ("solved", "solved inaccurate", "maximum iterations reached")
            if not ok or res.x is None or not np.all(np.isfinite(res.x)):
                raise SolverError(
                    f"OSQP could not keep the command within its bounds in the window starting at t = "
                    f"{self.w0 * dt:.3f} s (status {res.info.status!r}; bounds: deviation {D * 1e3:g} mm, "
                    f"velocity {V * 1e3:g} mm/s, acceleration {Acc * 1e3:g} mm/s^2)")
            out[:, ch] = res.x * sc
        return out

    def _gram_of(self, full: bool, factor) -> np.ndarray:
        """The window's Gram matrix with its Tikhonov term (for OSQP's objective): a ``full`` window's
        without pins, the same every time (cached), else (the tail window, pinned rows) rebuilt from
        the window's factor."""
        if full:
            G = getattr(self, "_gram", None)
            if G is None:
                G = self._gram = self.Phi.T @ self.Phi
                G[np.diag_indices_from(G)] += self.lam
            return G
        return np.linalg.inv(_chol_to_inv(factor))

    def _bounded_joint(self, c, a, r, B2, Bs, e0, e1, e2, vref, aref, Vb, Ab, band, nJ, rhs, factor,
                       full, _dirs=None):
        """The bounds of :meth:`set_bounds` on every channel plus, on the rows the common-mode band
        covers, the components of ``set_common_accel_bound(components=...)``
        (:meth:`set_common_accel_bound`): one QP over all channels, which those components couple.
        A component the reference itself exceeds is relaxed to the reference's value.  Falls back
        to the channels' own bounds where the committed past leaves no room.  The components are
        taken along the command's own direction, which the solution changes: where the solution
        breaks them along its new direction, one more solve with those directions (``_dirs``)."""
        import osqp
        import scipy.sparse as sp

        D = self.bounds[0]
        C = self.C
        ra = np.nonzero(np.isfinite(band[0][r]))[0]  # constraint rows the band covers
        b0, b1, b2 = np.split(Bs @ c, 3)  # (Bs: B0, B1, B2 stacked, sparse)
        val, vel, acc = b0 + e0, b1 + e1 + vref, b2 + e2 + aref
        # the components along and across the command's own direction (the unbounded solution's):
        # the firmware caps each written segment by its direction, and where the command
        # pre-actuates a z move it turns steep while the reference still runs flat (a layer change
        # without a retraction: up to 1.5 ms late on cube_prusa with other_delta's max_z_accel)
        dv, da = (vel, acc) if _dirs is None else _dirs
        M, L = self.comp_fn(self.cpos[a + r[ra]], dv[ra], da[ra])  # (R', K, C), (R', K)
        ref_k = np.einsum("rkc,rc->rk", M, aref[ra])
        now_k = np.einsum("rkc,rc->rk", M, acc[ra])
        Lb = np.maximum(L, np.abs(ref_k) * 1.0001)
        box_bad = np.any(np.abs(val) > D) or np.any(np.abs(vel) > Vb) or np.any(np.abs(acc) > Ab)
        if not box_bad and not np.any(np.abs(now_k) > Lb):
            return c
        self.qp_windows += 1
        sc = 1e-4
        g = rhs().reshape(nJ, -1)
        # per channel: value, velocity, acceleration rows (the same in every window of this shape);
        # then the components, coupling the channels: row (k, r) of channel ch is M[r, k, ch] B2[r]
        akey = (nJ, len(r), C)
        A_box = self._abox_cache.get(akey)
        if A_box is None:
            A_box = self._abox_cache[akey] = sp.kron(sp.identity(C, format="csr"), Bs, format="csr")
        B2a = B2[ra]
        rr, jj = np.nonzero(B2a)  # (its pattern on the band's rows, row-major)
        bv = B2a[rr, jj]
        K_, R_ = M.shape[1], len(ra)
        kk, cc = np.meshgrid(np.arange(K_), np.arange(C), indexing="ij")  # (K, C) blocks
        A_cmp = sp.csr_matrix(((M[rr][:, kk, cc] * bv[:, None, None]).transpose(1, 2, 0).reshape(-1),
                               (((kk * R_)[:, :, None] + rr[None, None, :]).reshape(-1),
                                ((cc * nJ)[:, :, None] + jj[None, None, :]).reshape(-1))),
                              shape=(K_ * R_, C * nJ))
        lo_box = np.concatenate([np.concatenate([-D - e0[:, ch], -Vb[:, ch] - vref[:, ch] - e1[:, ch],
                                                 -Ab[:, ch] - aref[:, ch] - e2[:, ch]]) for ch in range(C)])
        hi_box = np.concatenate([np.concatenate([D - e0[:, ch], Vb[:, ch] - vref[:, ch] - e1[:, ch],
                                                 Ab[:, ch] - aref[:, ch] - e2[:, ch]]) for ch in range(C)])
        base_k = np.einsum("rkc,rc->rk", M, aref[ra] + e2[ra])  # the components without the new bases
        lo_c = (-Lb - base_k).T.reshape(-1)
        hi_c = (Lb - base_k).T.reshape(-1)
        A_raw = sp.vstack([A_box, A_cmp], format="csr")
        nb = A_box.shape[0]

        g_solve = partial(cho_solve, factor, check_finite=False)
        c_free = g_solve(g).T.reshape(-1)  # the unconstrained minimiser, channel-major
        osqp_parts: list = []

        def osqp_problem():
            """OSQP's scaled problem (coefficients in units of ``sc``, the objective normalised, every
            constraint row to unit size), built only when the exact solve gives up."""
            if not osqp_parts:
                G = self._gram_of(full, factor)
                gn = float(np.mean(np.diag(G))) * sc * sc
                A = A_raw.tocsc() * sc
                rn = np.maximum(np.abs(A).max(axis=1).toarray().ravel(), 1e-300)
                A = sp.csr_matrix(sp.diags(1.0 / rn) @ A)
                P = sp.kron(sp.identity(C, format="csc"), sp.csc_matrix(G * sc * sc / gn), format="csc")
                osqp_parts.extend([A, rn, P, -(g.T.reshape(-1)) * sc / gn, c.T.reshape(-1) / sc])
            return osqp_parts

        def solve(lo, hi, rows=slice(None)):
            cv = active_set_qp(c_free, A_raw[rows], lo[rows], hi[rows], g_solve, nJ, C)
            if cv is not None:
                self.qp_exact += 1
                return cv / sc
            A, rn, P, q, x0 = osqp_problem()
            solver = osqp.OSQP()
            solver.setup(P=sp.triu(P, format="csc"), q=q, A=sp.csc_matrix(A[rows]), l=lo[rows] / rn[rows],
                         u=hi[rows] / rn[rows], verbose=False, warm_starting=True, eps_abs=1e-5, eps_rel=1e-5,
                         max_iter=4000, polishing=False)
            solver.warm_start(x=x0)
            res = osqp_solve(solver)
            ok = res.info.status in ("solved", "solved inaccurate", "maximum iterations reached")
            return res.x if ok and res.x is not None and np.all(np.isfinite(res.x)) else None

        lo_all, hi_all = np.concatenate([lo_box, lo_c]), np.concatenate([hi_box, hi_c])
        x = None
        if not box_bad:  # the channels' own bounds are rarely near: first without them (a smaller problem)
            x = solve(lo_all, hi_all, slice(nb, None))
            if x is not None:
                ab = A_raw[:nb] @ (x * sc)
                if np.any(ab < lo_box - 1e-9 * np.abs(lo_box)) or np.any(ab > hi_box + 1e-9 * np.abs(hi_box)):
                    x = None
        if x is None:
            x = solve(lo_all, hi_all)
        if x is None:  # the committed past leaves no room for the components: the channels' bounds
            self.band_dropped += 1
            x = solve(np.concatenate([lo_box, np.full(len(lo_c), -1e30)]),
                      np.concatenate([hi_box, np.full(len(hi_c), 1e30)]))
        if x is None:
            raise SolverError(f"OSQP could not keep the command within its bounds in the window starting at "
                              f"t = {self.w0 * self.basis.dt_s:.3f} s")
        out = (x * sc).reshape(C, nJ).T
        if _dirs is None:
            _, b1, b2 = np.split(Bs @ out, 3)
            acc2, vel2 = b2 + e2 + aref, b1 + e1 + vref
            M2, L2 = self.comp_fn(self.cpos[a + r[ra]], vel2[ra], acc2[ra])
            Lb2 = np.maximum(L2, np.abs(np.einsum("rkc,rc->rk", M2, aref[ra])) * 1.0001)
            if np.any(np.abs(np.einsum("rkc,rc->rk", M2, acc2[ra])) > Lb2 * 1.02):
                self.qp_redirected += 1
                return self._bounded_joint(out, a, r, B2, Bs, e0, e1, e2, vref, aref, Vb, Ab, band, nJ, rhs,
                                           factor, full, _dirs=(vel2, acc2))
        return out

    def _values(self, upto: int) -> np.ndarray:
        """Spline values for samples [done, upto) (all their bases committed)."""
        m, sup = self.m, self.basis.support
        n = upto - self.done
        out = np.zeros((max(n, 0), self.coef.shape[1]))
        if n <= 0:
            return out
        j_lo = max(self.cj0, (self.done - sup) // m)
        j_hi = min(self.cj0 + len(self.coef), -(-upto // m))
        if j_hi > j_lo:
            s_lo = j_lo * m
            up = np.zeros((upto - s_lo + m, self.coef.shape[1]))
            up[: (j_hi - j_lo) * m: m] = self.coef[j_lo - self.cj0:j_hi - self.cj0]
            for i in range(up.shape[1]):
                y = np.convolve(up[:, i], self.shape)[self.done - s_lo:upto - s_lo]
                out[: len(y), i] = y
        self.done = upto
        # forget coefficients no sample will need again
        keep_j = max(self.cj0, (upto - sup) // m)
        self.coef = self.coef[keep_j - self.cj0:]
        self.cj0 = keep_j
        return out

    def feed(self, target: np.ndarray, pin: np.ndarray | None = None, ref_vel=None, ref_acc=None,
             common_acc=None, poses=None) -> np.ndarray:
        """Add target rows (and optionally a mask of rows where the spline must vanish, the
        reference's velocity and acceleration per channel for :meth:`set_bounds`, m/s and m/s^2,
        and its common-mode acceleration (rows,) and nozzle positions (rows, 3) for
        :meth:`set_common_accel_bound`, m/s^2 and m); returns spline values of samples that became
        final (in order)."""
        target = np.asarray(target, float).reshape(-1, self.n_out * self.C)
        self.tgt = np.concatenate([self.tgt, target])
        self.pin = np.concatenate([self.pin, np.zeros(len(target), bool) if pin is None else np.asarray(pin, bool)])
        z = np.zeros((len(target), self.C))
        rv = z if ref_vel is None else np.asarray(ref_vel, float).reshape(-1, self.C)
        ra = z if ref_acc is None else np.asarray(ref_acc, float).reshape(-1, self.C)
        self.rvel = np.concatenate([self.rvel, rv])
        self.racc = np.concatenate([self.racc, ra])
        ca = np.zeros(len(target)) if common_acc is None else np.asarray(common_acc, float).reshape(-1)
        self.cacc = np.concatenate([self.cacc, ca])
        if poses is not None:
            self.cpos = np.concatenate([self.cpos, np.asarray(poses, float).reshape(-1, 3)])
        end = self.off + len(self.tgt)
        while self.w0 + self.W <= end:
            self._solve_window(self.W, final=False)
        vals = self._values(self.w0)
        self._trim()
        return vals

    def finish(self) -> np.ndarray:
        """Solve the remaining windows and return the last spline values."""
        end = self.off + len(self.tgt)
        while self.w0 < end:
            rows = min(self.W, end - self.w0)
            self._solve_window(rows, final=rows < self.W or self.w0 + self.W >= end)
        vals = self._values(end)
        return vals

    def _trim(self) -> None:
        cut = self.w0 - self.off
        if cut > 4 * self.W:
            self.tgt = self.tgt[cut:]
            self.pred = self.pred[cut:]
            self.pin = self.pin[cut:]
            self.rvel = self.rvel[cut:]
            self.racc = self.racc[cut:]
            self.cacc = self.cacc[cut:]
            if len(self.cpos):
                self.cpos = self.cpos[cut:]
            self.off += cut


def _chol_to_inv(factor) -> np.ndarray:
    """Inverse of the matrix a ``cho_factor`` result factorises (for rebuilding the Gram)."""
    n = factor[0].shape[0]
    return cho_solve(factor, np.eye(n), check_finite=False)
