"""The position-dependent (LPV) delta model: receptance coupling of carriages and rigid effector.

Linearised about a pose ``X`` (Eqs. 16-20), the joint-space dynamics read

    (s^2 M + s C + K) q = diag(s B_c + B_k) u,      u = F(s) q_d

with, for the paper's model,

    M = diag(m) + m_nt J^T J,   C = diag(c + b) + b_nt J^T J,   K = diag(k),
    B_c = c,  B_k = k,          F(s) = G_qd,e(s) = (d1 s + d0) / (s^2 + d2 s + d0)

which is Eq. 20, ``G = [I - G_Fq N_Fq J^T J]^-1 G_qd``, multiplied out (Eq. 15 with its damping
term read as ``b_nt J^T J``).  Task space: ``X = J q`` so ``G_task = J G J^-1`` (Eq. 35).

Physical effects beyond the paper (see :mod:`ffcomp.model.effects`) act on the per-pose matrices
:class:`PoseMatrices` (mass, damping, stiffness, input coupling, drive filter): the model never
assumes three identical carriages.

Two representations are provided and tested against each other:

* :func:`frequency_response`: batched over poses and frequencies (3x3 complex solves);
* :func:`state_space`: a python-control ``StateSpace`` at one pose (continuous, or discretised).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Sequence

import control
import numpy as np

from ..kinematics import DeltaGeometry, check_reachable, inverse, jacobian
from ..linalg3 import gram3, inv3
from .submodels import CarriageParams

__all__ = [
    "LpvModel",
    "PoseMatrices",
    "FRAMES",
    "frequency_response",
    "state_space",
    "state_space_arrays",
    "drive_filter_ss",
]

#: Input/output frames of a response: name -> (output frame, input frame).
FRAMES = {
    "joint": ("joint", "joint"),  # q_d -> q
    "task": ("task", "task"),  # X_d -> X          (Eq. 35)
    "task_to_joint": ("joint", "task"),  # X_d -> q
    "joint_to_task": ("task", "joint"),  # q_d -> X
}
AXES = {"x": 0, "y": 1, "z": 2, "qA": 0, "qB": 1, "qC": 2}


@dataclass(frozen=True)
class PoseMatrices:
    """Linearised joint-space matrices at P poses.

    Attributes
    ----------
    xyz_m, q_m : ndarray, shape (P, 3)
        Nozzle position and carriage heights, m.
    J : ndarray, shape (P, 3, 3)
        ``dX/dq``.
    M, C, K : ndarray, shape (P, 3, 3)
        Mass (kg), damping (N s/m) and stiffness (N/m) in joint space.
    B_c, B_k : ndarray, shape (P, 3)
        Input coupling: the drive position ``u`` pushes carriage i with ``B_c u_dot + B_k u``.
    d0, d1, d2 : ndarray, shape (3,)
        Electrical (drive) dynamics of each tower.
    delay_s : ndarray, shape (3,)
        Extra pure delay of each drive, s (0 for the paper's model).
    lag_s : ndarray, shape (3,)
        Extra first-order lag time constant of each drive, s (0 for the paper's model).
    drive_tf : tuple of (num, den)
        Extra transfer functions in series with every drive filter (polynomial coefficients in
        ``s``, highest power first, proper, unit DC gain expected); set by effects such as a
        compliant motor mount (an extra mode).  Empty for the paper's model.
    """

    xyz_m: np.ndarray
    q_m: np.ndarray
    J: np.ndarray
    M: np.ndarray
    C: np.ndarray
    K: np.ndarray
    B_c: np.ndarray
    B_k: np.ndarray
    d0: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    delay_s: np.ndarray
    lag_s: np.ndarray
    drive_tf: tuple = ()

    @property
    def n_poses(self) -> int:
        return self.xyz_m.shape[0]

    def replace(self, **kw) -> "PoseMatrices":
        return replace(self, **kw)


@dataclass(frozen=True)
class LpvModel:
    """The printer's position-dependent linear model.

    Build it with :meth:`from_profile`; evaluate with :meth:`matrices`, :func:`frequency_response`
    and :func:`state_space`.
    """

    geometry: DeltaGeometry
    carriage: CarriageParams
    m_nt: float
    b_nt: float
    m_f: float = 0.0
    effects: tuple = ()

    @classmethod
    def from_profile(cls, profile, *, effects: bool = True) -> "LpvModel":
        """Model of a :class:`~ffcomp.profile.PrinterProfile` (with its effects unless ``effects=False``)."""
        dyn = profile.dynamics
        eff = ()
        if effects and profile.effects:
            from .effects import build_effects

            eff = build_effects(profile.effects)
        return cls(
            geometry=profile.geometry_si(),
            carriage=CarriageParams.from_dynamics(dyn),
            m_nt=float(dyn.m_nt),
            b_nt=float(dyn.b_nt),
            m_f=float(dyn.m_f),
            effects=tuple(eff),
        )

    def with_effects(self, effects: Sequence) -> "LpvModel":
        return replace(self, effects=tuple(effects))

    def matrices(self, xyz_m, *, check: bool = True) -> PoseMatrices:
        """Linearised matrices at nozzle positions ``xyz_m`` (shape (P, 3) or (3,), metres)."""
        xyz = np.atleast_2d(np.asarray(xyz_m, float))
        if check:
            check_reachable(self.geometry, xyz, what="model pose")
        q = inverse(self.geometry, xyz)
        J = jacobian(self.geometry, xyz, q=q)
        JtJ = gram3(J)
        cp = self.carriage
        eye = np.eye(3)[None]
        P = xyz.shape[0]
        mats = PoseMatrices(
            xyz_m=xyz,
            q_m=q,
            J=J,
            M=cp.m[None, :, None] * eye + self.m_nt * JtJ,
            C=(cp.c + cp.b)[None, :, None] * eye + self.b_nt * JtJ,
            K=cp.k[None, :, None] * eye + np.zeros((P, 3, 3)),
            B_c=np.broadcast_to(cp.c, (P, 3)).copy(),
            B_k=np.broadcast_to(cp.k, (P, 3)).copy(),
            d0=cp.d0.copy(),
            d1=cp.d1.copy(),
            d2=cp.d2.copy(),
            delay_s=np.zeros(3),
            lag_s=np.zeros(3),
        )
        for eff in self.effects:
            mats = eff.apply(mats, self)
        return mats


# --------------------------------------------------------------------------- frequency domain

def _drive_filter(s: np.ndarray, mats: PoseMatrices, delay: str) -> np.ndarray:
    """Per-tower drive filter ``F_i(s)``, shape (F, 3)."""
    s = s[:, None]
    f = (mats.d1 * s + mats.d0) / (s**2 + mats.d2 * s + mats.d0)
    f = f / (1.0 + mats.lag_s * s)
    for num, den in mats.drive_tf:
        f = f * (np.polyval(num, s) / np.polyval(den, s))
    if np.any(mats.delay_s):
        if delay == "exact":
            f = f * np.exp(-mats.delay_s * s)
        else:
            order = int(delay.split(":")[1]) if ":" in delay else 6
            for i in range(3):
                if mats.delay_s[i] > 0:
                    num, den = control.pade(mats.delay_s[i], order)
                    f[:, i] *= np.polyval(num, s[:, 0]) / np.polyval(den, s[:, 0])
    return f


def joint_response(mats: PoseMatrices, freq_hz, *, delay: str = "exact") -> np.ndarray:
    """``G(j w)`` from commanded to actual carriage positions.

    Returns
    -------
    H : ndarray, shape (P, 3, 3, F), complex, dimensionless (outputs, inputs as in python-control).
    """
    w = 2.0 * np.pi * np.asarray(freq_hz, float)
    s = 1j * w
    # A(s) = s^2 M + s C + K : (P, F, 3, 3)
    A = (s[None, :, None, None] ** 2) * mats.M[:, None] + s[None, :, None, None] * mats.C[:, None] + mats.K[:, None]
    F = _drive_filter(s, mats, delay)  # (F, 3)
    rhs_diag = (mats.B_c[:, None, :] * s[None, :, None] + mats.B_k[:, None, :]) * F[None]  # (P, F, 3)
    G = inv3(A) * rhs_diag[..., None, :]  # A^-1 diag(rhs): scale columns
    return np.moveaxis(G, 1, -1)




def frequency_response(model_or_mats, xyz_m=None, freq_hz=None, *, frame: str = "task",
                       delay: str = "exact") -> np.ndarray:
    """Batched frequency response at many poses and frequencies.

    Parameters
    ----------
    model_or_mats : LpvModel or PoseMatrices
    xyz_m : array_like, shape (P, 3), optional
        Poses (metres); required with a model.
    freq_hz : array_like, shape (F,)
        Frequencies, Hz.
    frame : {"task", "joint", "task_to_joint", "joint_to_task"}
        Which response (see :data:`FRAMES`): ``task`` is ``J G J^-1`` (Eq. 35).
    delay : {"exact", "pade", "pade:N"}
        How a drive delay (effect) is evaluated; ``pade`` matches :func:`state_space`.

    Returns
    -------
    H : ndarray, shape (P, 3, 3, F), complex
        ``H[p, o, i, f]``: output ``o`` per unit input ``i`` at pose ``p``.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {sorted(FRAMES)}, got {frame!r}")
    if freq_hz is None:
        raise ValueError("freq_hz is required")
    mats = model_or_mats if isinstance(model_or_mats, PoseMatrices) else model_or_mats.matrices(xyz_m)
    G = joint_response(mats, freq_hz, delay=delay)
    out_f, in_f = FRAMES[frame]
    if in_f == "task" or out_f == "task":
        Gf = np.moveaxis(G, -1, 1)  # (P, F, 3, 3) for batched matmul
        if in_f == "task":
            Gf = Gf @ np.linalg.inv(mats.J)[:, None]
        if out_f == "task":
            Gf = mats.J[:, None] @ Gf
        G = np.moveaxis(Gf, 1, -1)
    return G


# --------------------------------------------------------------------------- state space

def mech_arrays(mats: PoseMatrices) -> tuple[np.ndarray, np.ndarray]:
    """Continuous mechanics ``(A, B)`` at every pose: shapes (P, 6, 6) and (P, 6, 6).

    State ``(q, q_dot)``, input ``(u, u_dot)`` (drive position and velocity):
    ``M q'' + C q' + K q = B_c u' + B_k u``.
    """
    P = mats.n_poses
    Minv = np.linalg.inv(mats.M)
    A = np.zeros((P, 6, 6))
    A[:, :3, 3:] = np.eye(3)
    A[:, 3:, :3] = -Minv @ mats.K
    A[:, 3:, 3:] = -Minv @ mats.C
    B = np.zeros((P, 6, 6))
    B[:, 3:, :3] = Minv * mats.B_k[:, None, :]
    B[:, 3:, 3:] = Minv * mats.B_c[:, None, :]
    return A, B


def drive_filter_ss(d0, d1, d2, lag_s=0.0, delay_s=0.0, pade_order: int = 6, drive_tf=()):
    """State-space ``(a, b, c)`` of one drive filter ``F(s)`` (strictly proper, so ``d = 0``)."""
    tfs = tuple((tuple(float(v) for v in n), tuple(float(v) for v in d)) for n, d in drive_tf)
    a, b, c = _drive_filter_ss(float(d0), float(d1), float(d2), float(lag_s), float(delay_s), int(pade_order), tfs)
    return a.copy(), b.copy(), c.copy()


@lru_cache(maxsize=64)
def _drive_filter_ss(d0, d1, d2, lag_s, delay_s, pade_order, drive_tf=()):
    sys = control.tf([d1, d0], [1.0, d2, d0])
    if lag_s > 0:
        sys = sys * control.tf([1.0], [lag_s, 1.0])
    for num, den in drive_tf:
        sys = sys * control.tf(list(num), list(den))
    ss = control.ss(sys)
    if abs(float(np.squeeze(ss.D))) > 0:
        raise ValueError("drive filter must be strictly proper")
    A, B, C = np.asarray(ss.A), np.asarray(ss.B)[:, 0], np.asarray(ss.C)[0]
    if delay_s > 0:
        # Pade approximant of a unit delay, time-scaled (a companion form of the scaled polynomial
        # would be hopelessly ill-conditioned), in series after the filter: u = Pade(F q_d)
        num, den = control.pade(1.0, pade_order)
        p = control.ss(control.tf(num, den))
        Ap, Bp = np.asarray(p.A) / delay_s, np.asarray(p.B)[:, 0] / delay_s
        Cp, Dp = np.asarray(p.C)[0], float(np.squeeze(p.D))
        n, k = len(A), len(Ap)
        A2 = np.zeros((n + k, n + k))
        A2[:n, :n] = A
        A2[n:, :n] = np.outer(Bp, C)
        A2[n:, n:] = Ap
        B2 = np.concatenate([B, np.zeros(k)])
        C2 = np.concatenate([Dp * C, Cp])
        A, B, C = A2, B2, C2
    return A, B, C


def state_space_arrays(mats: PoseMatrices, *, pade_order: int = 6):
    """Continuous-time ``(A, B, C, D)`` at every pose, batched: shapes (P,n,n), (P,n,3), (P,3,n), (P,3,3).

    State: the three drive filters' states, then ``q`` (3) and ``q_dot`` (3).  Output: ``q``.
    The drive output ``u_i = c_i x_i`` and its derivative ``c_i a_i x_i + c_i b_i q_d,i`` feed
    ``M q'' + C q' + K q = B_c u' + B_k u``.
    """
    P = mats.n_poses
    filt = [drive_filter_ss(mats.d0[i], mats.d1[i], mats.d2[i], mats.lag_s[i], mats.delay_s[i], pade_order,
                            mats.drive_tf) for i in range(3)]
    nf = [f[0].shape[0] for f in filt]
    off = np.concatenate([[0], np.cumsum(nf)])
    n_f = int(off[-1])
    n = n_f + 6
    A = np.zeros((P, n, n))
    B = np.zeros((P, n, 3))
    Minv = np.linalg.inv(mats.M)
    # rows of the force vector in terms of filter states and the input
    Fx = np.zeros((P, 3, n_f))  # force from filter states
    Fu = np.zeros((P, 3, 3))  # force from q_d (feedthrough of u_dot)
    for i, (a, b, c) in enumerate(filt):
        sl = slice(off[i], off[i + 1])
        A[:, sl, sl] = a
        B[:, sl, i] = b
        Fx[:, i, sl] = mats.B_c[:, i, None] * (c @ a)[None] + mats.B_k[:, i, None] * c[None]
        Fu[:, i, i] = mats.B_c[:, i] * float(c @ b)
    iq, iv = slice(n_f, n_f + 3), slice(n_f + 3, n)
    A[:, iq, iv] = np.eye(3)
    A[:, iv, :n_f] = Minv @ Fx
    A[:, iv, iq] = -Minv @ mats.K
    A[:, iv, iv] = -Minv @ mats.C
    B[:, iv, :] = Minv @ Fu
    C = np.zeros((P, 3, n))
    C[:, :, iq] = np.eye(3)
    D = np.zeros((P, 3, 3))
    return A, B, C, D


def state_space(model_or_mats, xyz_m=None, *, frame: str = "joint", dt_s: float | None = None,
                method: str = "zoh", pade_order: int = 6) -> control.StateSpace:
    """python-control ``StateSpace`` of the model at one pose.

    Parameters
    ----------
    frame : see :data:`FRAMES`
        ``task`` maps inputs through ``J^-1`` and outputs through ``J`` (Eq. 35).
    dt_s : float, optional
        Sample time; when given the system is discretised with ``method`` (python-control
        ``sample_system``: ``zoh``, ``foh``, ``tustin``, ...).
    """
    mats = model_or_mats if isinstance(model_or_mats, PoseMatrices) else model_or_mats.matrices(xyz_m)
    if mats.n_poses != 1:
        raise ValueError(f"state_space takes one pose, got {mats.n_poses}")
    A, B, C, D = (x[0] for x in state_space_arrays(mats, pade_order=pade_order))
    out_f, in_f = FRAMES[frame]
    J = mats.J[0]
    if in_f == "task":
        B = B @ np.linalg.inv(J)
    if out_f == "task":
        C = J @ C
    names_in = ["x_d", "y_d", "z_d"] if in_f == "task" else ["qA_d", "qB_d", "qC_d"]
    names_out = ["x", "y", "z"] if out_f == "task" else ["qA", "qB", "qC"]
    sys = control.ss(A, B, C, D, inputs=names_in, outputs=names_out)
    if dt_s is not None:
        sys = control.sample_system(sys, dt_s, method=method)
    return sys
