"""Streaming inverse: the default two-stage compensation in bounded memory.

:class:`StreamingInverse` chains the mechanics stage and the three drive stages, each a windowed
solver of :mod:`.stream` (:class:`~ffcomp.compensate.stream.FbsStream`, per mode where the towers
are alike: :mod:`.modal_fbs`): reference samples in, compensated carriage commands out, a few
hundred milliseconds behind.

Only the ``lpv`` and ``lti-centre`` methods stream (their normal equations are identical in every
window); the other variants of :mod:`.inverse` hold the trajectory in memory and exist to measure
the accuracy/time trade-off.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from ..model.lpv import LpvModel
from .bspline import UniformBasis
from .differ import SplineDerivatives
from .inverse import InverseConfig, LtiStream, _round_to, inertia_split, inverse_dynamics_force, mech_target
from .kernels import (
    DriveFilter,
    drive_kernel,
    drive_tail_samples,
    mech_arrays,
    mech_kernels,
    mech_tail_samples,
)
from .modal_fbs import ModalFbs, modal_split
from .nozzle_limits import nozzle_components, nozzle_z_accel
from .stream import FbsStream

__all__ = ["StreamingInverse"]


class StreamingInverse:
    """Reference samples in, compensated carriage commands out, in bounded memory.

    Feed chunks of the reference (carriage positions, their derivatives and the nozzle poses) with
    :meth:`push`; each call returns the commands of the samples that became final (a few hundred
    milliseconds behind the input); :meth:`finish` returns the rest.  The printer is taken to be at
    rest at the first sample before the stream starts (``cfg.pre_s`` of rest are added so the
    command can pre-actuate) and after it ends.
    """

    def __init__(self, model: LpvModel, dt_s: float, cfg: InverseConfig = InverseConfig(),
                 keep_padding: bool = False):
        if cfg.method not in ("lpv", "lti-centre"):
            raise ValueError(f"method {cfg.method!r} does not stream; use 'lpv' or 'lti-centre'")
        self.model, self.dt, self.cfg = model, dt_s, cfg
        self.keep_padding = keep_padding
        self.basis = UniformBasis(cfg.degree, cfg.knot_samples, dt_s)
        self.started = False
        self.n_in = 0  # reference samples received (without the rest padding)
        self.n_out = 0  # stream rows produced (with the padding)
        self._returned = 0  # commands returned to the caller
        self._pre_out = None
        self._diff = None  # the reference's derivatives from its samples (cfg.derivatives == "samples")

    def _start(self, q0, x0):
        m, cfg, dt = self.basis.m, self.cfg, self.dt
        self.q0 = q0.copy()
        if cfg.derivatives == "samples":
            self._diff = SplineDerivatives(q0, dt)
        self.x_centre = np.array([0.0, 0.0, x0[2]])
        mats0 = self.model.matrices(self.x_centre[None], check=False)
        A0, _ = mech_arrays(mats0)
        self.A0 = A0[0]
        self.Bf = np.zeros((6, 3))
        self.Bf[3:] = np.linalg.inv(mats0.M[0])
        self._lti = (LtiStream(self.A0, self.Bf, dt), LtiStream(self.A0, self.Bf, dt))
        self._M_prev = None
        self.Bk0 = mats0.B_k[0].copy()
        L = self.basis.support + mech_tail_samples(mats0, dt, cfg.kernel_tol)
        k0 = mech_kernels(mats0, self.basis, L, cfg.substeps)[0]
        win = _round_to(int(round(cfg.window_s / dt)), m)
        adv = _round_to(int(round(cfg.advance_s / dt)), m)
        split = modal_split(k0)  # towers alike: one solve per mode (modal_fbs), else coupled
        self.mech = (ModalFbs(*split, self.basis, win, adv, cfg.reg, cfg.row_stride) if split is not None
                     else FbsStream(k0, self.basis, win, adv, cfg.reg, cfg.row_stride))
        dwin = _round_to(int(round(cfg.drive_window_s / dt)), m)
        dadv = _round_to(int(round(cfg.drive_advance_s / dt)), m)
        self.drive, self.dfilt = [], []
        params = [(mats0.d0[i], mats0.d1[i], mats0.d2[i], mats0.lag_s[i], mats0.delay_s[i]) for i in range(3)]
        self.shared_drive = all(p == params[0] for p in params)  # one solve for the three towers
        for i in range(1 if self.shared_drive else 3):
            d0, d1, d2, lag, dly = params[i]
            Lb = self.basis.support + drive_tail_samples(d0, d2, lag, dt)
            kb = drive_kernel(d0, d1, d2, lag, dly, self.basis, Lb)
            self.drive.append(FbsStream(kb[None, :, None], self.basis, dwin, dadv, cfg.reg,
                                        channels=3 if self.shared_drive else 1))
        for i in range(3):
            self.dfilt.append(DriveFilter(*params[i], dt))
        self.zbound = cfg.bounds is not None and cfg.z_accel_bound is not None
        if cfg.bounds is not None:
            for d in self.drive:
                d.set_bounds(*cfg.bounds)
                if self.zbound:
                    d.set_common_accel_bound(cfg.z_accel_bound, cfg.z_bound_share,
                                             int(round(cfg.z_bound_reach_s / dt)),
                                             partial(nozzle_components, self.model.geometry,
                                                     z_limit=cfg.z_accel_bound))
        # reference carriage velocity and acceleration of rows in qbuf_u, the nozzle's z acceleration
        # and position
        self.dbuf = np.zeros((0, 10))
        # reference rows waiting for their delta (stage 1) and their eps (stage 2)
        self.qbuf_u = np.zeros((0, 3))  # q_ref rows not yet through stage 1
        self.pinbuf = np.zeros(0, bool)  # their hold flags
        self.qbuf_c = np.zeros((0, 3))  # q_ref rows not yet through stage 2
        self.started = True
        n_pre = _round_to(int(round(cfg.pre_s / dt)), m)
        self.n_pre = n_pre
        n_post = int(round(cfg.post_s / dt))
        self.n_post = n_post
        z = np.zeros((n_pre, 3))
        if self._diff is None:
            self._pre_out = self._push(np.repeat(q0[None], n_pre, 0), z, z, np.repeat(x0[None], n_pre, 0))
        else:
            self._pre_out = self._push_differenced(np.repeat(q0[None], n_pre, 0), np.repeat(x0[None], n_pre, 0),
                                                   np.zeros(n_pre, bool))

    def _push(self, q, qd, qdd, X, pin=None) -> np.ndarray:
        """Stage 1 on new rows (reference positions, velocities, accelerations, poses, hold flags)."""
        cfg = self.cfg
        self.pinbuf = np.concatenate([self.pinbuf, np.zeros(len(q), bool) if pin is None else pin])
        zacc = nozzle_z_accel(self.model.geometry, X, qdd) if self.zbound else np.zeros(len(q))
        self.dbuf = np.concatenate([self.dbuf, np.hstack([qd, qdd, zacc[:, None], X])])
        Xm = X.copy()
        if cfg.method == "lti-centre":
            Xm[:, :2] = 0.0
        mats = self.model.matrices(Xm, check=False)
        g = inverse_dynamics_force(self.model, mats, q, qd, qdd, Xm if cfg.method == "lti-centre" else X, self.q0)
        sc = self.Bk0 / mats.B_k  # the drive pushes with the pose's belt stiffness (see inverse.py)
        h, dh = inertia_split(mats, qd, qdd, self.dt, self._M_prev)
        self._M_prev = mats.M[-1].copy()
        # H0[g] (inertia as the derivative of H0[h]), continuing the modal states across chunks
        tgt = mech_target(self.A0, self.Bf, g * sc, h * sc, dh * sc, self.dt, lti=self._lti)
        return self._stage2(q, self.mech.feed(tgt))

    def _stage2(self, q, delta) -> np.ndarray:
        self.qbuf_u = np.concatenate([self.qbuf_u, q])
        n = len(delta)
        qn, self.qbuf_u = self.qbuf_u[:n], self.qbuf_u[n:]
        pn, self.pinbuf = self.pinbuf[:n], self.pinbuf[n:]
        dn, self.dbuf = self.dbuf[:n], self.dbuf[n:]
        return self._emit(qn, self._drive_stage(qn, qn + delta, pn, dn, final=False))

    def _drive_stage(self, qn, u, pn, dn, final: bool) -> list:
        """Stage 2 on rows whose drive positions are known: returns the corrections of each tower."""
        tgt = np.stack([u[:, i] - (self.dfilt[i](qn[:, i] - self.q0[i]) + self.q0[i]) for i in range(3)], 1)
        if self.shared_drive:
            e = self.drive[0].feed(tgt, pn, dn[:, :3], dn[:, 3:6], dn[:, 6], dn[:, 7:10])
            if final:
                e = np.concatenate([e, self.drive[0].finish()])
            return [e[:, i] for i in range(3)]
        eps = []
        for i in range(3):
            e = self.drive[i].feed(tgt[:, i:i + 1], pn, dn[:, i:i + 1], dn[:, 3 + i:4 + i], dn[:, 6])[:, 0]
            if final:
                e = np.concatenate([e, self.drive[i].finish()[:, 0]])
            eps.append(e)
        return eps

    def _emit(self, qn, eps) -> np.ndarray:
        self.qbuf_c = np.concatenate([self.qbuf_c, qn])
        n = min(len(e) for e in eps)
        self._eps_left = getattr(self, "_eps_left", [np.zeros(0)] * 3)
        allv = [np.concatenate([self._eps_left[i], eps[i]]) for i in range(3)]
        n = min(len(v) for v in allv)
        out = self.qbuf_c[:n] + np.stack([v[:n] for v in allv], 1)
        self.qbuf_c = self.qbuf_c[n:]
        self._eps_left = [v[n:] for v in allv]
        # drop the rest padding at the start (unless the caller emits it: then the whole timeline
        # runs n_pre samples late, which leaves room to pre-actuate the first move)
        skip = 0 if self.keep_padding else min(len(out), max(0, self.n_pre - self.n_out))
        self.n_out += len(out)
        return out[skip:]

    def push(self, q_m, xyz_m, qd=None, qdd=None, hold=None) -> np.ndarray:
        """Add reference samples (N, 3); returns finished commands (M, 3), M <= N overall.

        ``hold`` (N,) marks samples where the command must equal the reference (the planned nozzle
        stands still during an extruder-only move or a dwell, and a G-code file cannot move it then).
        """
        q_m = np.asarray(q_m, float)
        xyz_m = np.asarray(xyz_m, float)
        if len(q_m) == 0:
            return np.zeros((0, 3))
        if not self.started:
            self._start(q_m[0], xyz_m[0])
        if self._diff is None and (qd is None or qdd is None):  # derivatives="given"
            raise ValueError("push needs the carriage velocities and accelerations with derivatives='given' "
                             "(see ffcomp.kinematics.carriage_rates)")
        self.n_in += len(q_m)
        self._last = (q_m[-1].copy(), xyz_m[-1].copy())
        pin = np.zeros(len(q_m), bool) if hold is None else np.asarray(hold, bool)
        if self._diff is None:
            out = self._push(q_m, np.asarray(qd, float), np.asarray(qdd, float), xyz_m, pin)
        else:
            out = self._push_differenced(q_m, xyz_m, pin)
        if self._pre_out is not None:
            out = np.concatenate([self._pre_out, out])
            self._pre_out = None
        self._returned += len(out)
        return out

    def _push_differenced(self, q, X, pin) -> np.ndarray:
        """Stage 1 with the reference's derivatives taken from the samples (see :mod:`.differ`), a
        fixed number of samples late: the firmware moves through the samples, velocity jumps at
        corners included, which a planner's exact derivatives leave out (the command's bounds then
        compare with the samples' own velocity and acceleration too)."""
        qq, qd, qdd, XX, pp = self._diff.push(q, X, pin)
        return self._push(qq, qd, qdd, XX, pp) if len(qq) else np.zeros((0, 3))

    def _flush_differenced(self) -> np.ndarray:
        qq, qd, qdd, XX, pp = self._diff.finish()
        return self._push(qq, qd, qdd, XX, pp) if len(qq) else np.zeros((0, 3))

    def finish(self) -> np.ndarray:
        """Flush: rest padding after the end, the remaining windows; returns the last commands."""
        if not self.started:
            return np.zeros((0, 3))
        q_last, x_last = self._last
        n_post = int(round(self.cfg.post_s / self.dt))
        z = np.zeros((n_post, 3))
        if self._diff is None:
            parts = [self._push(np.repeat(q_last[None], n_post, 0), z, z, np.repeat(x_last[None], n_post, 0))]
        else:
            parts = [self._push_differenced(np.repeat(q_last[None], n_post, 0), np.repeat(x_last[None], n_post, 0),
                                            np.zeros(n_post, bool)), self._flush_differenced()]
        delta = self.mech.finish()
        parts.append(self._stage2_final(delta))
        out = np.concatenate(parts)
        if self.keep_padding:
            return out[: max(0, self.n_pre + self.n_in + self.n_post - self._returned)]
        return out[: max(0, self.n_in - self._returned)]

    def _stage2_final(self, delta) -> np.ndarray:
        n = len(delta)
        qn, self.qbuf_u = self.qbuf_u[:n], self.qbuf_u[n:]
        pn, self.pinbuf = self.pinbuf[:n], self.pinbuf[n:]
        dn, self.dbuf = self.dbuf[:n], self.dbuf[n:]
        return self._emit(qn, self._drive_stage(qn, qn + delta, pn, dn, final=True))
