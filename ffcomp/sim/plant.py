"""Nonlinear delta-printer simulator: the paper's physics without linearisation, effects included.

Each carriage ``i`` is driven through its drive (electrical) filter ``F_i(s)`` -- the strictly
proper realisation of :func:`~ffcomp.model.lpv.drive_filter_ss` (``d0, d1, d2``, optional lag and
Pade delay) -- which turns the command ``r_i`` into the drive position ``u_i``.  The carriages and
the rigid effector (with the forearm halves) obey, at the *actual* pose ``X = forward(q)``,

    M(X) q'' = B_c u' + B_k u - K(X) q - C(X) q' - m_nt J^T J' q' + f_g

where ``M = diag(m) + m_nt J^T J``, ``C = diag(c + b) + b_nt J^T J``, ``K``, ``B_c``, ``B_k`` come
from :meth:`LpvModel.matrices` at the actual pose, so every effect that edits the pose matrices
(mass, damping, stiffness, input coupling, drive filter) is honoured; ``J' q' = -S^-1 w`` with
``w_i = |X' - e_z q_i'|^2`` is the exact velocity term of the constraint ``|s_i|^2 = L_i^2`` (twice
differentiated), i.e. ``J_dot q_dot`` in closed form (:func:`~ffcomp.kinematics.velocity_product`);
``m_nt`` and the geometry are the model's (an effect that adds task-space mass is honoured in ``M``
but not in this small velocity term).  ``f_g`` is gravity, off by default: homing and bed probing
are done under gravity, so the static sag (``(m + m_nt/3) g / k`` ~ 26 um at the centre for the
paper's printer) is calibrated out and only dynamics matter; with ``gravity=True`` carriages get
``-m g`` and the effector ``J^T (0, 0, -m_nt g)``, and the run starts from the sagged equilibrium.

Positions are absolute, so ``B_k u - K q`` is the belt force ``k (u - q)`` of the paper.  An effect
may add a spring that is not a belt (``K != diag(B_k)``, e.g. ``frame_coupling``); the LPV model
then only defines deviation dynamics, and the simulator anchors that extra spring at the run's
first command ``q_0``: ``+ (K - diag(B_k)) q_0`` (zero for the paper's model).  The run starts at
rest, the linearisation about ``q_0`` is exactly the LPV model, and slow motions away from it
show the static gain ``K^-1 diag(B_k)`` that the model implies.

Integration (:meth:`DeltaPlant.simulate`)
    * Commands are held between samples (``hold="zoh"``, default: a stepper's step stream updated
      at the sample rate; it lags the sample instants by half a sample on average, which the
      lag-aligned metrics absorb) or linearly interpolated (``hold="linear"``).
    * The drive filter is linear and pose independent (:class:`PoseMatrices` gives it per tower),
      so ``u`` and ``u'`` are computed exactly on the half-step grid first, block by block
      (:class:`~ffcomp.sim.drive.DriveGrid`); the jump of ``u'`` at a held command step
      (``d1 != 0``) is honoured exactly (RK4's last stage uses the left limit).
    * The 6 mechanical states of all runs of a batch are integrated together by fixed-step RK4 at
      ``substeps`` steps per command sample (default 10: 10 kHz for 1 kHz commands).  The pose
      matrices are re-evaluated at the actual pose every ``pose_every`` steps (default: once per
      command sample), at the pose extrapolated to the middle of that hold window (midpoint
      rule); over a window the linear part of each step is the exact RK4 step map (one matrix
      product), and the small ``J' q'`` term, quadratic in the actual velocities, is
      extrapolated to each step's middle (Adams-Bashforth 2).  ``pose_every=0`` is the reference:
      everything re-evaluated at every RK4 stage.  On the 10 000 mm/s^2 square at (100, 0, 30) mm
      the defaults stay within 3 nm of the reference (2 ms windows: 10 nm, 4 ms: 55 nm), and
      5 kHz integration changes the result by < 0.1 nm (``benchmarks/bench_sim.py``).

Everything is SI: m, s, kg, N.  Runs are batched: commands ``(R, N, 3)`` give results ``(R, N, 3)``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import KinematicsError
from ..kinematics import forward, reachable, velocity_product
from ..linalg3 import inv3, rmatvec3
from ..model.lpv import LpvModel, drive_filter_ss
from .drive import DriveGrid, upsample

__all__ = ["DeltaPlant", "SimResult", "quantize", "HOLDS", "GRAVITY_M_S2"]

HOLDS = ("zoh", "linear")
GRAVITY_M_S2 = 9.80665


def quantize(q_m, steps_per_mm: float) -> np.ndarray:
    """Round carriage commands to whole (micro)steps: ``round(q / step) * step``, step ``1e-3 / spm`` m.

    The error is at most half a step.  Step 0 is at ``q = 0`` (the steps are counted from an
    absolute origin, as after homing to a known height).
    """
    step_m = 1e-3 / float(steps_per_mm)
    return np.round(np.asarray(q_m, float) / step_m) * step_m


@dataclass(frozen=True)
class SimResult:
    """Simulated runs, sampled at the command times.

    Attributes
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s.
    q_cmd_m : ndarray, shape (R, N, 3)
        Carriage commands actually applied (after quantisation), m.
    u_m : ndarray, shape (R, N, 3)
        Drive positions (drive-filter outputs), m.
    q_m, qd_m_s : ndarray, shape (R, N, 3)
        Carriage positions (m) and velocities (m/s).
    xyz_m : ndarray, shape (R, N, 3)
        Nozzle positions ``forward(q)``, m.
    """

    t_s: np.ndarray
    q_cmd_m: np.ndarray
    u_m: np.ndarray
    q_m: np.ndarray
    qd_m_s: np.ndarray
    xyz_m: np.ndarray

    @property
    def n_runs(self) -> int:
        return self.q_m.shape[0]

    def run(self, r: int) -> "SimResult":
        """Run ``r`` alone (still with a leading axis of length 1)."""
        sl = slice(r, r + 1)
        return SimResult(self.t_s, self.q_cmd_m[sl], self.u_m[sl], self.q_m[sl], self.qd_m_s[sl],
                         self.xyz_m[sl])


@dataclass
class _Held:
    """Pose-dependent coefficients of the mechanical ODE, held over a window (batched over R).

    ``A`` is the linear part of ``y = [q, v]``; ``Phi`` and ``Gam`` the RK4 step map of the
    linear part: ``y+ = Phi y + Gam[0] F1 + Gam[1] F2 + Gam[2] F4`` for input accelerations at
    the start, middle and end of a step; ``Gw`` maps the ``w`` of the ``J' q'`` term (held over a
    step) to the step increment.
    """

    MBc: np.ndarray  # (R, 3, 3) M^-1 diag(B_c)
    MBk: np.ndarray  # (R, 3, 3) M^-1 diag(B_k)
    MW: np.ndarray  # (R, 3, 3) M^-1 m_nt J^T S^-1 (acceleration per unit w)
    A: np.ndarray  # (R, 6, 6)
    J: np.ndarray  # (R, 3, 3)
    ag: np.ndarray  # (R, 3) constant acceleration M^-1 (f_g + (K - diag(B_k)) q_0)
    Phi: np.ndarray | None = None  # (R, 6, 6)
    Gam: np.ndarray | None = None  # (3, R, 6, 3)
    Gw: np.ndarray | None = None  # (R, 6, 3)


class DeltaPlant:
    """The nonlinear printer: drive filters, carriages, rigid effector, exact kinematics.

    Parameters
    ----------
    model : LpvModel
        Supplies the geometry, ``m_nt`` and, through :meth:`LpvModel.matrices` (effects included),
        the pose matrices.  Use :meth:`carriage_only` for the effector-detached carriage.
    gravity : bool
        Add gravity (see the module notes); default off.
    pade_order : int
        Pade order of a drive delay (as :func:`~ffcomp.model.lpv.state_space_arrays`).
    """

    def __init__(self, model: LpvModel, *, gravity: bool = False, pade_order: int = 6):
        self.model = model
        self.geometry = model.geometry
        self.gravity = bool(gravity)
        self.pade_order = int(pade_order)
        g = model.geometry
        nominal = np.array([[0.0, 0.0, 0.5 * (g.z_min_m + g.z_max_m)]])
        mats = model.matrices(nominal, check=False)
        self._filters = [drive_filter_ss(mats.d0[i], mats.d1[i], mats.d2[i], mats.lag_s[i],
                                         mats.delay_s[i], self.pade_order) for i in range(3)]
        nf = [f[0].shape[0] for f in self._filters]
        self._off = np.concatenate([[0], np.cumsum(nf)]).astype(int)
        self.n_drive_states = int(self._off[-1])
        self.block_samples = 2000  # command samples per block of the fine drive grid
        self._m_carr = np.asarray(model.carriage.m, float)

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def from_profile(cls, profile, *, effects: bool = True, **kw) -> "DeltaPlant":
        """Plant of a :class:`~ffcomp.profile.PrinterProfile` (its effects included by default)."""
        return cls(LpvModel.from_profile(profile, effects=effects), **kw)

    def carriage_only(self) -> "DeltaPlant":
        """The same printer with forearms and effector detached: ``m_nt = b_nt = 0``.

        The carriage mass stays ``m`` of the profile, i.e. carriage plus half a forearm pair
        (Eq. 21), which is what the paper's first identification sweep measures (``G_qd``).
        """
        return DeltaPlant(replace(self.model, m_nt=0.0, b_nt=0.0), gravity=self.gravity,
                          pade_order=self.pade_order)

    @property
    def n_states(self) -> int:
        """Size of the full state (drive-filter states, q, q_dot) used by :meth:`rhs`."""
        return self.n_drive_states + 6

    # ------------------------------------------------------------------ exact right-hand side
    def _static_force(self, mats, q_ref: np.ndarray | None) -> np.ndarray:
        """Gravity ``-m g - m_nt g J^T e_z`` plus the anchor ``(K - diag(B_k)) q_ref`` (R, 3), N."""
        f = np.zeros(mats.B_k.shape)
        if self.gravity:
            f -= GRAVITY_M_S2 * (self._m_carr[None, :] + self.model.m_nt * mats.J[:, 2, :])
        if q_ref is not None:
            f += np.einsum("rij,rj->ri", mats.K, q_ref) - mats.B_k * q_ref
        return f

    def rhs(self, x: np.ndarray, q_cmd_m: np.ndarray, q_ref_m: np.ndarray | None = None) -> np.ndarray:
        """Exact time derivative of the full state, every term at the actual state.

        Parameters
        ----------
        x : ndarray, shape (R, n) or (n,)
            State: the three drive filters' states (tower A, B, C, each as
            :func:`drive_filter_ss`), then ``q`` (m) and ``q_dot`` (m/s), the order of
            :func:`~ffcomp.model.lpv.state_space_arrays`.
        q_cmd_m : ndarray, shape (R, 3) or (3,)
            Carriage command, m.
        q_ref_m : ndarray, shape (R, 3) or (3,), optional
            Configuration where springs other than the belts are relaxed (see the module notes);
            irrelevant when ``K = diag(B_k)`` (the paper's model).

        Returns
        -------
        ndarray, shape of ``x``
        """
        single = np.ndim(x) == 1
        x = np.atleast_2d(np.asarray(x, float))
        r = np.atleast_2d(np.asarray(q_cmd_m, float))
        nfs = self.n_drive_states
        dx = np.empty_like(x)
        u = np.empty((x.shape[0], 3))
        ud = np.empty((x.shape[0], 3))
        for i, (a, b, c) in enumerate(self._filters):
            z = x[:, self._off[i]:self._off[i + 1]]
            dz = z @ a.T + r[:, i:i + 1] * b[None]
            dx[:, self._off[i]:self._off[i + 1]] = dz
            u[:, i] = z @ c
            ud[:, i] = dz @ c
        q, v = x[:, nfs:nfs + 3], x[:, nfs + 3:nfs + 6]
        X = forward(self.geometry, q)
        mats = self.model.matrices(X, check=False)
        Jdv = velocity_product(self.geometry, X, v, q=mats.q_m, J=mats.J)
        f = (mats.B_c * ud + mats.B_k * u - np.einsum("rij,rj->ri", mats.K, q)
             - np.einsum("rij,rj->ri", mats.C, v)
             - self.model.m_nt * rmatvec3(mats.J, Jdv)
             + self._static_force(mats, None if q_ref_m is None else np.atleast_2d(q_ref_m)))
        dx[:, nfs:nfs + 3] = v
        dx[:, nfs + 3:] = np.linalg.solve(mats.M, f[:, :, None])[:, :, 0]
        return dx[0] if single else dx

    def equilibrium(self, q_cmd_m: np.ndarray) -> np.ndarray:
        """Full state at rest under a constant command (drive filters at steady state).

        Uses ``q_ref_m = q_cmd_m`` (the run starts here); without gravity ``q = q_cmd``.

        Returns
        -------
        ndarray, shape (R, n) or (n,)
        """
        single = np.ndim(q_cmd_m) == 1
        r = np.atleast_2d(np.asarray(q_cmd_m, float))
        x = np.zeros((r.shape[0], self.n_states))
        for i, (a, b, _c) in enumerate(self._filters):
            x[:, self._off[i]:self._off[i + 1]] = -np.linalg.solve(a, b)[None] * r[:, i:i + 1]
        x[:, self.n_drive_states:self.n_drive_states + 3] = self._rest_q(r)
        return x[0] if single else x

    def _rest_q(self, u0: np.ndarray) -> np.ndarray:
        """Carriage heights at rest with drive positions and anchor ``u0`` (R, 3): ``K (q - u0) = f_g``."""
        q = u0.copy()
        if not self.gravity:
            return q
        for _ in range(4):
            mats = self.model.matrices(forward(self.geometry, q), check=False)
            q = u0 + np.linalg.solve(mats.K, self._static_force(mats, None)[:, :, None])[:, :, 0]
        return q

    # ------------------------------------------------------------------ fast batched integration
    def _held(self, q: np.ndarray, X_guess: np.ndarray, q_ref: np.ndarray,
              dt: float | None = None) -> tuple[_Held, np.ndarray]:
        """Coefficients at carriage heights ``q`` (R, 3) (with the RK4 map for step ``dt``); and the pose."""
        X, Sinv = _refine_forward(self.geometry, q, X_guess)
        mats = self.model.matrices(X, check=False)
        R = q.shape[0]
        Minv = inv3(mats.M)
        MW = Minv @ (self.model.m_nt * np.einsum("rki,rkj->rij", mats.J, Sinv))
        A = np.zeros((R, 6, 6))
        A[:, :3, 3:] = np.eye(3)
        A[:, 3:, :3] = -Minv @ mats.K
        A[:, 3:, 3:] = -Minv @ mats.C
        ag = np.einsum("rij,rj->ri", Minv, self._static_force(mats, q_ref))
        H = _Held(Minv * mats.B_c[:, None, :], Minv * mats.B_k[:, None, :], MW, A, mats.J, ag)
        if dt is not None:
            H.Phi, H.Gam = _rk4_map(A, dt)
            H.Gw = H.Gam.sum(axis=0) @ MW
        return H, X

    def simulate(self, t_s, q_cmd_m, *, substeps: int = 10, hold: str = "zoh", pose_every: int | None = None,
                 steps_per_mm: float | None = None, check: bool = True) -> SimResult:
        """Run carriage commands through the nonlinear printer.

        Parameters
        ----------
        t_s : array_like, shape (N,)
            Uniform command times, s.
        q_cmd_m : array_like, shape (N, 3) or (R, N, 3)
            Carriage commands, m; R independent runs are integrated together.
        substeps : int
            RK4 steps per command sample (10 -> 10 kHz for 1 kHz commands).
        hold : {"zoh", "linear"}
            Commands held between samples (a stepper's step stream) or linearly interpolated.
        pose_every : int, optional
            RK4 steps between evaluations of the pose matrices; default ``substeps`` (once per
            command sample); 0 re-evaluates them at every RK4 stage (the slow reference).
        steps_per_mm : float, optional
            Quantise the commands to whole steps first (:func:`quantize`).
        check : bool
            Raise :class:`~ffcomp.errors.KinematicsError` if a command has no pose.

        Returns
        -------
        SimResult
            Arrays shaped (R, N, 3) (R = 1 for 2-D input); the run starts at rest at the first command.
        """
        t_s = np.asarray(t_s, float)
        r = np.asarray(q_cmd_m, float)
        if r.ndim == 2:
            r = r[None]
        if r.ndim != 3 or r.shape[2] != 3 or r.shape[1] != t_s.shape[0] or t_s.shape[0] < 2:
            raise ValueError(f"q_cmd_m must be (N, 3) or (R, N, 3) with N = len(t_s) >= 2, got {r.shape}")
        if hold not in HOLDS:
            raise ValueError(f"hold must be one of {HOLDS}, got {hold!r}")
        pose_every = substeps if pose_every is None else int(pose_every)
        if substeps < 1 or pose_every < 0:
            raise ValueError("substeps must be >= 1 and pose_every >= 0")
        T = (t_s[-1] - t_s[0]) / (t_s.shape[0] - 1)
        if not T > 0 or not np.allclose(np.diff(t_s), T, rtol=1e-6, atol=0.0):
            raise ValueError("t_s must be increasing and uniformly spaced")
        R, N, _ = r.shape
        if steps_per_mm:
            r = quantize(r, steps_per_mm)
        if check:
            X_cmd = forward(self.geometry, r.reshape(-1, 3))
            ok = reachable(self.geometry, X_cmd, tol_m=1e-3)  # 1 mm slack: steps, shaping
            if not np.all(ok):
                k = int(np.argmin(ok))
                q_mm, x_mm = np.round(r.reshape(-1, 3)[k] * 1e3, 3), np.round(X_cmd[k] * 1e3, 3)
                raise KinematicsError(f"carriage command #{k % N} of run {k // N} ({q_mm} mm) maps to an "
                                      f"unreachable nozzle position {x_mm} mm")
        n2 = 2 * substeps
        dt = T / substeps
        drive = DriveGrid(self._filters, 0.5 * dt, hold)
        dstate = drive.start(R)
        r0 = r[:, :1]
        y = np.zeros((R, 6))
        y[:, :3] = self._rest_q(r[:, 0])
        X = forward(self.geometry, y[:, :3])
        out_q, out_v, out_u = np.empty((R, N, 3)), np.empty((R, N, 3)), np.empty((R, N, 3))
        out_q[:, 0], out_v[:, 0] = y[:, :3], 0.0
        window = pose_every if pose_every > 0 else 1
        w_prev = np.zeros((R, 3))
        q_last, J_last = y[:, :3], None
        for k0 in range(0, N - 1, self.block_samples):  # blocks bound the memory of the fine grid
            k1 = min(k0 + self.block_samples, N - 1)
            u_g, ud_g, udl_g = drive.run(upsample(r, k0, k1, n2, hold) - r0, dstate)
            u_g += r0
            out_u[:, k0:k1 + 1] = u_g[:, ::n2]
            n_steps = (k1 - k0) * substeps
            step = 0
            while step < n_steps:
                nw = min(window, n_steps - step)
                j0 = 2 * step
                if pose_every == 0:
                    y, X = self._exact_step(y, dt, X, r[:, 0], u_g, ud_g, udl_g, j0)
                    nw = 1
                else:
                    q_mid = y[:, :3] + y[:, 3:] * (0.5 * nw * dt)
                    if J_last is not None:  # first-order guess of the new pose
                        X = X + (J_last @ (q_mid - q_last)[:, :, None])[:, :, 0]
                    H, X = self._held(q_mid, X, r[:, 0], dt)
                    q_last, J_last = q_mid, H.J
                    g = self._window_forcing(H, u_g, ud_g, udl_g, j0, nw)
                    # y+ = Phi y + g + Gw (1.5 w - 0.5 w_prev): the small J' q' term extrapolated to
                    # the step middle (Adams-Bashforth 2) from the step-start velocities
                    Tm = np.concatenate([H.Phi, 1.5 * H.Gw, -0.5 * H.Gw], axis=2)
                    J = H.J
                    for s in range(nw):
                        v = y[:, 3:]
                        Xd = (J @ v[:, :, None])[:, :, 0]
                        w = np.einsum("ri,ri->r", Xd, Xd)[:, None] + v * (v - 2.0 * Xd[:, 2:3])
                        y = (Tm @ np.concatenate([y, w, w_prev], axis=1)[:, :, None])[:, :, 0] + g[:, s]
                        w_prev = w
                        if (step + s + 1) % substeps == 0:
                            k = k0 + (step + s + 1) // substeps
                            out_q[:, k], out_v[:, k] = y[:, :3], y[:, 3:]
                if pose_every == 0 and (step + 1) % substeps == 0:
                    k = k0 + (step + 1) // substeps
                    out_q[:, k], out_v[:, k] = y[:, :3], y[:, 3:]
                step += nw
        xyz = forward(self.geometry, out_q.reshape(-1, 3)).reshape(R, N, 3)
        return SimResult(t_s, r, out_u, out_q, out_v, xyz)

    @staticmethod
    def _window_forcing(H: _Held, u_g, ud_g, udl_g, j0: int, nw: int) -> np.ndarray:
        """Input part of the ``nw`` RK4 steps from grid index ``j0``: shape (R, nw, 6)."""
        sl = slice(j0, j0 + 2 * nw + 1)
        F = (np.einsum("rij,rtj->rti", H.MBc, ud_g[:, sl]) + np.einsum("rij,rtj->rti", H.MBk, u_g[:, sl])
             + H.ag[:, None])
        jl = slice(j0 + 2, j0 + 2 * nw + 1, 2)
        Fl = F[:, 2::2] + np.einsum("rij,rtj->rti", H.MBc, udl_g[:, jl] - ud_g[:, jl])
        return (np.einsum("rij,rtj->rti", H.Gam[0], F[:, 0:-1:2])
                + np.einsum("rij,rtj->rti", H.Gam[1], F[:, 1::2])
                + np.einsum("rij,rtj->rti", H.Gam[2], Fl))

    def _exact_step(self, y, dt, X, q_ref, u_g, ud_g, udl_g, j0):
        """One RK4 step with the pose matrices re-evaluated at every stage (reference path)."""

        def deriv(yy, jj, left=False):
            nonlocal X
            H, X = self._held(yy[:, :3], X, q_ref)
            ud = udl_g[:, jj] if left else ud_g[:, jj]
            F = np.einsum("rij,rj->ri", H.MBc, ud) + np.einsum("rij,rj->ri", H.MBk, u_g[:, jj]) + H.ag
            return np.concatenate([yy[:, 3:], _accel(yy, H, F)], axis=1)

        k1 = deriv(y, j0)
        k2 = deriv(y + 0.5 * dt * k1, j0 + 1)
        k3 = deriv(y + 0.5 * dt * k2, j0 + 1)
        k4 = deriv(y + dt * k3, j0 + 2, left=True)
        return y + (dt / 6.0) * (k1 + 2.0 * (k2 + k3) + k4), X


def _w_term(J: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``w_i = |X' - e_z q_i'|^2`` with ``X' = J q'`` (R, 3), m^2/s^2; ``J' q' = -S^-1 w``."""
    Xd = (J @ v[:, :, None])[:, :, 0]
    return (Xd[:, 0:1] ** 2 + Xd[:, 1:2] ** 2) + (Xd[:, 2:3] - v) ** 2


def _accel(y: np.ndarray, H: _Held, F: np.ndarray) -> np.ndarray:
    """Carriage accelerations (R, 3) for states ``y = [q, v]`` (R, 6) and input forcing ``F`` (R, 3)."""
    lin = (H.A[:, 3:] @ y[:, :, None])[:, :, 0]
    return lin + F + (H.MW @ _w_term(H.J, y[:, 3:])[:, :, None])[:, :, 0]


_RK4_Y0 = np.hstack([np.eye(6), np.zeros((6, 9))])  # identity on the state, then three inputs
_RK4_E = np.zeros((3, 6, 15))
for _k in range(3):
    _RK4_E[_k, 3:, 6 + 3 * _k:9 + 3 * _k] = np.eye(3)


def _rk4_map(A: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The classical RK4 step of ``y' = A y + E f(t)`` (``E = [0; I]``) as a linear map.

    Returns ``Phi`` (R, 6, 6) and ``Gam`` (3, R, 6, 3) such that one RK4 step is
    ``Phi y + Gam[0] f(t) + Gam[1] f(t + dt/2) + Gam[2] f(t + dt)`` -- the RK4 formulas applied
    to the identity and unit inputs, so it is exactly RK4, at one matrix product per step.
    """
    Y0, E = _RK4_Y0, _RK4_E
    k1 = A @ Y0 + E[0]
    k2 = A @ (Y0 + 0.5 * dt * k1) + E[1]
    k3 = A @ (Y0 + 0.5 * dt * k2) + E[1]
    k4 = A @ (Y0 + dt * k3) + E[2]
    Y1 = Y0 + (dt / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
    return Y1[:, :, :6], np.stack([Y1[:, :, 6 + 3 * k:9 + 3 * k] for k in range(3)])


def _refine_forward(geom, q: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nozzle positions for carriage heights ``q`` by Newton's method from a nearby guess ``X``.

    Solves ``|s_i|^2 = L_i^2`` with ``s_i = X - P_i(q_i)`` (the rows of ``S``).  One iteration from
    a guess within ~2 um (the previous pose moved along ``J q'``) leaves ~1e-11 m; a poor guess
    gets more iterations, and :func:`~ffcomp.kinematics.forward` as the last resort.

    Returns
    -------
    X : ndarray, shape (R, 3)
    S_inv : ndarray, shape (R, 3, 3)
        Inverse of ``S`` at (within rounding) ``X``.
    """
    P = np.empty((q.shape[0], 3, 3))
    P[:, :, :2] = geom.tower_xy_m[None]
    P[:, :, 2] = q - geom.effector_offset_z_m
    L2 = geom.arm_length_m**2
    for _ in range(8):
        S = X[:, None, :] - P
        g = np.einsum("rij,rij->ri", S, S) - L2
        Sinv = inv3(S)
        X = X - 0.5 * np.einsum("rij,rj->ri", Sinv, g)
        if not np.abs(g).max() > 1e-6:  # was within ~2 um: after the Newton step within ~1e-11 m
            return X, Sinv
        if not np.all(np.isfinite(X)):
            break
    X = forward(geom, q)
    return X, inv3(X[:, None, :] - P)
