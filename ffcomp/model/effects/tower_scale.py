"""Per-tower carriage parameters: unequal belt tension, carriage mass or friction per tower.

Physics
-------
The paper identifies one carriage (tower A) and assumes all three are equal (its Eq. 1 note).
Real towers differ: belt tension sets the tooth engagement and hence the effective belt
stiffness, carriages carry different cable chains or endstop flags, guide rails bind differently.
This effect scales each tower's carriage sub-model relative to the profile:

* ``k_scale_X``: belt stiffness of tower X.  The belt force ``k (u - q)`` scales in both the
  stiffness ``K`` and the input coupling ``B_k`` (static gain stays 1).
* ``m_scale_X``: the carriage mass ``m`` of tower X (the diagonal of ``M``).
* ``c_scale_X``: the carriage's damping (belt ``c`` in ``C`` and ``B_c``, and guide friction ``b``).

Towers are the profile's towers in order (A, B, C = the profile's first, second and third
``tower_angles_deg``), so the effect is independent of where each tower stands.

Signature in the FRFs
---------------------
One tower's carriage mode is off by ``sqrt(k_scale / m_scale)`` at every pose: in the task-space
FRFs the mode of that tower separates from the others (x-to-x at the bed centre shows a split or
broadened peak, the mode belonging to the weak tower is low everywhere), while the carriage sweep
of the identified tower (A) still matches.

Parameters
----------
k_scale_A, k_scale_B, k_scale_C : belt stiffness factors.
m_scale_A, m_scale_B, m_scale_C : carriage mass factors.
c_scale_A, c_scale_B, c_scale_C : carriage damping factors.

All nine are fitted by default, starting from 1: stiffness and mass separate through the coupling
with the effector (``m_nt J^T J``) and the mass line above resonance, damping through the peak
heights; from the identification sweeps alone (tower A) they would not be.
"""

from __future__ import annotations

import numpy as np

from . import Effect, Param, register

__all__ = ["TowerScale"]

_T = "ABC"


def _params():
    p = {}
    for t in _T:
        p[f"k_scale_{t}"] = Param(1.0, "", 0.2, 5.0, f"belt stiffness of tower {t} / profile's", search=(0.5, 2.0))
    for t in _T:
        p[f"m_scale_{t}"] = Param(1.0, "", 0.2, 5.0, f"carriage mass of tower {t} / profile's", search=(0.5, 2.0))
    for t in _T:
        p[f"c_scale_{t}"] = Param(1.0, "", 0.0, 20.0, f"carriage damping of tower {t} / profile's",
                                  search=(0.2, 5.0))
    return p


@register
class TowerScale(Effect):
    """Stiffness, mass and damping factors of each tower's carriage (see module)."""

    name = "tower_scale"
    summary = "per-tower carriage stiffness / mass / damping factors (e.g. unequal belt tension)"
    params = _params()
    base_fixed = ("k_scale_A", "m_scale_A", "c_scale_A")  # with the base refitted: towers B, C relative to A
    fit = tuple(_params())  # all nine: each is identifiable from task-space sweeps at several poses
    grid = False  # start from 1 (no difference between towers)
    evidence_keys = ("peak_shift", "tower")

    def _vec(self, what: str) -> np.ndarray:
        return np.array([self.values[f"{what}_scale_{t}"] for t in _T])

    def apply(self, mats, model):
        """Belt force ``k (u - q)`` scaled in ``K`` and ``B_k``; carriage mass in ``M``; damping in ``C``, ``B_c``."""
        sk, sm, sc = self._vec("k"), self._vec("m"), self._vec("c")
        i = np.arange(3)
        K, M, C = mats.K.copy(), mats.M.copy(), mats.C.copy()
        K[:, i, i] += (sk - 1.0) * mats.B_k
        M[:, i, i] += (sm - 1.0) * model.carriage.m
        C[:, i, i] += (sc - 1.0) * (mats.B_c + model.carriage.b)
        return mats.replace(K=K, M=M, C=C, B_k=mats.B_k * sk, B_c=mats.B_c * sc)

    def explain(self, model) -> str:
        """Each tower's factors (those off by more than 1 %) and the shift of its carriage mode."""
        sk, sm = self._vec("k"), self._vec("m")
        fr = np.sqrt(sk / sm)
        parts = []
        for j, t in enumerate(_T):
            bits = []
            if abs(sk[j] - 1) > 0.01:
                bits.append(f"belt stiffness {sk[j]:.3f}x")
            if abs(sm[j] - 1) > 0.01:
                bits.append(f"mass {sm[j]:.3f}x")
            if abs(self.values[f"c_scale_{t}"] - 1) > 0.01:
                bits.append(f"damping {self.values[f'c_scale_{t}']:.3f}x")
            if bits:
                parts.append(f"tower {t}: {', '.join(bits)} (carriage mode {fr[j] - 1:+.1%})")
        if not parts:
            parts.append("all towers within 1 % of the profile")
        j = int(np.argmax(np.abs(fr - 1)))
        odd = ""
        if abs(fr[j] - 1) > 0.02:
            odd = f"; tower {_T[j]}'s mode is {'low' if fr[j] < 1 else 'high'}"
        # relative to tower A (what the data determine when the base is refitted too), always shown
        rel = ", ".join(f"{w}_{t}/{w}_A = {self._vec(n)[i] / self._vec(n)[0]:.3f}"
                        for w, n in (("k", "k"), ("m", "m"), ("c", "c")) for i, t in enumerate(_T) if i > 0)
        return "; ".join(parts) + odd + f"; relative to tower A: {rel}"
