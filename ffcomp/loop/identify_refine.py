"""Refine a two-sweep identification with more sweeps: the other towers' carriage sweeps and any
assembled sweeps, fitted with the full LPV model.

The paper's identification sees carriage A alone and the assembled printer at the centre, and
assumes three equal towers.  A carriage sweep of tower B or C (``kind: carriage``, ``qB -> qB``)
shows that tower's own mode; with it the towers' belt stiffness and damping are fitted per tower
(carriage masses stay equal: the same parts), together with the base dynamics, from all the
sweeps given (coherence-weighted relative complex least squares, :func:`ffcomp.loop.fit.fit_free`).
The result is written into the profile's per-tower ``dynamics`` (``k = [k_A, k_B, k_C]``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..measure.predict import check_measurements
from ..model.lpv import LpvModel
from .base_fit import BASE_KEYS, apply_base_to_profile, base_spec
from .fit import fit_free

__all__ = ["Refinement", "refine_identification"]


@dataclass(frozen=True)
class Refinement:
    """The refined profile, the per-tower factors relative to tower A, residuals before/after."""

    profile: object
    k_ratio: tuple
    c_ratio: tuple
    residual_before: np.ndarray
    residual_after: np.ndarray
    towers: tuple

    def to_dict(self) -> dict:
        return {"k_ratio_to_A": list(self.k_ratio), "c_ratio_to_A": list(self.c_ratio),
                "towers_with_carriage_sweeps": list(self.towers),
                "mean_residual_before": float(np.mean(self.residual_before)),
                "mean_residual_after": float(np.mean(self.residual_after))}


def refine_identification(profile, measurements) -> Refinement:
    """Refit ``profile``'s base dynamics, and per-tower k and c where a carriage sweep shows that
    tower, to ``measurements`` (which should include the two identification sweeps)."""
    ms = list(measurements)
    model0 = LpvModel.from_profile(profile, effects=False)
    check_measurements(model0, ms)
    towers = sorted({m.output[1] for m in ms if m.kind == "carriage" and m.output in ("qB", "qC")})
    specs = [base_spec(model0), {"name": "tower_scale", **{f"{w}_scale_{t}": 1.0 for w in "kmc" for t in "ABC"}}]
    free = [(0, p) for p in BASE_KEYS] + [(1, f"{w}_scale_{t}") for t in towers for w in "kc"]
    res = fit_free(model0, specs, free, ms, fresh=[False] * len(free), tol=1e-6, max_nfev=40)
    base, ts = res.effects[0], res.effects[1]
    kr = (1.0,) + tuple(float(ts[f"k_scale_{t}"]) for t in "BC")
    cr = (1.0,) + tuple(float(ts[f"c_scale_{t}"]) for t in "BC")
    # the model that was fitted: the base (per-tower pattern kept) with tower_scale on top, whose
    # damping factor scales each carriage's whole damping c + b and whose stiffness factor k
    new = apply_base_to_profile(profile, base)
    dyn = new.dynamics
    new = new.with_(dynamics=replace(dyn, **{key: tuple(float(v) * r for v, r in zip(getattr(dyn, key), ratio))
                                            for key, ratio in (("k", kr), ("c", cr), ("b", cr))}))
    return Refinement(new, kr, cr, res.residual_before, res.residual_after, tuple(towers))
