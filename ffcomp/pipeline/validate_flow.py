"""Validation flow: measurements -> validate / diagnose / fit -> reports; virtual measurements; FRF
from time-domain data.  Plain objects out; the CLI prints and writes them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..measure.dataset import load_dataset
from ..measure.frf_file import save_frf
from ..model.effects import EFFECTS, load_library

__all__ = ["ValidateRun", "FitRun", "profile_label", "load_data", "run_validate", "run_diagnose", "run_fit",
           "run_virtual", "run_frf", "parse_effect_args", "effects_catalogue", "base_name"]


@dataclass(frozen=True)
class ValidateRun:
    """``report`` for ``--profile``; ``before`` and ``comparison`` with ``--compare``."""

    report: object
    before: object = None
    comparison: dict | None = None
    skipped: tuple = ()

    def to_dict(self) -> dict:
        d = self.report.to_dict()
        if self.comparison is not None:
            d["compare"] = self.comparison
        d["skipped"] = [{"path": p, "reason": r} for p, r in self.skipped]
        return d


@dataclass(frozen=True)
class FitRun:
    """The fit and the profile it produced; ``noise_floor`` of the data for context."""

    result: object
    profile: object
    noise_floor: float
    skipped: tuple = field(default=())
    noise_note: str = ""

    def to_dict(self) -> dict:
        return {**self.result.to_dict(), "noise_floor": self.noise_floor, "noise_note": self.noise_note,
                "profile_name": self.profile.name}


def load_data(path):
    """Measurements in ``path`` and the files skipped (path, reason)."""
    skipped: list = []
    ms = load_dataset(path, skipped=skipped)
    return ms, tuple(skipped)


def profile_label(profile) -> str:
    """Short label of a profile for reports: its file name, or its name if it has no file."""
    return Path(profile.source).name if profile.source and not profile.source.startswith("<") else profile.name


def run_validate(data, profile, compare=None, *, noise_floor: float | None = None) -> ValidateRun:
    """Validate ``profile`` (and optionally the ``compare`` profile, as "before") against ``data``."""
    from ..loop.validate import compare as cmp
    from ..loop.validate import validate

    ms, skipped = load_data(data)
    rep = validate(profile, ms, name=profile_label(profile), noise_floor=noise_floor)
    if compare is None:
        return ValidateRun(rep, skipped=skipped)
    before = validate(compare, ms, name=profile_label(compare), noise_floor=noise_floor)
    return ValidateRun(rep, before, cmp(before, rep), skipped)


def run_diagnose(data, profile, *, candidates=None, folds: int = 4, noise_floor: float | None = None,
                 refit_base: bool | None = None, extra=()):
    """Diagnose ``profile`` against ``data``; returns ``(Diagnosis, skipped)``."""
    from ..loop.diagnose import diagnose

    ms, skipped = load_data(data)
    return diagnose(profile, ms, candidates=candidates, folds=folds, noise_floor=noise_floor,
                    refit_base=refit_base, extra=extra), skipped


def base_name(name: str) -> str:
    """A profile name without the suffixes the loop appends (``+ fitted ..``, ``(identified from ..)``)."""
    for tail in (" + fitted", " (identified from"):
        name = name.split(tail)[0]
    return name.strip()


def run_fit(data, profile, add=(), *, set_values=(), free=(), refit: bool = True, base: bool | None = None,
            noise_floor: float | None = None) -> FitRun:
    """Fit ``add`` (and the profile's own effects unless ``refit`` is False, and the base dynamics
    when the data support it unless ``base`` is False); the new profile."""
    from ..loop.fit import fit_effects, fitted_profile
    from ..measure.noise import noise_floors

    ms, skipped = load_data(data)
    res = fit_effects(profile, ms, add, refit=refit, set_values=set_values, free_extra=free, base=base)
    names = ", ".join(e["name"] for e in res.effects) or "no effects"
    new = fitted_profile(profile, res).with_(name=f"{base_name(profile.name)} + fitted {names}", source=None)
    from ..measure.predict import BatchPredictor
    from ..model.lpv import LpvModel

    nfs = noise_floors(ms, override=noise_floor, predictions=BatchPredictor(ms)(LpvModel.from_profile(new)))
    return FitRun(res, new, nfs.mean, skipped, nfs.note)


def parse_effect_args(args) -> list[dict]:
    """``NAME``, ``NAME=VALUE``, ``NAME:param=VALUE`` (repeatable) -> profile effect dicts (merged per name)."""
    from ..loop.fit import parse_assignment

    out: dict[str, dict] = {}
    for a in args:
        name, param, value = parse_assignment(a)
        d = out.setdefault(name, {"name": name})
        if value is not None:
            d[param] = value
    return list(out.values())


def run_virtual(profile, effects, out_dir, *, noise: float = 0.02, seed: int = 0, freq_hz=None,
                heights_mm=(30.0, 130.0), offset_mm=None, truth=None, averages: int | None = None,
                averages_key: bool = True, all_carriages: bool = False) -> list[Path]:
    """Write virtual measurements of ``profile`` with hidden ``effects`` into ``out_dir``.

    ``truth``: optional path for the profile with the hidden effects (a TOML spoiler file).
    """
    from ..measure.virtual import file_name, measurement_plan, virtual_measurements
    from ..model.effects import build_effects
    from ..profile import save_profile

    build_effects(effects)  # validate names and values before writing anything
    plan = measurement_plan(profile, offset_mm=offset_mm, heights_mm=heights_mm, all_carriages=all_carriages)
    ms = virtual_measurements(profile, effects, freq_hz=freq_hz, noise=noise, seed=seed, plan=plan,
                              averages=averages, averages_key=averages_key)
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, (it, m) in enumerate(zip(plan, ms)):
        p = d / file_name(i, it)
        save_frf(m, p)
        paths.append(p)
    if truth:
        from ..model.effects import with_plugin_refs

        hidden = profile.with_(effects=with_plugin_refs(tuple(profile.effects) + tuple(effects)),
                               name=f"{profile.name} + hidden {', '.join(e['name'] for e in effects) or 'nothing'}")
        save_profile(hidden, truth)
    return paths


def run_frf(response, command, *, response_column, command_column, kind, position_mm, input_, output,
            out=None, **kw):
    """Estimate an FRF from time series files; write it (FRF_FORMAT) if ``out`` is given."""
    from ..measure.timedomain import frf_from_time, read_timeseries

    resp = read_timeseries(response)
    cmd = read_timeseries(command) if command else resp
    est = frf_from_time(cmd, command_column, resp, response_column, **kw)
    src = f"ffcomp frf: H1 of {Path(response).name}:{response_column} over {Path(command or response).name}:" \
          f"{command_column}"
    meas = est.to_measurement(kind, position_mm, input_, output, src)
    if out:
        save_frf(meas, out)
    return est, meas


def effects_catalogue() -> list[dict]:
    """Every effect in the library: name, summary, parameters (default, unit, range, fitted?)."""
    load_library()
    out = []
    for name in sorted(EFFECTS):
        cls = EFFECTS[name]
        doc = (cls.__module__ and __import__(cls.__module__, fromlist=["x"]).__doc__ or "").strip().splitlines()
        out.append({"name": name, "summary": cls.summary or (doc[0] if doc else ""),
                    "params": [{"name": k, "default": p.default, "unit": p.unit, "lo": p.lo, "hi": p.hi,
                                "search": list(p.fit_range), "fitted": k in cls.fit_params(), "doc": p.doc}
                               for k, p in cls.params.items()]})
    return out
