"""Frame compliance coupling the carriages (e.g. the top frame ring flexing).

Physics
-------
The towers are tied together by the top and bottom frame rings that also carry the belt idlers
and motors.  When carriage ``i`` moves against carriage ``j`` the ring between their towers
deflects; to first order this is a spring ``k_c`` between every pair of carriages, potential
energy ``1/2 k_c sum_{i<j} (q_i - q_j)^2``, i.e.

    K += k_c L,     L = [[2, -1, -1], [-1, 2, -1], [-1, -1, 2]]

(the Laplacian of the triangle of towers).  The input coupling ``B_k`` is unchanged: the belts
still push each carriage on its own.  ``k_c`` is given relative to the mean belt stiffness,
``coupling = k_c / mean(k)``; negative values (down to -0.3) model a frame that softens the
differential motion.

``PoseMatrices`` has a diagonal input coupling, so this is a parallel coupling: it also moves the
static gain of differential (lateral) commands to ``k / (k + 3 k_c)``; a compliance in series
with the belts (static gain 1) is not representable there.  Use the fit near and above the
resonances; a lateral low-frequency gain different from one is part of the signature.

Signature in the FRFs
---------------------
The common mode (all carriages in phase: z-to-z at the bed centre, the z->qA identification
sweep) is unchanged; the differential modes (x, y) are stiffer (``coupling > 0``) at every pose
by about ``sqrt(1 + 3 coupling)``, and their low-frequency gain is below one.

Parameters
----------
coupling : ``k_c / mean(k)`` (dimensionless).
"""

from __future__ import annotations

import numpy as np

from . import Effect, Param, register

__all__ = ["FrameCoupling", "LAPLACIAN"]

LAPLACIAN = np.array([[2.0, -1.0, -1.0], [-1.0, 2.0, -1.0], [-1.0, -1.0, 2.0]])


@register
class FrameCoupling(Effect):
    """A spring ``k_c = coupling * mean(k)`` between every pair of carriages (see module)."""

    name = "frame_coupling"
    summary = "frame/tower compliance: coupling stiffness between the carriages (off-diagonal K)"
    params = {
        "coupling": Param(0.0, "", -0.3, 3.0, "coupling stiffness k_c between each pair of carriages / mean belt "
                          "stiffness", search=(-0.25, 1.0)),
    }
    fit = ("coupling",)
    evidence_keys = ("common_vs_lateral", "lateral_gain", "peak_shift")

    def k_c(self, model) -> float:
        """Coupling stiffness, N/m."""
        return self.values["coupling"] * float(np.mean(model.carriage.k))

    def apply(self, mats, model):
        """``K += k_c L`` (``L`` the triangle's Laplacian); input coupling unchanged."""
        if self.values["coupling"] == 0:
            return mats
        return mats.replace(K=mats.K + self.k_c(model) * LAPLACIAN[None])

    def explain(self, model) -> str:
        """``k_c`` in N/m and what it does to the lateral modes and static gain."""
        c = self.values["coupling"]
        return (f"k_c = {self.k_c(model):.4g} N/m between each pair of carriages ({c:.3f} of the belt stiffness): "
                f"lateral (differential) modes {np.sqrt(max(1 + 3 * c, 1e-9)) - 1:+.1%}, lateral static gain "
                f"{1 / (1 + 3 * c):.3f}, vertical common mode unchanged")
