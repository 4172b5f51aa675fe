"""The paper's two sub-models as plain functions of ``s`` (Eqs. 18, 22-25, 34) and as LTI objects.

Sub-model 1 (per carriage, decoupled): ``q = G_qd(s) q_d + G_Fq(s) F``,
``G_qd = G_qd,m G_qd,e`` with ``G_qd,m = (c s + k) / (m s^2 + (c + b) s + k)``,
``G_qd,e = (d1 s + d0) / (s^2 + d2 s + d0)``, and ``G_Fq = -1 / (m s^2 + (c + b) s + k)``.
Sub-model 2 (rigid effector): ``N_Fq = m_nt s^2 + b_nt s``.

All parameters SI; ``s`` is complex angular frequency (rad/s).  Arrays broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass

import control
import numpy as np

__all__ = [
    "CarriageParams",
    "g_qd_mech",
    "g_qd_elec",
    "g_qd",
    "g_fq",
    "n_fq",
    "carriage_tf",
    "derived_modal",
]


@dataclass(frozen=True)
class CarriageParams:
    """Per-tower carriage and drive parameters, each an array of shape (3,) (SI units).

    m (kg), c (N s/m, belt), b (N s/m, guide), k (N/m, belt), d0 (1/s^2), d1 (1/s), d2 (1/s).
    """

    m: np.ndarray
    c: np.ndarray
    b: np.ndarray
    k: np.ndarray
    d0: np.ndarray
    d1: np.ndarray
    d2: np.ndarray

    @classmethod
    def from_dynamics(cls, dyn) -> "CarriageParams":
        arr = {n: np.asarray(getattr(dyn, n), float).reshape(3) for n in ("m", "c", "b", "k", "d0", "d1", "d2")}
        return cls(**arr)


def g_qd_mech(s, m, c, b, k):
    """Mechanical part ``(c s + k) / (m s^2 + (c + b) s + k)`` (Eq. 23), dimensionless."""
    return (c * s + k) / (m * s**2 + (c + b) * s + k)


def g_qd_elec(s, d0, d1, d2):
    """Electrical part ``(d1 s + d0) / (s^2 + d2 s + d0)`` (Eq. 25), unit DC gain."""
    return (d1 * s + d0) / (s**2 + d2 * s + d0)


def g_qd(s, m, c, b, k, d0, d1, d2):
    """Commanded-to-actual carriage position, effector detached (Eq. 22)."""
    return g_qd_mech(s, m, c, b, k) * g_qd_elec(s, d0, d1, d2)


def g_fq(s, m, c, b, k):
    """Force-to-carriage-position receptance ``-1 / (m s^2 + (c + b) s + k)`` (Eq. 34), m/N."""
    return -1.0 / (m * s**2 + (c + b) * s + k)


def n_fq(s, m_nt, b_nt):
    """Effector dynamic stiffness ``m_nt s^2 + b_nt s`` (Eq. 18), N/m."""
    return m_nt * s**2 + b_nt * s


def carriage_tf(m, c, b, k, d0, d1, d2) -> control.TransferFunction:
    """``G_qd(s)`` of one carriage as a python-control transfer function."""
    mech = control.tf([c, k], [m, c + b, k])
    elec = control.tf([d1, d0], [1.0, d2, d0])
    return mech * elec


def derived_modal(m, c, b, k, m_nt, b_nt) -> dict[str, float]:
    """Modal quantities the paper tabulates, derived from the physical parameters.

    Returns ``w_n`` and ``zeta`` of the bare carriage (Eqs. 26-27) and ``w_n_p``, ``zeta_p`` of the
    carriage loaded by a third of the effector at the bed centre (Eqs. 29-32), in rad/s.
    """
    wn = np.sqrt(k / m)
    zeta = (c + b) / (2 * m * wn)
    m_p = m + m_nt / 3.0
    b_p = c + b + b_nt / 3.0
    wn_p = np.sqrt(k / m_p)
    zeta_p = b_p / (2 * m_p * wn_p)
    return {"w_n": float(np.mean(wn)), "zeta": float(np.mean(zeta)),
            "w_n_p": float(np.mean(wn_p)), "zeta_p": float(np.mean(zeta_p))}
