"""Belt-span stiffness that varies with carriage height.

Physics
-------
Each carriage is clamped to a closed timing-belt loop that runs from the motor pulley at the
bottom of its tower up to an idler at the top and back.  Seen from the carriage, the belt is two
spans in parallel, both anchored at the motor pulley: the lower span (length ``l1``, carriage to
pulley) and the upper span plus the return side (``l2``, over the idler and back down).  With the
belt's axial stiffness ``EA`` (N),

    k(q) = EA / l1 + EA / l2,      l1 = l1_ref + (q - q_ref),      l1 + l2 = loop  (fixed)

The profile's ``k`` is what the identification measured, i.e. ``k(q_ref)`` at the identification
pose ``(0, 0, z_ref_mm)``; this effect rescales it by ``k(q) / k(q_ref)`` per tower and pose.
The belt force ``k(q) (u - q) + c(q) (u_dot - q_dot)`` linearises (about ``u = q``) to the same
``k(q)`` in the stiffness ``K`` and the input coupling ``B_k``; the belt's material damping ``c``
is taken proportional to its stiffness (``tau = c / k`` constant), so ``C`` and ``B_c`` scale too.
``k(q)`` is lowest with the carriage mid-loop (``l1 = l2``) and grows towards either end.

Signature in the FRFs
---------------------
No change at the identification height; the carriage modes move as the carriages climb or
descend: a resonance shift (and residual) that grows with the carriages' distance from the
identification height: between heights at the bed centre, and with ``|x|, |y|`` (the carriages of
the towers the nozzle approaches rise, the others fall).

Parameters
----------
l1_ref_mm : lower-span length (carriage clamp to motor pulley) at the identification height, mm.
loop_mm : ``l1 + l2``: twice the pulley-to-idler distance, mm (fixed by the frame; fitted too,
    or set it with ``ffcomp fit --set belt_span:loop_mm=...`` if you measured it).
z_ref_mm : nozzle height of the identification sweep at the bed centre, mm (not fitted).
"""

from __future__ import annotations

import numpy as np

from ...kinematics import inverse
from . import Effect, Param, register

__all__ = ["BeltSpan", "stiffness_ratio"]


def stiffness_ratio(q_m, q_ref_m, l1_ref_m: float, loop_m: float) -> np.ndarray:
    """``k(q) / k(q_ref)`` for two spans in parallel (``l1 + l2 = loop``); broadcasts, dimensionless."""
    l1 = np.clip(l1_ref_m + (np.asarray(q_m, float) - q_ref_m), 0.02 * loop_m, 0.98 * loop_m)
    l1r = l1_ref_m
    f = 1.0 / l1 + 1.0 / (loop_m - l1)
    f_ref = 1.0 / l1r + 1.0 / (loop_m - l1r)
    return f / f_ref


@register
class BeltSpan(Effect):
    """Belt stiffness ``k(q) = EA/l1 + EA/l2`` relative to the identification height (see module)."""

    name = "belt_span"
    summary = "belt stiffness EA/l1 + EA/l2 varies with carriage height (two spans in parallel)"
    params = {
        "l1_ref_mm": Param(400.0, "mm", 10.0, 5000.0,
                           "lower-span length (carriage to motor pulley) at the identification height",
                           search=(100.0, 1200.0)),
        "loop_mm": Param(1500.0, "mm", 100.0, 10000.0, "l1 + l2: twice the motor-pulley-to-idler distance",
                         search=(500.0, 4000.0)),
        "z_ref_mm": Param(30.0, "mm", -1000.0, 1000.0, "nozzle height of the identification sweep (bed centre)"),
    }
    fit = ("l1_ref_mm", "loop_mm")
    evidence_keys = ("height", "height_shift")

    def __init__(self, **values):
        super().__init__(**values)
        if not self.values["l1_ref_mm"] < 0.98 * self.values["loop_mm"]:
            raise ValueError(f"effect 'belt_span': l1_ref_mm = {self.values['l1_ref_mm']:g} must be shorter "
                             f"than loop_mm = {self.values['loop_mm']:g}")

    def q_ref(self, model) -> np.ndarray:
        """Carriage heights at the identification pose, shape (3,), m."""
        return inverse(model.geometry, np.array([0.0, 0.0, self.values["z_ref_mm"] * 1e-3]))

    def ratio(self, q_m, model) -> np.ndarray:
        """``k(q) / k(q_ref)`` for carriage heights ``q_m`` (m), shape like ``q_m`` (P, 3)."""
        return stiffness_ratio(q_m, self.q_ref(model)[None, :], self.values["l1_ref_mm"] * 1e-3,
                               self.values["loop_mm"] * 1e-3)

    def apply(self, mats, model):
        """Scale each belt's stiffness (``K`` diagonal, ``B_k``) and damping (``C``, ``B_c``) by ``k(q)/k(q_ref)``."""
        r = self.ratio(mats.q_m, model)  # (P, 3)
        K, C = mats.K.copy(), mats.C.copy()
        i = np.arange(3)
        K[:, i, i] += (r - 1.0) * mats.B_k
        C[:, i, i] += (r - 1.0) * mats.B_c
        return mats.replace(K=K, C=C, B_k=mats.B_k * r, B_c=mats.B_c * r)

    def explain(self, model) -> str:
        """The span geometry and the stiffness ratio at the bottom and top of the z range."""
        g = model.geometry
        z = np.linspace(max(g.z_min_m, 0.0), g.z_max_m, 7)
        q = inverse(g, np.column_stack([np.zeros_like(z), np.zeros_like(z), z]))[:, 0]
        r = self.ratio(np.column_stack([q, q, q]), model)[:, 0]
        v = self.values
        return (f"lower belt span {v['l1_ref_mm']:.0f} mm of a {v['loop_mm']:.0f} mm loop at the identification "
                f"height z = {v['z_ref_mm']:g} mm: belt stiffness {r[0]:.3f}x at z = {z[0] * 1e3:.0f} mm and "
                f"{r[-1]:.3f}x at z = {z[-1] * 1e3:.0f} mm (carriage modes {np.sqrt(r[0]) - 1:+.1%} / "
                f"{np.sqrt(r[-1]) - 1:+.1%})")
