"""The base dynamics (the paper's m, c, b, k, b_nt and drive d0, d1, d2) as fittable parameters.

The two-sweep identification sees one carriage (A) alone and the assembled printer at one pose;
when a tower differs, or an effect acts at the identification pose, its result is biased (m, k,
b off by 20 % with tower B 25 % softer).  With sweeps at several poses the base can be refitted
together with the effects (:func:`ffcomp.loop.fit.fit_effects`), from all of them.

The base enters a fit as one pseudo-effect entry ``{"name": "base", "m": ..., ...}`` holding the
tower means; per-tower differences already in the profile are kept (``m, k, d0, d2`` scaled, ``c,
b, d1`` shifted).  Bounds are physical and wide around the starting values: masses and
stiffnesses within a factor 2, damping ``>= 0``, ``d1`` within ``0.5 sqrt(d0)``.  The effector
and forearm masses are measured, not fitted; they fix the scale (the FRFs are dimensionless).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..model.effects import Param

__all__ = ["BASE", "BASE_KEYS", "base_table", "base_spec", "apply_base", "apply_base_to_profile", "explain_base"]

#: name of the pseudo-effect entry that carries the base dynamics in a fit
BASE = "base"
#: the refitted base parameters (tower means), SI
BASE_KEYS = ("m", "c", "b", "k", "b_nt", "d0", "d1", "d2")
_UNITS = {"m": "kg", "c": "N s/m", "b": "N s/m", "k": "N/m", "b_nt": "N s/m", "d0": "1/s^2", "d1": "1/s",
          "d2": "1/s"}
_SCALED = ("m", "k", "d0", "d2")


def base_spec(model) -> dict:
    """The model's base dynamics as a fit entry (tower means)."""
    cp = model.carriage
    d = {"name": BASE}
    for k in BASE_KEYS:
        d[k] = float(model.b_nt) if k == "b_nt" else float(np.mean(getattr(cp, k)))
    return d


def base_table(spec: dict) -> dict[str, Param]:
    """Physical fit bounds around the starting values of ``spec`` (name -> :class:`Param`)."""
    m, c, b, k = spec["m"], spec["c"], spec["b"], spec["k"]
    d0, d1, d2, bnt = spec["d0"], spec["d1"], spec["d2"], spec["b_nt"]
    crit = 2.0 * np.sqrt(max(k * m, 0.0))
    rng = {
        "m": (0.5 * m, 2.0 * m),
        "k": (0.5 * k, 2.0 * k),
        "c": (0.0, max(3.0 * c, 2e-4 * k)),
        "b": (0.0, max(3.0 * b, 0.3 * crit)),
        "b_nt": (0.0, max(3.0 * bnt, 0.3 * crit)),
        "d0": (0.5 * d0, 2.0 * d0),
        "d1": (d1 - 0.5 * np.sqrt(d0), d1 + 0.5 * np.sqrt(d0)),
        "d2": (0.3 * d2, 3.0 * d2),
    }
    return {key: Param(float(spec[key]), _UNITS[key], lo, hi, f"base dynamics {key} (tower mean)", search=(lo, hi))
            for key, (lo, hi) in rng.items()}


def _per_tower(old: np.ndarray, key: str, new_mean: float) -> np.ndarray:
    old = np.asarray(old, float)
    mean = float(np.mean(old))
    if key in _SCALED:
        return old * (new_mean / mean) if mean != 0 else np.full(3, new_mean)
    return old + (new_mean - mean)


def apply_base(model, spec: dict):
    """``model`` with the base dynamics of ``spec`` (per-tower pattern of ``model`` kept)."""
    cp = model.carriage
    kw = {k: _per_tower(getattr(cp, k), k, spec[k]) for k in BASE_KEYS if k != "b_nt"}
    return replace(model, carriage=replace(cp, **kw), b_nt=float(spec["b_nt"]))


def apply_base_to_profile(profile, spec: dict):
    """``profile`` with the base dynamics of ``spec`` (per-tower pattern kept)."""
    dyn = profile.dynamics
    kw = {k: tuple(float(v) for v in _per_tower(getattr(dyn, k), k, spec[k])) for k in BASE_KEYS if k != "b_nt"}
    return profile.with_(dynamics=replace(dyn, **kw, b_nt=float(spec["b_nt"])))


def explain_base(start: dict, fitted: dict, min_change: float = 0.02) -> str:
    """The base parameters that moved by more than ``min_change`` (relative), in words."""
    parts = []
    for k in BASE_KEYS:
        a, b = float(start[k]), float(fitted[k])
        ref = abs(a) if k != "d1" else np.sqrt(abs(float(start["d0"])))
        if ref > 0 and abs(b - a) > min_change * ref:
            rel = f" ({(b - a) / abs(a):+.0%})" if a != 0 else ""
            parts.append(f"{k} {a:.4g} -> {b:.4g} {_UNITS[k]}{rel}")
    return "base dynamics: " + (", ".join(parts) if parts else "unchanged (within 2 %)")
