"""Rotational inertia of the forearms (rods instead of masses split between their ends).

Physics
-------
The paper lumps each forearm pair's mass ``m_f`` half at the carriage and half at the effector
(Eqs. 21, 28), i.e. as two point masses at the rod ends.  A rigid rod of mass ``m`` whose ends
move with velocities ``va`` and ``vb`` has a velocity field linear along its length, so its
kinetic energy is

    T_rod = m/2 * integral_0^1 |va + (vb - va) t|^2 dt = m/6 (|va|^2 + va.vb + |vb|^2)

against ``m/4 (|va|^2 + |vb|^2)`` for the lumped model: the difference is ``-m/12 |va - vb|^2``
(the lumped model overstates the rod's inertia about its centre, ``m l^2/4`` instead of
``m l^2/12``).  Both rods of a pair move alike (parallelogram), so per pair the correction is
``-m_f/12 |va - vb|^2`` with ``va = (0, 0, q_dot_i)`` (the carriage) and ``vb = X_dot = J q_dot``
(the effector translates).  Writing ``va = E_i q_dot`` (``E_i`` has a single 1 at row z, column
i) and summing over the towers,

    T_corr = 1/2 q_dot^T dM q_dot,      dM = -(m_f/6) sum_i (E_i - J)^T (E_i - J)

which is added to the joint-space mass matrix ``M`` at every pose.  A general symmetric rod with
central inertia ``I`` gives ``-(m/8)(1 - 4 I / (m l^2)) |va - vb|^2``: the parameter ``scale``
multiplies the uniform-rod correction, ``scale = 1.5 (1 - 4 I / (m l^2))``: 1 for a uniform rod,
0 for all the mass at the ends (the paper's model), 1.5 for all of it at mid-length.

Signature in the FRFs
---------------------
Nothing changes for a pure vertical move at the bed centre (all rod ends move together) nor for
the carriage sweep (forearms detached: a model with ``m_nt = 0`` gets no correction); lateral
modes have less mass than the model says, so the x and y resonances are a few percent high
everywhere, more where the arms are steep (large ``|va - vb|`` per unit effector motion).

Parameters
----------
scale : fraction of the uniform-rod correction (1 = uniform rods); uses the profile's ``m_f``.
"""

from __future__ import annotations

import numpy as np

from . import Effect, Param, register

__all__ = ["ForearmInertia", "mass_correction"]


def mass_correction(J: np.ndarray, m_f: float) -> np.ndarray:
    """Uniform-rod correction ``-(m_f/6) sum_i (E_i - J)^T (E_i - J)``, shape (P, 3, 3), kg.

    Parameters
    ----------
    J : ndarray, shape (P, 3, 3)
        ``dX/dq`` at each pose.
    m_f : float
        Mass of one forearm pair, kg.
    """
    J = np.asarray(J, float)
    out = np.zeros_like(J)
    for i in range(3):
        D = -J.copy()
        D[:, 2, i] += 1.0  # E_i - J
        out += np.einsum("pki,pkj->pij", D, D)
    return -(m_f / 6.0) * out


@register
class ForearmInertia(Effect):
    """Uniform-rod forearms: joint-space mass correction ``scale * dM(J)`` (see module)."""

    name = "forearm_inertia"
    summary = "forearms as uniform rods (rotational inertia) instead of masses split between the ends"
    params = {
        "scale": Param(1.0, "", 0.0, 1.5, "fraction of the uniform-rod correction (1 = uniform rods, "
                       "0 = point masses at the ends)", search=(0.0, 1.5)),
    }
    fit = ("scale",)
    evidence_keys = ("common_vs_lateral", "peak_shift")

    def apply(self, mats, model):
        """Add ``scale * mass_correction(J, m_f)`` to ``M`` (nothing without an effector)."""
        # no effector (m_nt = 0: the carriage sweep, forearms detached) means no rods between carriage and effector
        if model.m_f <= 0 or model.m_nt <= 0 or self.values["scale"] == 0:
            return mats
        return mats.replace(M=mats.M + self.values["scale"] * mass_correction(mats.J, model.m_f))

    def explain(self, model) -> str:
        """The scale as a rod inertia about its centre, compared with uniform rods and point masses."""
        s = self.values["scale"]
        rho = 1.0 - s / 1.5  # 4 I / (m l^2)
        return (f"scale {s:.3f} of the uniform-rod correction (rod inertia about its centre "
                f"{rho / 4:.3f} m l^2; uniform rod 0.083, paper's lumped ends 0.25), with m_f = {model.m_f:g} kg: "
                f"lateral modes lighter than the lumped model, vertical motion at the centre unchanged")
