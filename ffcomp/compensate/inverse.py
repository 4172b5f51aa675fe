"""The feedforward inverse: reference carriage trajectories -> compensated carriage commands.

Two filtered-B-spline stages, split where the model splits exactly (see :mod:`.kernels`):

1. **mechanics** (coupled 3x3, position dependent): find drive positions ``u`` (quintic B-splines)
   such that ``G_m(X) u`` tracks the reference carriage positions.  The filtered basis comes from
   the model frozen at each basis function's pose (``lpv``, the efficient LPV scheme), from the
   exact time-varying model along the path (``lpv-exact``), or from the model frozen at the bed
   centre (``lti-centre``);
2. **drive** (per tower, LTI, lightly damped, right-half-plane zero): find commands ``q_d``
   (quintic B-splines) such that ``F(s) q_d`` tracks ``u``.  LTI, so the windows share one
   factorisation.

Both stages solve overlapping windows in sequence (limited preview), so the cost grows linearly
with the print and memory stays bounded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..linalg3 import matvec3, rmatvec3
from ..model.lpv import LpvModel, PoseMatrices
from .bspline import UniformBasis
from .fbs import FbsConfig, fbs_solve
from .kernels import (
    DriveFilter,
    drive_kernel,
    drive_tail_samples,
    ltv_mech_response,
    mech_arrays,
    mech_kernels,
    mech_tail_samples,
    modal_foh,
)
from .ltv import simulate_lti, simulate_piecewise

__all__ = ["METHODS", "FINE", "InverseConfig", "InverseResult", "invert", "mech_tail_for", "inertia_split",
           "mech_target", "LtiStream"]

#: inverse variants: how the mechanics stage sees the position-dependent model
METHODS = {
    "lpv": "exact LPV inverse dynamics along the path, projected on the B-spline by an FBS "
           "least squares weighted with the centre model (fast, default)",
    "lpv-basis": "filtered basis through the model frozen at each basis function's pose "
                 "(the efficient LPV FBS of the literature)",
    "lpv-exact": "filtered basis through the time-varying model along the path (exact LPV FBS, slow)",
    "window-centre": "model frozen at the centre pose of each committed block (piecewise LTI)",
    "lti-centre": "model frozen at the bed centre (LTI FBS)",
}


@dataclass(frozen=True)
class InverseConfig:
    """Settings of the inverse (documented defaults).

    method : {"lpv", "lpv-exact", "lti-centre"}
    degree : B-spline degree (5: quintic)
    knot_samples : samples per knot interval (5 at 1 kHz = 5 ms)
    window_s, advance_s : window length and committed advance of the mechanics stage, s
    drive_window_s, drive_advance_s : the same for the drive stage, s
    reg : relative Tikhonov weight towards the reference
    task_weighted : weigh the mechanics residual by J so the error is measured at the nozzle
    pre_s, post_s : rest padding before (room to pre-actuate) and after (settling), s
    kernel_stride : compute frozen-pose kernels every this many bases, interpolate in between
    substeps : integration substeps per sample inside a basis' support
    row_stride : evaluate the mechanics residual on every this-many-th sample
    kernel_tol : truncate kernels when the slowest mode has decayed to this fraction
    bounds : (deviation m, carriage velocity m/s, carriage acceleration m/s^2) of the command, enforced
        with OSQP where the least-squares solution breaks them (streaming inverse only); None: unbounded
    z_accel_bound : the firmware's cap on the nozzle's z acceleration, m/s^2 (Klipper's delta caps
        every move's acceleration at ``max_z_accel * d/|dz|``): where the reference's own z
        acceleration comes within ``z_bound_share`` of it (and ``z_bound_reach_s`` around), the
        command's z acceleration is kept within it too (streaming inverse, with ``bounds``; see
        :meth:`~ffcomp.compensate.stream.FbsStream.set_common_accel_bound`); None: no such bound
    z_bound_share : share of ``z_accel_bound`` the reference's z acceleration must reach for the bound
        to apply (elsewhere the compensation keeps its freedom)
    z_bound_reach_s : how far before and after such samples the bound applies, s (the command
        pre-actuates a move and settles after it)
    derivatives : {"samples", "given"}: the reference velocity and acceleration in the inverse
        dynamics: those of the cubic interpolant of the samples (default, :mod:`.differ`: the
        firmware moves through the samples, so corners' velocity jumps are part of the motion) or
        the caller's (a planner's exact derivatives, which leave the jumps out)
    """

    method: str = "lpv"
    degree: int = 5
    knot_samples: int = 4
    window_s: float = 0.80
    advance_s: float = 0.60
    drive_window_s: float = 1.00
    drive_advance_s: float = 0.70
    reg: float = 1e-7
    task_weighted: bool = True
    pre_s: float = 0.05
    post_s: float = 0.30
    kernel_stride: int = 4
    substeps: int = 2
    row_stride: int = 2
    kernel_tol: float = 1e-3
    bounds: tuple | None = None
    derivatives: str = "samples"
    z_accel_bound: float | None = None
    z_bound_share: float = 0.3
    z_bound_reach_s: float = 0.04

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {sorted(METHODS)}, got {self.method!r}")
        if self.derivatives not in ("samples", "given"):
            raise ValueError(f"derivatives must be 'samples' or 'given', got {self.derivatives!r}")


@dataclass(frozen=True)
class InverseResult:
    """Compensated commands on the reference's sample grid (SI).

    q_cmd : (N, 3) carriage commands, m;  u : (N, 3) intended drive positions, m;
    q_pred_mech : (N, 3) the mechanics stage's prediction of the carriages for ``u``, m.
    """

    q_cmd: np.ndarray
    u: np.ndarray
    q_pred_mech: np.ndarray


#: the accuracy setting: cubic spline, a knot per sample.  1.0-1.6x the physical limit on the bench
#: (the default's quintic 4 ms spline: 1.3-4.3x, docs/limit.md), but its commands jerk: carriage accelerations
#: of ~100 m/s^2 at square corners and ~600 m/s^2 on a 250 Hz polygon (the default: ~10 m/s^2), so
#: the profile's acceleration bound binds and the streaming inverse spends its time in OSQP.
FINE = InverseConfig(degree=3, knot_samples=1)


def _round_to(n: int, m: int) -> int:
    return max(m, int(round(n / m)) * m)


def mech_tail_for(model: LpvModel, xyz_m: np.ndarray, dt_s: float, tol: float = 1e-3) -> int:
    """Kernel tail of the mechanics: slowest decay over a subsample of the path's poses."""
    idx = np.linspace(0, len(xyz_m) - 1, min(len(xyz_m), 64)).astype(int)
    return mech_tail_samples(model.matrices(xyz_m[idx], check=False), dt_s, tol)


def _derivatives(q: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and acceleration of a sampled trajectory at rest before and after its ends: those
    of its cubic interpolant (:func:`~ffcomp.compensate.differ.spline_derivatives`)."""
    from .differ import spline_derivatives

    return spline_derivatives(q, dt_s)


def reference_forcing(mats: PoseMatrices, q, qd, qdd) -> np.ndarray:
    """Force the mechanics feel when the drives simply follow the reference (``u = q_ref``).

    With ``u = q_ref + delta`` and ``q = q_ref + e``:
    ``M e'' + C e' + K e = B_c delta' + B_k delta + f_ref`` with
    ``f_ref = B_c q_ref' + B_k q_ref - (M q_ref'' + C q_ref' + K q_ref)``, shape (N, 3), N.
    """
    f = mats.B_c * qd + mats.B_k * q
    f -= matvec3(mats.M, qdd) + matvec3(mats.C, qd) + matvec3(mats.K, q)
    return f


def force_response(mats_seg: PoseMatrices, f: np.ndarray, dt_s: float, seg: int) -> np.ndarray:
    """Carriage deviation ``e`` (N, 3) of the mechanics driven by force ``f`` (N, 3), piecewise-frozen LPV."""
    A, _ = mech_arrays(mats_seg)
    Bf = np.zeros((A.shape[0], 6, 3))
    Bf[:, 3:, :] = np.linalg.inv(mats_seg.M)
    x, _ = simulate_piecewise(A, Bf, f, dt_s, seg)
    return x[:, :3]


def invert(model: LpvModel, q_ref_m: np.ndarray, xyz_ref_m: np.ndarray, dt_s: float,
           cfg: InverseConfig = InverseConfig(), qd_ref=None, qdd_ref=None) -> InverseResult:
    """Compensate one trajectory held in memory.

    The command is the reference plus a quintic B-spline correction, found in two FBS stages
    (mechanics, then drive), both in deviation form so the position-dependent model only ever
    acts on small signals.

    Parameters
    ----------
    q_ref_m, xyz_ref_m : ndarray, shape (N, 3)
        Reference carriage and nozzle positions on a uniform grid of step ``dt_s``; the printer is
        assumed at rest at the first sample before the trajectory and after the last one.
    qd_ref, qdd_ref : ndarray, shape (N, 3), optional
        Exact carriage velocities and accelerations (central differences otherwise).
    """
    q_ref_m = np.asarray(q_ref_m, float)
    xyz_ref_m = np.asarray(xyz_ref_m, float)
    N = len(q_ref_m)
    basis = UniformBasis(cfg.degree, cfg.knot_samples, dt_s)
    m = basis.m
    n_pre = _round_to(int(round(cfg.pre_s / dt_s)), m)
    n_post = int(round(cfg.post_s / dt_s))
    pad = lambda a: np.concatenate([np.repeat(a[:1], n_pre, 0), a, np.repeat(a[-1:], n_post, 0)])  # noqa: E731
    q, X = pad(q_ref_m), pad(xyz_ref_m)
    if qd_ref is None or qdd_ref is None or cfg.derivatives == "samples":
        qd, qdd = _derivatives(q, dt_s)
    else:
        z = lambda a: np.concatenate([np.zeros((n_pre, 3)), a, np.zeros((n_post, 3))])  # noqa: E731
        qd, qdd = z(np.asarray(qd_ref, float)), z(np.asarray(qdd_ref, float))
    Np = len(q)
    Xm = X.copy()
    if cfg.method == "lti-centre":
        Xm[:, :2] = 0.0
    mats_all = model.matrices(Xm[:1], check=False)

    # ---- stage 1: mechanics (coupled, LPV) -> drive positions u = q_ref + delta
    win = _round_to(int(round(cfg.window_s / dt_s)), m)
    adv = _round_to(int(round(cfg.advance_s / dt_s)), m)
    if cfg.method in ("lpv", "lti-centre"):
        coef_u, pred_e = _mech_stage_fast(model, q, qd, qdd, X, Xm, basis, win, adv, cfg)
    else:
        coef_u, pred_e = _mech_stage_frozen(model, q, qd, qdd, X, basis, win, adv, cfg)
    delta = basis.evaluate(coef_u, Np)
    u = q + delta

    # ---- stage 2: drive (per tower, LTI) -> commands q_d = q_ref + eps
    dwin = _round_to(int(round(cfg.drive_window_s / dt_s)), m)
    dadv = _round_to(int(round(cfg.drive_advance_s / dt_s)), m)
    q_cmd = np.empty_like(q)
    for i in range(3):
        d0, d1, d2 = mats_all.d0[i], mats_all.d1[i], mats_all.d2[i]
        lag, dly = mats_all.lag_s[i], mats_all.delay_s[i]
        L_b = basis.support + drive_tail_samples(d0, d2, lag, dt_s)
        k = drive_kernel(d0, d1, d2, lag, dly, basis, L_b)
        u_ref = DriveFilter(d0, d1, d2, lag, dly, dt_s)(q[:, i] - q[0, i]) + q[0, i]

        def dk(j0, j1, k=k):
            return np.broadcast_to(k[None, None, :, None], (j1 - j0, 1, len(k), 1))

        target = (u[:, i] - u_ref)[:, None]
        coef_d, _ = fbs_solve(target, dk, L_b, FbsConfig(basis, dwin, dadv, cfg.reg, lti=True))
        q_cmd[:, i] = q[:, i] + basis.evaluate(coef_d[:, 0], Np)
    sl = slice(n_pre, n_pre + N)
    return InverseResult(q_cmd=q_cmd[sl], u=u[sl], q_pred_mech=(q + pred_e)[sl])


def inverse_dynamics_force(model: LpvModel, mats: PoseMatrices, q, qd, qdd, X, q_anchor=None) -> np.ndarray:
    """Drive-side force the exact inverse must add: ``B_c delta' + B_k delta = g`` with

    ``g = M q'' + C q' + K q - B_c q' - B_k q + m_nt J^T J_dot q'`` evaluated at every sample's
    pose (the last term is the nonlinear velocity coupling of Eq. 15), shape (N, 3), N.
    Positions are taken relative to ``q_anchor`` (the rest position the stream starts from), where
    every spring of the model is relaxed; for the paper's model ``K = diag(B_k)`` and it cancels.
    """
    from ..kinematics import velocity_product

    qa = q if q_anchor is None else q - q_anchor
    g = -reference_forcing(mats, qa, qd, qdd)
    Jdqd = velocity_product(model.geometry, X, qd, q=mats.q_m, J=mats.J)
    g += model.m_nt * rmatvec3(mats.J, Jdqd)
    return g


def inertia_split(mats: PoseMatrices, qd: np.ndarray, qdd: np.ndarray, dt_s: float,
                  M_prev: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The inertial force ``M q''`` as the time derivative of a momentum-like ``h = M q'``.

    Returns ``h`` (N, 3) and ``dh ~ M q'' + M' q'`` (N, 3), ``M'`` by backward differences from
    ``M_prev`` (the sample before the first; default: the first's).  The mechanics' response to
    ``dh`` is then taken as the *velocity* of their response to ``h`` (exact for a linear-time-
    invariant weighting and ``h`` linear between samples): the sampled acceleration, which at a
    corner jumps from one sample to the next, never has to be interpolated.
    """
    M = mats.M
    Mp = np.concatenate([(M[:1] if M_prev is None else M_prev[None]), M[:-1]])
    h = matvec3(M, qd)
    dh = matvec3(M, qdd) + matvec3((M - Mp) / dt_s, qd)
    return h, dh


def mech_target(A0, Bf, g, h, dh, dt_s, lti=None):
    """``H0[g]`` with its inertial part through :func:`inertia_split`: ``H0[g - dh] + d/dt H0[h]``.

    ``lti`` is a pair of :class:`LtiStream` (streaming) or None (one signal in memory).
    Returns the carriage part (N, 3).
    """
    if lti is None:
        x1, _ = simulate_lti(A0, Bf, g - dh, dt_s)
        x2, _ = simulate_lti(A0, Bf, h, dt_s)
    else:
        x1, x2 = lti[0](g - dh), lti[1](h)
    return x1[:, :3] + x2[:, 3:6]


class LtiStream:
    """``simulate_lti`` of one system over consecutive chunks (modal state and last input carried)."""

    def __init__(self, A, B, dt_s):
        self.A, self.B, self.dt = A, B, dt_s
        self.foh = modal_foh(A[None], B[None], dt_s)
        self.z = None
        self.last = None

    def __call__(self, w: np.ndarray) -> np.ndarray:
        if self.z is None:
            x, self.z = simulate_lti(self.A, self.B, w, self.dt, foh=self.foh)
        else:
            x, self.z = simulate_lti(self.A, self.B, np.concatenate([self.last, w]), self.dt, z0=self.z, foh=self.foh)
            x = x[1:]
        self.last = w[-1:]
        return x


def _mech_stage_fast(model, q, qd, qdd, X, Xm, basis, win, adv, cfg):
    """Default mechanics stage: the exact LPV inverse, projected on the spline by an LTI-weighted FBS.

    Because ``delta*`` (with ``B_c delta*' + B_k delta* = g``) makes the LPV error vanish for any
    weighting, the weighting only shapes how the spline misses ``delta*``; the centre model does
    that well and its normal equations are the same in every window (factorised once).
    """
    mats = model.matrices(Xm, check=False)
    g = inverse_dynamics_force(model, mats, q, qd, qdd, Xm if cfg.method == "lti-centre" else X, q[0])
    x0 = Xm[:1].copy()
    x0[:, :2] = 0.0
    mats0 = model.matrices(x0, check=False)
    # the drive pushes with the belt stiffness of the pose, the weighting model with the centre's
    sc = mats0.B_k[0] / mats.B_k
    g = g * sc
    h, dh = inertia_split(mats, qd, qdd, basis.dt_s)
    A0, _ = mech_arrays(mats0)
    Bf = np.zeros((6, 3))
    Bf[3:] = np.linalg.inv(mats0.M[0])
    target = mech_target(A0[0], Bf, g, h * sc, dh * sc, basis.dt_s)  # H0[g]: what B delta must produce
    L = basis.support + mech_tail_samples(mats0, basis.dt_s, cfg.kernel_tol)
    k0 = mech_kernels(mats0, basis, L, cfg.substeps)[0]

    def kfn(j0, j1):
        return np.broadcast_to(k0[None], (j1 - j0,) + k0.shape)

    coef, pred = fbs_solve(target, kfn, L, FbsConfig(basis, win, adv, cfg.reg, lti=True, row_stride=cfg.row_stride))
    return coef, pred - target


def _mech_stage_frozen(model, q, qd, qdd, X, basis, win, adv, cfg):
    """Mechanics stage with filtered bases from a frozen (per basis / per block) or exact LTV model."""
    m = basis.m
    Np = len(q)
    mats_all = model.matrices(X, check=False)
    f_ref = reference_forcing(mats_all, q - q[0], qd, qdd)
    if cfg.method == "window-centre":
        seg_pose = lambda idx: np.minimum((idx // adv) * adv + adv // 2, Np - 1)  # noqa: E731
    else:
        seg_pose = lambda idx: np.minimum(idx + m // 2, Np - 1)  # noqa: E731
    seg_idx = seg_pose(np.arange(-(-Np // m)) * m)
    e_ref = force_response(_take(mats_all, seg_idx), f_ref, basis.dt_s, m)
    L = basis.support + mech_tail_for(model, X, basis.dt_s, cfg.kernel_tol)
    if cfg.method == "lpv-exact":
        kfn = _ltv_kernel_fn(model, X, basis, L)
    else:
        Xk = X if cfg.method == "lpv-basis" else X[seg_pose(np.arange(Np))]
        kfn = StridedKernels(model, Xk, basis, L, cfg.kernel_stride if cfg.method == "lpv-basis" else 1,
                             cfg.substeps)
    row_w = mats_all.J if cfg.task_weighted else None
    coef, pred_e = fbs_solve(-e_ref, kfn, L, FbsConfig(basis, win, adv, cfg.reg, row_stride=cfg.row_stride),
                             row_weights=row_w)
    return coef, e_ref + pred_e


class StridedKernels:
    """Frozen-pose kernels at every ``stride``-th basis, linearly interpolated in between.

    Basis ``j``'s pose is the reference pose at the basis' centre.  Kernels at the grid bases are
    computed once (in batches) and kept while later windows still need them.
    """

    def __init__(self, model: LpvModel, X: np.ndarray, basis: UniformBasis, L: int, stride: int,
                 substeps: int):
        self.model, self.X, self.basis, self.L = model, X, basis, L
        self.stride, self.substeps = max(1, int(stride)), substeps
        self.cache: dict[int, np.ndarray] = {}

    def _grid(self, gs: np.ndarray) -> np.ndarray:
        need = [g for g in gs if g not in self.cache]
        if need:
            m = self.basis.m
            idx = np.clip(np.asarray(need) * m + self.basis.greville_offset(), 0, len(self.X) - 1)
            K = mech_kernels(self.model.matrices(self.X[idx], check=False), self.basis, self.L, self.substeps)
            for g, k in zip(need, K):
                self.cache[g] = k
        lo = gs[0]
        for g in [g for g in self.cache if g < lo - 2 * self.stride]:
            del self.cache[g]
        return np.stack([self.cache[g] for g in gs])

    def __call__(self, j0: int, j1: int) -> np.ndarray:
        s = self.stride
        js = np.arange(j0, j1)
        g0 = (js // s) * s
        grid = np.arange(g0[0], g0[-1] + s + 1, s)
        Kg = self._grid(grid)  # (G, 3, L, 3)
        k = (g0 - grid[0]) // s
        frac = ((js - g0) / s)[:, None, None, None]
        return Kg[k] * (1.0 - frac) + Kg[k + 1] * frac


def _take(mats: PoseMatrices, idx) -> PoseMatrices:
    """Pose matrices at a subset of the poses."""
    return mats.replace(xyz_m=mats.xyz_m[idx], q_m=mats.q_m[idx], J=mats.J[idx], M=mats.M[idx], C=mats.C[idx],
                        K=mats.K[idx], B_c=mats.B_c[idx], B_k=mats.B_k[idx])


def _ltv_kernel_fn(model: LpvModel, X: np.ndarray, basis: UniformBasis, L: int):
    """Exact LPV: each basis filtered through the model evaluated at every sample of the path."""
    m = basis.m
    Np = len(X)
    b0, b1 = basis.shape(0), basis.shape(1)

    def kfn(j0, j1):
        nJ = j1 - j0
        s0 = j0 * m
        span = min((j1 - 1) * m + L, Np + L) - s0
        idx = np.clip(np.arange(s0, s0 + span), 0, Np - 1)
        mats: PoseMatrices = model.matrices(X[idx], check=False)
        w = np.zeros((span, 6, nJ * 3))
        for jj in range(nJ):
            s = jj * m
            n = min(basis.support, span - s)
            for i in range(3):
                col = jj * 3 + i
                w[s:s + n, i, col] = b0[:n]
                w[s:s + n, 3 + i, col] = b1[:n]
        y = ltv_mech_response(mats, w, basis.dt_s)  # (span, 3, nJ*3)
        K = np.zeros((nJ, 3, L, 3))
        for jj in range(nJ):
            s = jj * m
            n = min(L, span - s)
            K[jj, :, :n, :] = y[s:s + n, :, jj * 3:(jj + 1) * 3].transpose(2, 0, 1)
        return K

    return kfn
