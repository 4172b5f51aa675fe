"""Fitting effect parameters to measured FRFs (coherence-weighted complex least squares).

The noise of a measured FRF is relative: an H1 estimate's error has variance
``|H|^2 (1 - g^2) / (g^2 n)``, and the virtual measurements' is ``rel^2 |H|^2``.  The fit therefore
minimises the coherence-weighted relative complex error, every measurement counting alike:

    cost = 1/N sum_m  1/F_m sum_f  w_mf |H_pred,mf - H_meas,mf|^2 / |H_meas,mf|^2

(``w`` = coherence, or 1).  That keeps the information above the resonances, where the magnitude
is small but a lag or a delay shows most clearly.  Reports and the held-out scores of
:mod:`ffcomp.loop.diagnose` use the normalised complex residual of ``ffcomp validate``
(:meth:`Objective.per_measurement`).  Parameters are scaled to their search range (``Param.search``),
bounded by it, started from the best point of a small grid (plus the defaults or the current
values) and refined with :func:`scipy.optimize.least_squares` (trust-region reflective).
Standard errors come from the Jacobian at the optimum (``s^2 (J^T J)^-1``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares

from ..errors import SolverError
from ..measure.predict import BatchPredictor, check_measurements
from ..model.effects import EFFECTS, load_library
from ..model.lpv import LpvModel
from .base_fit import BASE, BASE_KEYS, apply_base, base_spec, base_table
from .geometry_fit import GEOM, apply_geometry, geometry_table

__all__ = ["ParamEstimate", "FitResult", "Objective", "fit_effects", "fit_free", "residuals_of",
           "parse_assignment", "base_supported", "effect_specs", "fitted_profile"]


@dataclass(frozen=True)
class ParamEstimate:
    """One fitted parameter: value, approximate standard error, unit, whether it ended on a bound."""

    effect: str
    param: str
    value: float
    stderr: float
    unit: str
    start: float
    lo: float
    hi: float
    at_bound: bool

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class FitResult:
    """Result of :func:`fit_effects` / :func:`fit_free`.

    Attributes
    ----------
    effects : tuple of dict
        The complete ``[[effects]]`` list after the fit (profile form).
    estimates : tuple of ParamEstimate
    residual_before, residual_after : ndarray, shape (N,)
        Normalised complex residual of each measurement before and after.
    success : bool
    message : str
    nfev : int
    """

    effects: tuple
    estimates: tuple
    residual_before: np.ndarray
    residual_after: np.ndarray
    success: bool
    message: str
    nfev: int
    labels: tuple = field(default=())
    #: the refitted base dynamics (``{"name": "base", "m": ..}``, tower means) and their start, or None
    base: dict | None = None
    base_start: dict | None = None

    @property
    def values(self) -> np.ndarray:
        return np.array([e.value for e in self.estimates])

    def value(self, effect: str, param: str) -> float:
        """Fitted (or fixed) value of ``effect:param`` in :attr:`effects`."""
        for e in self.effects:
            if e["name"] == effect:
                return float(e[param])
        raise KeyError(f"{effect}:{param}")

    def to_dict(self) -> dict:
        return {
            "effects": [dict(e) for e in self.effects],
            "estimates": [e.to_dict() for e in self.estimates],
            "mean_residual_before": float(np.mean(self.residual_before)),
            "mean_residual_after": float(np.mean(self.residual_after)),
            "residual_before": self.residual_before.tolist(),
            "residual_after": self.residual_after.tolist(),
            "measurements": list(self.labels),
            "success": self.success,
            "message": self.message,
            "nfev": self.nfev,
            "base": self.base,
            "base_start": self.base_start,
        }


class Objective:
    """Fit residuals (relative, coherence-weighted) and reported residuals of a data set for a model."""

    def __init__(self, measurements, predictor: BatchPredictor | None = None):
        self.measurements = list(measurements)
        self.predictor = predictor or BatchPredictor(self.measurements)
        n = len(self.measurements)
        self._sw = [np.sqrt(m.weights) for m in self.measurements]
        self._den = [np.sqrt(np.sum(m.weights * np.abs(m.H) ** 2) * n) for m in self.measurements]
        self._rel = [np.sqrt(m.weights / (len(m.H) * n)) / np.maximum(np.abs(m.H), 1e-300 + 1e-12 * np.max(np.abs(m.H)))
                     for m in self.measurements]

    def per_measurement(self, model) -> np.ndarray:
        """Normalised complex residual of each measurement, shape (N,)."""
        Hs = self.predictor(model)
        n = len(self.measurements)
        return np.array([np.linalg.norm(sw * (h - m.H)) / d * np.sqrt(n)
                         for sw, h, m, d in zip(self._sw, Hs, self.measurements, self._den)])

    def vector(self, model) -> np.ndarray:
        """The fit's residual vector (real and imaginary parts; see the module docstring)."""
        Hs = self.predictor(model)
        parts = [g * (h - m.H) for g, h, m in zip(self._rel, Hs, self.measurements)]
        r = np.concatenate(parts)
        return np.concatenate([r.real, r.imag])


def residuals_of(model, measurements) -> np.ndarray:
    """Normalised complex residual of each measurement (coherence-weighted), shape (N,)."""
    return Objective(measurements).per_measurement(model)


def parse_assignment(text: str) -> tuple[str, str | None, float | None]:
    """``NAME``, ``NAME=VALUE`` (primary parameter) or ``NAME:PARAM=VALUE`` -> (name, param, value)."""
    load_library()
    head, eq, val = text.partition("=")
    name, _, param = head.strip().partition(":")
    name = name.strip()
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r} (known: {', '.join(sorted(EFFECTS))})")
    cls = EFFECTS[name]
    param = param.strip() or None
    if param is not None and param not in cls.params:
        raise ValueError(f"effect {name!r} has no parameter {param!r} (known: {', '.join(cls.params)})")
    if not eq:
        return name, param, None
    try:
        value = float(val)
    except ValueError:
        raise ValueError(f"{text!r}: {val!r} is not a number") from None
    return name, param or cls.primary(), value


def _model_with(model0: LpvModel, specs) -> LpvModel:
    effs = []
    for s in specs:
        s = dict(s)
        name = s.pop("name")
        if name == BASE:
            model0 = apply_base(model0, s)
            continue
        if name == GEOM:
            model0 = apply_geometry(model0, s)
            continue
        effs.append(EFFECTS[name](**s))
    return model0.with_effects(effs)


def _param(spec: dict, p: str, tables: dict | None = None):
    """The :class:`Param` of parameter ``p`` of the entry ``spec`` (an effect or the base)."""
    if spec["name"] == BASE:
        return (tables or {}).get(BASE, base_table(spec))[p]
    if spec["name"] == GEOM:
        return (tables or {}).get(GEOM, geometry_table(spec))[p]
    return EFFECTS[spec["name"]].params[p]


def _grid(free, specs, fresh, n_max: int = 64, seed: int = 0) -> np.ndarray:
    """Start points in normalised coordinates: a grid over fresh parameters, current values otherwise."""
    axes = []
    for (k, p, lo, hi), is_fresh in zip(free, fresh):
        cur = (float(specs[k][p]) - lo) / (hi - lo)
        if is_fresh:
            pts = [0.1, 0.5, 0.9] if sum(fresh) > 1 else [0.05, 0.25, 0.5, 0.75, 0.95]
            axes.append(sorted({float(np.clip(cur, 0, 1)), *pts}))
        else:
            axes.append([float(np.clip(cur, 0, 1))])
    size = int(np.prod([len(a) for a in axes], dtype=float))
    if size <= n_max:
        return np.array(list(itertools.product(*axes)))
    # too many combinations to list: the current point plus random grid points
    rng = np.random.default_rng(seed)
    cur = np.array([a[0] if len(a) == 1 else float(np.clip((float(specs[k][p]) - lo) / (hi - lo), 0, 1))
                    for a, (k, p, lo, hi) in zip(axes, free)])
    picks = np.array([[a[rng.integers(len(a))] for a in axes] for _ in range(n_max - 1)])
    return np.vstack([cur, picks])


def fit_free(model0: LpvModel, specs, free, measurements, *, fresh=None, x0=None, objective=None,
             max_nfev: int | None = None, n_starts: int = 1, before=None, tol: float = 1e-10,
             tables: dict | None = None) -> FitResult:
    """Fit the ``free`` parameters of the effect list ``specs`` on top of ``model0``.

    Parameters
    ----------
    model0 : LpvModel
        The model without any of ``specs`` (its own ``effects`` are ignored).
    specs : list of dict
        Effects in application order, profile form (``{"name": ..., param: value}``, all params).
    free : list of (int, str)
        (index into ``specs``, parameter name) to fit; bounds from ``Param.fit_range``.
    fresh : list of bool, optional
        Which free parameters start from a grid (new effects) rather than their current value.
    x0 : ndarray, optional
        Start (physical values, one per free parameter); skips the grid.
    before : list of dict, optional
        The effect list the "before" residuals refer to (default: ``specs`` as given).
    tol : float
        ``xtol`` and ``ftol`` of :func:`scipy.optimize.least_squares` (parameters scaled to 0..1).
    tables : dict, optional
        ``{"base": {param: Param}}``: the bounds of the base dynamics entry (default: around the
        entry's own values, :func:`~ffcomp.loop.base_fit.base_table`).
    """
    load_library()
    specs = [dict(s) for s in specs]
    tables = dict(tables or {})
    for s in specs:
        if s["name"] == BASE and BASE not in tables:
            tables[BASE] = base_table(s)
        if s["name"] == GEOM and GEOM not in tables:
            tables[GEOM] = geometry_table(s)
    model0 = model0.with_effects(())
    obj = objective or Objective(measurements)
    bounds = []
    for k, p in free:
        lo, hi = _param(specs[k], p, tables).fit_range
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            raise SolverError(f"parameter {specs[k]['name']}:{p} has no finite fit range")
        bounds.append((k, p, float(lo), float(hi)))
    lo_v = np.array([b[2] for b in bounds])
    wid = np.array([b[3] - b[2] for b in bounds])
    before = obj.per_measurement(_model_with(model0, specs if before is None else before))

    def physical(x):
        x = np.clip(x, 0.0, 1.0)
        x = np.where(x < 1e-6, 0.0, np.where(x > 1 - 1e-6, 1.0, x))  # a value on a bound is the bound
        return lo_v + x * wid

    def specs_at(x):
        out = [dict(s) for s in specs]
        for (k, p, _, _), v in zip(bounds, physical(x)):
            out[k][p] = float(v)
        return out

    bad = None

    def fun(x):
        nonlocal bad
        try:
            return obj.vector(_model_with(model0, specs_at(x)))
        except (ValueError, np.linalg.LinAlgError):
            if bad is None:
                bad = np.full_like(obj.vector(model0), 10.0)
            return bad

    if not bounds:
        return FitResult(tuple(specs), (), before, before, True, "nothing to fit", 0, _labels(obj))
    if x0 is not None:
        starts = [(np.asarray(x0, float) - lo_v) / wid]
    else:
        fresh = [True] * len(bounds) if fresh is None else list(fresh)
        grid = _grid(bounds, specs, fresh)
        costs = np.array([np.sum(fun(x) ** 2) for x in grid])
        order = np.argsort(costs)
        starts = [grid[i] for i in order[:max(1, n_starts)]]
    best = None
    nfev = 0
    for s in starts:
        try:
            r = least_squares(fun, np.clip(s, 0, 1), bounds=(0.0, 1.0), method="trf", x_scale=1.0,
                              max_nfev=max_nfev or 60 * (len(bounds) + 1), xtol=tol, ftol=tol)
        except (ValueError, np.linalg.LinAlgError) as e:
            raise SolverError(f"effect fit failed: {e}") from e
        nfev += r.nfev
        if best is None or r.cost < best.cost:
            best = r
    x = best.x
    se = _stderr(best, wid)
    final = specs_at(x)
    after = obj.per_measurement(_model_with(model0, final))
    est = tuple(
        ParamEstimate(final[k]["name"], p, float(v), float(e), _param(final[k], p, tables).unit,
                      float(specs[k][p]), lo, hi, bool(xi < 1e-4 or xi > 1 - 1e-4))
        for (k, p, lo, hi), v, e, xi in zip(bounds, physical(x), se, x))
    return FitResult(tuple(final), est, before, after, bool(best.success), str(best.message), nfev, _labels(obj))


def _stderr(res, wid) -> np.ndarray:
    """Standard errors ``sqrt(diag(s^2 (J^T J)^-1))`` over the parameters not on a bound (NaN there)."""
    x = res.x
    inner = (x > 1e-4) & (x < 1 - 1e-4)
    se = np.full(len(x), np.nan)
    if not inner.any():
        return se
    J = res.jac[:, inner]
    s2 = 2.0 * res.cost / max(len(res.fun) - int(inner.sum()), 1)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        return se
    se[inner] = np.sqrt(np.clip(np.diag(cov), 0, None)) * wid[inner]
    return se


def _labels(obj: Objective) -> tuple:
    return tuple((m.path or m.label) for m in obj.measurements)


def base_supported(measurements, *, min_poses: int = 3) -> bool:
    """Whether a data set can carry a refit of the base dynamics: sweeps at ``min_poses`` poses or more."""
    poses = {tuple(np.round(np.asarray(m.position_mm, float), 0)) for m in measurements}
    return len(poses) >= min_poses and len(list(measurements)) >= 2 * min_poses


def effect_specs(profile) -> list[dict]:
    """The profile's ``[[effects]]`` with every parameter filled in (defaults where absent)."""
    from pathlib import Path

    from ..model.effects import build_effects

    src = profile.source
    build_effects(profile.effects, Path(src).parent if src and not str(src).startswith("<") else None)  # plug-ins
    specs = []
    for e in profile.effects:
        e = dict(e)
        cls = EFFECTS[e["name"]]
        specs.append({"name": cls.name, **{k: float(e.get(k, p.default)) for k, p in cls.params.items()}})
    return specs


def fit_effects(profile, measurements, add=(), *, refit: bool = True, set_values=(), free_extra=(),
                n_starts: int = 1, base: bool | None = None) -> FitResult:
    """Add effects to a profile and fit their parameters (and, with ``refit``, those already there).

    Parameters
    ----------
    profile : PrinterProfile
    measurements : sequence of FrfMeasurement
    add : sequence of str
        Effect names to add (each with its default parameters, then fitted).
    refit : bool
        Also fit the fitted parameters (``Effect.fit``) of the profile's existing effects.
    set_values : sequence of (name, param, value)
        Fixed values to set before fitting (e.g. a measured ``belt_span:loop_mm``).
    free_extra : sequence of (name, param)
        Extra parameters to fit beyond each effect's defaults.
    base : bool, optional
        Refit the base dynamics (m, c, b, k, b_nt, d0, d1, d2) jointly with the effects
        (:mod:`ffcomp.loop.base_fit`); default: when the data have sweeps at 3 poses or more.
        Parameters an effect shares with the base (``Effect.base_fixed``, e.g. tower A's scale
        factors) are then held at their values.

    Returns
    -------
    FitResult ; :attr:`FitResult.effects` holds the effects, :attr:`FitResult.base` the refitted
    base (or None); :func:`fitted_profile` applies both.
    """
    load_library()
    measurements = list(measurements)
    specs = effect_specs(profile)
    model0 = LpvModel.from_profile(profile, effects=False)
    check_measurements(model0, measurements)
    use_base = base_supported(measurements) if base is None else bool(base)
    off = 1 if use_base else 0
    if use_base:
        specs.insert(0, base_spec(model0))
    n_old = len(specs)
    for name in add:
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r} (known: {', '.join(sorted(EFFECTS))})")
        if any(s["name"] == name for s in specs):
            continue
        specs.append({"name": name, **{k: p.default for k, p in EFFECTS[name].params.items()}})
    for name, param, value in set_values:
        hits = [s for s in specs if s["name"] == name]
        if not hits:
            raise ValueError(f"--set {name}:{param}: effect {name!r} is neither in the profile nor added")
        hits[0][param] = float(value)
    free, fresh = [], []
    if use_base:
        free += [(0, p) for p in BASE_KEYS]
        fresh += [False] * len(BASE_KEYS)
    for k, s in enumerate(specs[off:], off):
        if k < n_old and not refit:
            continue
        cls = EFFECTS[s["name"]]
        names = list(cls.fit_params())
        names += [p for n, p in free_extra if n == s["name"] and p not in names]
        fixed = {p for n, p, _ in set_values if n == s["name"]}
        if use_base:
            fixed |= set(getattr(cls, "base_fixed", ()))
        for p in names:
            if p not in fixed:
                free.append((k, p))
                fresh.append(k >= n_old and cls.grid)
    res = fit_free(model0, specs, free, measurements, fresh=fresh, n_starts=n_starts, before=specs[:n_old])
    if not use_base:
        return res
    return replace(res, effects=tuple(res.effects[1:]), base=dict(res.effects[0]), base_start=dict(specs[0]))


def fitted_profile(profile, result: FitResult):
    """``profile`` with the fit's effects and, if refitted, base dynamics."""
    from ..model.effects import with_plugin_refs
    from .base_fit import apply_base_to_profile

    out = profile.with_(effects=with_plugin_refs(result.effects))
    return apply_base_to_profile(out, result.base) if result.base is not None else out
