"""Which physical effect is the model missing?  Fit each candidate, score it on held-out poses.

For every effect in the library that the profile does not have yet, its parameters (together with
those of the profile's own effects, which were fitted without it) are fitted to the measurements
(:mod:`ffcomp.loop.fit`, coherence-weighted complex least squares); refitting the profile's own
effects alone is one more candidate.  Each is scored by cross-validation **by pose**: the poses
are split into ``k`` folds; each fold's measurements are predicted with parameters fitted on the
other folds only.  An effect that merely bends the model towards the noise gains nothing on poses
it has not seen.

Scores use mean squares of the normalised complex residual ``r`` (per measurement) against the
noise floor ``nu`` (:mod:`ffcomp.measure.noise`):

* excess error of the base model ``E0 = mean(r0^2) - mean(nu^2)``;
* a candidate removes ``(mean(r0^2) - mean(r_heldout^2)) / E0`` of it;
* the base model is *significantly* wrong when ``E0 > base_threshold * mean(nu^2)``; a candidate
  is significant when it removes at least ``min_removed`` of the excess and at least
  ``min_gain * mean(nu^2)`` in absolute terms;
* the status is ``ok`` (nothing significant to explain), ``explained`` (the best candidate removes
  at least ``explain_fraction`` of the excess and leaves less than twice the noise, RMS),
  ``partial`` (it is significant but leaves more: fit it and diagnose again, or something outside
  the library is missing) or ``unexplained`` (no candidate is significant, or one frequency band
  fails at every pose and in the carriage sweep and the best candidate leaves more than twice the
  noise: :func:`~ffcomp.loop.evidence.fixed_band`).

Candidates are ranked by held-out residual, significant ones first; when the profile already has
effects, a new effect is significant only if it also beats refitting those effects alone by the
same margins (parsimony).  The evidence in words comes from the fitted values
(``Effect.explain``) and from the residual's signatures (:mod:`ffcomp.loop.evidence`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..measure.noise import noise_floors
from ..measure.predict import BatchPredictor, check_measurements
from ..model.effects import EFFECTS, load_library
from ..model.lpv import LpvModel
from .base_fit import BASE, BASE_KEYS, base_spec, explain_base
from .evidence import evidence, features, fixed_band
from .fit import Objective, _model_with, base_supported, effect_specs, fit_free
from .geometry_fit import GEOM, geometry_spec, profile_geometry_change

__all__ = ["Candidate", "Diagnosis", "diagnose", "pose_folds"]


@dataclass(frozen=True)
class Candidate:
    """One candidate effect, fitted on all data and scored on held-out poses.

    ``heldout`` and ``insample`` are per-measurement normalised complex residuals, shape (N,);
    ``removed`` is the fraction of the base model's excess error (above noise) removed held out.
    """

    effect: str
    refit: bool
    params: dict
    estimates: tuple
    heldout: np.ndarray
    insample: np.ndarray
    removed: float
    gain: float
    significant: bool
    explanation: str
    evidence: tuple
    effects: tuple = ()
    #: ``"effect"``, or ``"geometry"`` (a profile value is wrong: ``set_value`` says which)
    kind: str = "effect"
    set_value: str = ""

    @property
    def label(self) -> str:
        if self.kind == "geometry":
            return f"geometry: {self.effect.replace('_', ' ')}"
        return f"refit {self.effect}" if self.refit else self.effect

    @property
    def command(self) -> str:
        """The command that applies this candidate (``ffcomp fit``, or ``ffcomp profile set`` for geometry)."""
        if self.kind == "geometry":
            return f"ffcomp profile set P.toml {self.set_value}"
        add = "" if self.refit else f" --add {self.effect}"
        return f"ffcomp fit DATA --profile P.toml{add} -o P2.toml"

    @property
    def mean_heldout(self) -> float:
        return float(np.mean(self.heldout))

    def to_dict(self) -> dict:
        return {"effect": self.effect, "refit": self.refit, "params": dict(self.params),
                "estimates": [e.to_dict() for e in self.estimates],
                "mean_residual_heldout": self.mean_heldout, "mean_residual_insample": float(np.mean(self.insample)),
                "removed_fraction": self.removed, "gain_over_noise": self.gain, "significant": self.significant,
                "explanation": self.explanation, "evidence": list(self.evidence),
                "effects": [dict(e) for e in self.effects], "command": self.command, "kind": self.kind,
                "set_value": self.set_value,
                "residual_heldout": self.heldout.tolist()}


@dataclass(frozen=True)
class Diagnosis:
    """Result of :func:`diagnose`; candidates ranked best first."""

    profile: str
    labels: tuple
    n_poses: int
    folds: int
    noise: np.ndarray
    noise_source: str
    base_residual: np.ndarray
    base_significant: bool
    candidates: tuple
    evidence: tuple
    verdict: str
    status: str = "ok"
    noise_note: str = ""

    @property
    def noise_floor(self) -> float:
        return float(np.mean(self.noise))

    @property
    def best(self) -> Candidate | None:
        """The top-ranked candidate (lowest held-out residual), significant or not."""
        return self.candidates[0] if self.candidates else None

    @property
    def significant(self) -> list[Candidate]:
        """The significant candidates, best first."""
        return [c for c in self.candidates if c.significant]

    def to_dict(self) -> dict:
        return {"profile": self.profile, "n_measurements": len(self.labels), "n_poses": self.n_poses,
                "folds": self.folds, "noise_floor": self.noise_floor, "noise_source": self.noise_source,
                "noise_note": self.noise_note,
                "mean_residual_base": float(np.mean(self.base_residual)),
                "base_significant": self.base_significant, "status": self.status, "verdict": self.verdict,
                "evidence": [e.to_dict() for e in self.evidence],
                "candidates": [c.to_dict() for c in self.candidates],
                "measurements": list(self.labels), "residual_base": self.base_residual.tolist(),
                "noise": self.noise.tolist()}


def pose_folds(measurements, k: int) -> list[np.ndarray]:
    """Split measurement indices into ``k`` folds by pose (all sweeps at a pose go together)."""
    keys = [tuple(np.round(np.asarray(m.position_mm, float), 0)) for m in measurements]
    poses = sorted(set(keys), key=lambda p: (p[2], np.hypot(p[0], p[1]), np.arctan2(p[1], p[0])))
    k = max(1, min(k, len(poses)))
    fold_of = {p: i % k for i, p in enumerate(poses)}
    return [np.array([j for j, key in enumerate(keys) if fold_of[key] == f]) for f in range(k)]


def _specs_of(profile) -> list[dict]:
    return effect_specs(profile)


def diagnose(profile, measurements, *, candidates=None, folds: int = 4, base_threshold: float = 0.3,
             min_removed: float = 0.25, min_gain: float = 0.3, explain_fraction: float = 0.8,
             min_floor: float = 0.003, noise_floor: float | None = None,
             refit_base: bool | None = None, geometry: bool = True, extra=()) -> Diagnosis:
    """Rank candidate effects by the error they remove on held-out poses.

    Parameters
    ----------
    profile : PrinterProfile
        The model to diagnose (its own effects are part of the base model).
    measurements : sequence of FrfMeasurement
    candidates : sequence of str, optional
        Effect names to try (default: every registered effect; those already in the profile are
        refitted).
    folds : int
        Cross-validation folds by pose (fewer if there are fewer poses; no held-out scoring with
        fewer than 3 poses).
    base_threshold, min_removed, min_gain, explain_fraction : float
        Significance thresholds (see the module docstring).
    min_floor : float
        Smallest noise floor used for significance (relative): noise-free data (a simulation,
        coherence 1) would otherwise make any linearisation or rounding error "significant".
    noise_floor : float, optional
        Use this noise floor instead of the estimates (``--noise-floor``).
    extra : sequence of str
        Plug-in effects to try as well (loaded with :func:`~ffcomp.model.effects.load_plugin`).
    geometry : bool
        Also try the geometry as the cause (delta radius, arm length, tower-angle frame; only with
        the default candidates), :mod:`ffcomp.loop.geometry_fit`.
    refit_base : bool, optional
        Refit the base dynamics alongside every candidate (and alone, as the first candidate);
        default: when the data have sweeps at 3 poses or more (:func:`~ffcomp.loop.fit.base_supported`).

    Returns
    -------
    Diagnosis
    """
    load_library()
    measurements = list(measurements)
    model0 = LpvModel.from_profile(profile, effects=False)
    check_measurements(model0, measurements)
    base_specs = _specs_of(profile)
    use_base = base_supported(measurements) if refit_base is None else bool(refit_base)
    if use_base:
        base_specs.insert(0, base_spec(model0))
    obj = Objective(measurements)
    base_model = _model_with(model0, base_specs)
    preds = obj.predictor(base_model)
    r0 = obj.per_measurement(base_model)
    nfs = noise_floors(measurements, override=noise_floor, predictions=preds)
    nu, src = nfs.values, nfs.source
    nu = np.where(np.isfinite(nu), nu, np.nanmedian(nu) if np.any(np.isfinite(nu)) else 0.0)
    nu = np.maximum(nu, min_floor)
    nu2 = float(np.mean(nu**2))
    e0 = float(np.mean(r0**2)) - nu2
    base_sig = e0 > base_threshold * nu2
    fold_idx = pose_folds(measurements, folds)
    n_poses = len({tuple(np.round(np.asarray(m.position_mm, float), 0)) for m in measurements})
    cv = len(fold_idx) >= 3
    fold_objs = []
    if cv:
        for test in fold_idx:
            train = np.setdiff1d(np.arange(len(measurements)), test)
            tr = [measurements[i] for i in train]
            te = [measurements[i] for i in test]
            fold_objs.append((test, Objective(tr, BatchPredictor(tr)), Objective(te, BatchPredictor(te))))
    # default: the library, the plug-ins the profile names and those asked for (``extra``); a plug-in
    # loaded for another purpose is not a candidate unless named
    own = {e["name"] for e in profile.effects}
    names = list(candidates) if candidates else sorted(
        n for n, c in EFFECTS.items() if c.plugin is None or n in own or n in set(extra))
    for name in names:
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r} (known: {', '.join(sorted(EFFECTS))})")
    present = [s["name"] for s in base_specs if s["name"] != BASE]
    # the profile's own effects were fitted without the missing one: refit them alongside each candidate
    old_free = [(i, p) for i, s in enumerate(base_specs)
                for p in (BASE_KEYS if s["name"] == BASE else EFFECTS[s["name"]].fit_params())]
    jobs = []
    for name in names:
        if name in present:
            continue
        cls = EFFECTS[name]
        specs = base_specs + [{"name": name, **{p: v.default for p, v in cls.params.items()}}]
        new = [(len(base_specs), p) for p in cls.fit_params() if not (use_base and p in cls.base_fixed)]
        jobs.append((name, False, specs, old_free + new, [False] * len(old_free) + [cls.grid] * len(new)))
    if geometry and candidates is None:
        g0 = geometry_spec(model0)
        for key in ("delta_radius_mm", "arm_length_mm"):
            specs = base_specs + [dict(g0)]
            jobs.append((key[:-3], False, specs, old_free + [(len(base_specs), key)],
                         [False] * (len(old_free) + 1)))
    if old_free and (candidates is None or use_base or any(n in present for n in names)):
        # first: a new effect must beat merely refitting the base and the profile's own effects (parsimony)
        own = "+".join((["base dynamics"] if use_base else []) + present)
        jobs.insert(0, (own, True, base_specs, old_free, [False] * len(old_free)))
    ev = evidence(features(base_model, measurements, preds, r0, nu))
    fb = fixed_band(measurements, preds, nu) if base_sig else None
    if fb is not None:
        ev = [fb] + list(ev)
    cands = []
    ref2 = float(np.mean(r0**2))  # reference of the new-effect candidates: base, or the refit if better
    for name, refit, specs, free, fresh in jobs:
        full = fit_free(model0, specs, free, measurements, fresh=fresh, objective=obj, tol=1e-6, max_nfev=30)
        x_full = np.array([e.value for e in full.estimates])
        held = np.empty(len(measurements))
        if cv:
            for test, otr, ote in fold_objs:
                # warm start from the all-data optimum: a few iterations suffice to score the fold
                fr = fit_free(model0, specs, free, None, x0=x_full, objective=otr, before=base_specs, tol=1e-4,
                              max_nfev=8)
                held[test] = ote.per_measurement(_model_with(model0, fr.effects))
        else:
            held = full.residual_after
        gain = float(np.mean(r0**2) - np.mean(held**2))
        removed = min(gain / e0, 1.0) if e0 > 0 else 0.0  # > 1 only when held out beats the noise estimate
        sig = bool(base_sig and removed >= min_removed and gain >= min_gain * nu2)
        if not refit and ref2 < float(np.mean(r0**2)):
            inc = ref2 - float(np.mean(held**2))  # what the new effect adds to the refit alone
            sig = sig and inc >= min_gain * nu2 and inc >= min_removed * max(ref2 - nu2, 0.0)
        if refit:
            ref2 = min(ref2, float(np.mean(held**2)))
        if full.effects[-1]["name"] == GEOM and not refit:
            key = name + "_mm"
            setv, words = profile_geometry_change(profile, key, full.effects[-1][key])
            cands.append(Candidate(name, False, {key: full.effects[-1][key]}, tuple(full.estimates), held,
                                   full.residual_after, float(removed), gain / nu2 if nu2 else float("inf"), sig,
                                   words, (), tuple(full.effects), "geometry", setv))
            continue
        mine = [e for e in full.effects if e["name"] != BASE] if refit else [full.effects[-1]]
        keys = {k for e in mine for k in getattr(EFFECTS[e["name"]], "evidence_keys", ())}
        fitted0 = _model_with(model0, [e for e in full.effects if e["name"] == BASE])
        expl = "; ".join(EFFECTS[e["name"]](**{p: v for p, v in e.items() if p != "name"}).explain(fitted0)
                         for e in mine)
        if refit and use_base:
            expl = "; ".join(x for x in (explain_base(base_specs[0], full.effects[0]), expl) if x)
        params = {p: v for p, v in full.effects[-1].items() if p != "name"} if not refit else {
            f"{e['name']}:{p}": v for e in full.effects for p, v in e.items() if p != "name"}
        cands.append(Candidate(name, refit, params, tuple(full.estimates), held, full.residual_after,
                               float(removed), gain / nu2 if nu2 else float("inf"), sig, expl,
                               tuple(e.text for e in ev if e.key in keys and e.strength >= 0.5), tuple(full.effects)))
    if geometry and candidates is None:
        rot = _frame_candidate(profile, model0, base_specs, obj, r0, e0, nu2, base_sig, min_removed, min_gain)
        if rot is not None and rot.gain >= min_gain:  # a rotation that does not help is no candidate
            cands.append(rot)
    cands.sort(key=lambda c: (not c.significant, c.mean_heldout))
    for j, c in enumerate(cands[:2]):
        if c.significant and not c.refit and c.kind == "effect":
            txt = _pose_consistency(model0, [dict(e) for e in c.effects], len(c.effects) - 1, measurements, c)
            if txt:
                cands[j] = replace(c, evidence=(txt,) + c.evidence)
    sig = [c for c in cands if c.significant]
    status = ("ok" if not base_sig else "unexplained" if not sig else
              "explained" if sig[0].removed >= explain_fraction else "partial")
    if status == "explained" and np.mean(sig[0].heldout**2) > 4.0 * nu2:
        status = "partial"  # most of a large error, but what is left is still twice the noise or more
    if fb is not None and status == "partial" and np.mean(sig[0].heldout**2) > 4.0 * nu2:
        status = "unexplained"  # a fixed-frequency misfit the best candidate leaves: outside the library
    verdict = _verdict(r0, nu, status, cands, cv, fb)
    labels = tuple(m.path or m.label for m in measurements)
    return Diagnosis(profile.name, labels, n_poses, len(fold_idx) if cv else 0, nu, src, r0, base_sig,
                     tuple(cands), tuple(ev), verdict, status, nfs.note)


def _frame_candidate(profile, model0, base_specs, obj, r0, e0, nu2, base_sig, min_removed, min_gain):
    """The tower angles rotated by multiples of 30 deg (e.g. the firmware frame on paper-frame data),
    scored without fitting (nothing is fitted, so in-sample is held-out)."""
    g0 = geometry_spec(model0)
    tried = []
    for rot in range(30, 360, 30):
        spec = dict(g0, rotation_deg=float(rot if rot <= 180 else rot - 360))
        try:
            r = obj.per_measurement(_model_with(model0, base_specs + [spec]))
        except (ValueError, np.linalg.LinAlgError):
            continue  # a pose out of reach in the rotated frame
        tried.append((spec, r))
    if not tried:
        return None
    # rotations 120 deg apart only relabel the towers: among the (near) ties prefer a named frame
    low = min(float(np.mean(r**2)) for _, r in tried)
    ang0 = np.asarray(profile.geometry.tower_angles_deg, float)

    def pref(item):
        new = (ang0 + item[0]["rotation_deg"]) % 360.0
        named = 0 if np.allclose(new, [0, 120, 240]) else 1 if np.allclose(new, [210, 330, 90]) else 2
        return (named, abs(item[0]["rotation_deg"]))

    spec, r = min((t for t in tried if np.mean(t[1] ** 2) <= 1.02 * low), key=pref)
    gain = float(np.mean(r0**2) - np.mean(r**2))
    removed = min(gain / e0, 1.0) if e0 > 0 else 0.0
    sig = bool(base_sig and removed >= min_removed and gain >= min_gain * nu2)
    setv, words = profile_geometry_change(profile, "rotation_deg", spec["rotation_deg"])
    return Candidate("tower_frame", False, {"rotation_deg": spec["rotation_deg"]}, (), r, r, float(removed),
                     gain / nu2 if nu2 else float("inf"), sig, words, (), tuple(base_specs) + (spec,), "geometry", setv)


def _pose_consistency(model0, specs, k, measurements, cand) -> str | None:
    """Fit the candidate pose by pose: is its parameter the same everywhere (physical) or not?"""
    cls = EFFECTS[cand.effect]
    free = [(k, p) for p in cls.fit_params()]
    x_full = np.array([specs[k][p] for _, p in free])
    groups: dict = {}
    for m in measurements:
        groups.setdefault(tuple(np.round(np.asarray(m.position_mm, float), 0)), []).append(m)
    if len(groups) < 3:
        return None
    vals, ses = [], []
    for ms in groups.values():
        fr = fit_free(model0, specs, free, ms, x0=x_full, max_nfev=30, tol=1e-6)
        vals.append([e.value for e in fr.estimates])
        ses.append([e.stderr if not e.at_bound else np.nan for e in fr.estimates])
    vals, ses = np.array(vals), np.array(ses)
    parts = []
    order = sorted(range(len(free)), key=lambda i: -abs(x_full[i] - cls.params[free[i][1]].default)
                   / np.ptp(cls.params[free[i][1]].fit_range))
    for i in order[:2]:
        p = cls.params[free[i][1]]
        if abs(x_full[i] - p.default) < 0.01 * np.ptp(p.fit_range):
            continue
        ok = np.isfinite(ses[:, i]) & (ses[:, i] < 0.1 * np.ptp(p.fit_range))
        if ok.sum() < 3:
            continue
        v = vals[ok, i]
        lo, hi = np.percentile(v, [25, 75])
        med = float(np.median(v))
        tol = max(0.15 * abs(x_full[i] - p.default), 0.02 * np.ptp(p.fit_range))
        unit = f" {p.unit}" if p.unit else ""
        txt = f"{free[i][1]} {med:.4g} ({lo:.4g} to {hi:.4g}){unit}"
        if abs(med - x_full[i]) > tol:
            txt += f" but {x_full[i]:.4g} from all poses together — not one value"
        elif hi - lo < tol:
            txt += " — the same at every pose"
        else:
            txt += " — varies from pose to pose"
        parts.append(txt)
    if not parts:
        return None
    return f"fitted pose by pose ({len(groups)} poses; median, quartiles): " + "; ".join(parts)


def _verdict(r0, nu, status, cands, cv, fb=None) -> str:
    m0, mn = float(np.mean(r0)), float(np.mean(nu))
    how = "on held-out poses" if cv else "in sample (too few poses to hold any out)"
    if status == "ok":
        return (f"The model matches the measurements to the noise floor (mean residual {m0:.4f}, noise {mn:.4f}): "
                "nothing significant to diagnose.")
    if status == "unexplained":
        best = cands[0] if cands else None
        tail = (f" The best candidate, {best.label}, removes {max(best.removed, 0):.0%} of the error above the "
                f"noise {how} and leaves {best.mean_heldout:.4f}, {best.mean_heldout / mn:.1f}x the noise."
                if best else "")
        band = f" The evidence points at it: {fb.text}." if fb is not None else ""
        return (f"The model misses something (mean residual {m0:.4f}, noise {mn:.4f}) that no candidate effect "
                f"explains.{band}{tail} Look at where it fails (ffcomp validate) and the evidence below.")
    sig = [c for c in cands if c.significant]
    c = sig[0]
    left = float(np.mean(c.heldout))
    alt = ""
    if len(sig) > 1:
        alt = (" Partial alternatives (they remove part of the same error, less of it): "
               + ", ".join(f"{s.label} ({s.removed:.0%})" for s in sig[1:]) + ".")
    fit = f" Apply it with: {c.command}"
    if status == "partial":
        return (f"No candidate explains all of it (mean residual {m0:.4f}, noise {mn:.4f}). The best, {c.label}, "
                f"removes {c.removed:.0%} of the error above the noise {how} (-> {left:.4f}): fit it and diagnose "
                f"again (a second effect?), or something outside the library is missing.{alt}{fit}")
    more = (" Some error remains above the noise: after fitting it, diagnose again."
            if np.mean(c.heldout**2) > 1.5**2 * np.mean(nu**2) else "")
    if c.kind == "geometry":
        twins = [o for o in sig[1:] if o.kind == "geometry" and np.mean(o.heldout**2) <= 1.1 * np.mean(c.heldout**2)]
        also = "".join(f" Nearly as good: {o.explanation} (at these poses the two are hard to tell apart; sweeps "
                       "at more heights and radii separate them)." for o in twins)
        return (f"Geometry, not a physical effect: {c.explanation}.{also} Correcting it removes {c.removed:.0%} of the "
                f"error above the noise {how} (mean residual {m0:.4f} -> {left:.4f}, noise {mn:.4f}). Fix the "
                f"profile: {c.command}, then diagnose again.{more}")
    if c.refit and c.effect == "base dynamics":
        return (f"No physical effect is missing: the two-sweep identification's base dynamics are off "
                f"({c.explanation.removeprefix('base dynamics: ')}). Refitting them from all the sweeps removes "
                f"{c.removed:.0%} of the error above the noise {how} (mean residual {m0:.4f} -> {left:.4f}, noise "
                f"{mn:.4f}).{more}{fit}")
    if c.refit:
        return (f"Nothing new is missing: the profile's own effects ({c.effect}) have the wrong parameters. "
                f"Refitting them removes {c.removed:.0%} of the error above the noise {how} (mean residual "
                f"{m0:.4f} -> {left:.4f}, noise {mn:.4f}).{more}{fit}")
    return (f"Most likely missing: {c.label}. It removes {c.removed:.0%} of the error above the noise {how} "
            f"(mean residual {m0:.4f} -> {left:.4f}, noise {mn:.4f}).{more}{alt}{fit}")
