"""The simulation bench: command variants (baselines and, later, compensation) on stress moves.

:data:`VARIANTS` maps a name to ``fn(profile, t_s, xyz_ref_m, q_ref_m) -> q_cmd_m`` (all (N, 3) SI
arrays on the uniform grid ``t_s``).  Built in: ``none`` (the planned carriage path as is) and the
Klipper input shapers, each tuned two ways: ``<shaper>-centre`` at the coupled x/y mode of the model
at the bed centre ``(0, 0, z)`` and ``<shaper>-avg`` at that mode's mean over the bed (both lateral
modes over a 10 mm grid at the same height).  Shapers act as Klipper applies them on a delta: on
the Cartesian X and Y (not Z) before the inverse kinematics.  The compensation module registers
``lpv`` and ``lti-centre`` with :func:`register_variant`; the bench runs every registered row.
Modules named in :data:`PROVIDERS` are imported before a bench run (missing ones are skipped), so
a module that registers its variants at import time (e.g. ``ffcomp/compensate/variants.py``)
shows up without the bench importing it by hand.

:func:`run_bench` runs every variant on every case in one batched integration per case
(:meth:`DeltaPlant.simulate` with R = number of variants) and scores them with
:func:`ffcomp.sim.metrics.evaluate` against the planned reference.  Cases: the synthetic square and
zig-zag at 10 000 mm/s^2 translated to the bed centre and 100 mm out, and windows of the stress
samples ``samples/gcode/stress_*.gcode`` when they are found (they are optional).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..kinematics import inverse
from ..model.lpv import LpvModel
from ..model.modes import modes, workspace_grid
from . import metrics, shapers
from .moves import Trajectory, load_gcode_trajectory, pattern
from .plant import DeltaPlant

__all__ = ["VARIANTS", "PROVIDERS", "load_providers", "VariantFn", "register_variant", "describe_variant",
           "shaper_tuning", "ShaperTuning", "bench_cases", "run_bench", "run_case", "BenchResult", "CaseResult",
           "gcode_cases", "crop_at_rest", "markdown_table", "BED_POSITIONS_MM", "POLYGON_POSITIONS_MM",
           "ZMOVE_POSITIONS_MM", "LIMIT_ROW", "limit_ratios"]

VariantFn = Callable[[object, np.ndarray, np.ndarray, np.ndarray], np.ndarray]

#: How the plant sees the 1 kHz command samples: the firmware moves linearly between the points of a
#: G-code file, and a step stream steps at exact times, so commands are interpolated linearly
#: (``"zoh"`` would add half a sample of delay and a 1 kHz staircase to every row).
HOLD = "linear"

#: name -> fn(profile, t_s, xyz_ref_m, q_ref_m) -> q_cmd_m; the bench's rows, in order
VARIANTS: dict[str, VariantFn] = {}

#: modules imported by :func:`load_providers` (each may call :func:`register_variant` on import)
PROVIDERS: list[str] = ["ffcomp.compensate.variants"]


def load_providers() -> None:
    """Import the :data:`PROVIDERS` modules that exist (their import registers their variants)."""
    import importlib

    for mod in PROVIDERS:
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as e:
            if e.name is None or not mod.startswith(e.name):  # a missing dependency inside it: re-raise
                raise


def register_variant(name: str, fn: VariantFn | None = None):
    """Add a bench row ``name`` (usable as a decorator); replaces an existing one of that name."""
    def deco(f: VariantFn) -> VariantFn:
        VARIANTS[name] = f
        return f

    return deco if fn is None else deco(fn)


@register_variant("none")
def _none(profile, t_s, xyz_ref_m, q_ref_m):
    """No compensation: the planned carriage path."""
    return np.asarray(q_ref_m, float)


# --------------------------------------------------------------------------- shaper tuning

@dataclass(frozen=True)
class ShaperTuning:
    """Shaper frequencies from the model: coupled x/y mode at the bed centre and bed average (Hz)."""

    centre_hz: float
    avg_hz: float
    centre_damping: float
    z_m: float

    def freq(self, tuning: str) -> float:
        return self.centre_hz if tuning == "centre" else self.avg_hz


_TUNING_CACHE: dict[str, ShaperTuning] = {}


def shaper_tuning(profile, z_m: float = 0.03, grid_step_m: float = 0.01) -> ShaperTuning:
    """Tune shapers to the model: its lateral (x/y) modes at ``(0, 0, z_m)`` and over the bed.

    The centre value is the lowest mode whose task-space shape is mainly x or y; the average is
    the mean over a ``grid_step_m`` grid of the printable disc of the two lateral modes (which split
    away from the centre).  Cached per profile content.
    """
    key = repr((profile.geometry, profile.dynamics, profile.effects, z_m, grid_step_m))
    if key in _TUNING_CACHE:
        return _TUNING_CACHE[key]
    model = LpvModel.from_profile(profile)
    c = modes(model, np.array([[0.0, 0.0, z_m]]))
    lat = [j for j in range(3) if c.direction[0, j] in ("x", "y")]
    j0 = lat[0] if lat else 0
    grid = workspace_grid(model.geometry, z_m, grid_step_m)
    ms = modes(model, grid)
    lateral = ms.direction != "z"
    avg = float(np.mean(ms.freq_hz[lateral])) if lateral.any() else float(c.freq_hz[0, j0])
    out = ShaperTuning(float(c.freq_hz[0, j0]), avg, float(c.damping[0, j0]), z_m)
    _TUNING_CACHE[key] = out
    return out


def _shaper_variant(name: str, tuning: str) -> VariantFn:
    def fn(profile, t_s, xyz_ref_m, q_ref_m):
        A, T = shapers.shaper_impulses(name, shaper_tuning(profile).freq(tuning))
        xyz = shapers.shape_cartesian(t_s, xyz_ref_m, (A, T), (A, T), None)
        return inverse(profile.geometry_si(), xyz)

    fn.__doc__ = f"Klipper {name.upper()} on X and Y, tuned to the model's {tuning} x/y mode."
    fn.shaper, fn.tuning = name, tuning  # type: ignore[attr-defined]
    return fn


for _name in shapers.SHAPERS:
    for _tuning in ("centre", "avg"):
        register_variant(f"{_name}-{_tuning}", _shaper_variant(_name, _tuning))


def describe_variant(name: str, profile) -> dict:
    """Table metadata of a variant: shaper, frequency (Hz) and Klipper smoothing (mm, at 5000 mm/s^2)."""
    fn = VARIANTS[name]
    shaper = getattr(fn, "shaper", None)
    if shaper is None:
        return {"name": name, "kind": "none" if name == "none" else "compensation"}
    f = shaper_tuning(profile).freq(fn.tuning)
    A, T = shapers.shaper_impulses(shaper, f)
    return {"name": name, "kind": "shaper", "shaper": shaper, "tuning": fn.tuning, "freq_hz": f,
            "smoothing_mm": shapers.shaper_smoothing(A, T),
            "residual_at_design": float(shapers.residual_vibration(A, T, f))}


# --------------------------------------------------------------------------- cases

BED_POSITIONS_MM = ((0.0, 0.0), (100.0, 0.0), (-100.0, 0.0), (0.0, 100.0), (0.0, -100.0))
#: the 64-segment polygon circle (200 mm/s) and the z loop: at the centre and off-centre
POLYGON_POSITIONS_MM = ((0.0, 0.0), (60.0, 40.0))
ZMOVE_POSITIONS_MM = ((0.0, 0.0), (-50.0, -60.0))
#: the physical-limit row (:mod:`ffcomp.compensate.limit`) the tables compare every row with
LIMIT_ROW = "limit"


def bench_cases(profile, *, quick: bool = False, z_mm: float = 30.0,
                accel_mm_s2: float = 10000.0) -> list[Trajectory]:
    """Synthetic cases: square and zig-zag at the bed positions (quick: fewer, shorter)."""
    geom = profile.geometry_si()
    rate = float(profile.limits.sample_rate_hz)
    # off-centre positions pulled in on a smaller bed so the 60 mm square still fits
    s = min(1.0, (float(profile.geometry.print_radius_mm) - 35.0) / 100.0)
    if quick:
        return [pattern("square", geom, (0.0, 0.0, z_mm), accel_mm_s2=accel_mm_s2, rate_hz=rate, loops=1),
                pattern("square", geom, (100.0 * s, 0.0, z_mm), accel_mm_s2=accel_mm_s2, rate_hz=rate, loops=1),
                pattern("zigzag", geom, (0.0, 0.0, z_mm), accel_mm_s2=accel_mm_s2, rate_hz=rate, lines=6)]
    out = []
    for name in ("square", "zigzag"):
        for x, y in BED_POSITIONS_MM:
            out.append(pattern(name, geom, (x * s, y * s, z_mm), accel_mm_s2=accel_mm_s2, rate_hz=rate))
    for x, y in POLYGON_POSITIONS_MM:
        out.append(pattern("polygon", geom, (x, y, z_mm), accel_mm_s2=accel_mm_s2, rate_hz=rate))
    for x, y in ZMOVE_POSITIONS_MM:
        out.append(pattern("zmove", geom, (x, y, z_mm), accel_mm_s2=accel_mm_s2, rate_hz=rate))
    return out


def crop_at_rest(traj: Trajectory, max_s: float, geom, *, z_below_m: float = 0.005, pad_s: float = 0.25,
                 stop_accel_m_s2: float = 10.0) -> Trajectory:
    """A window of a long trajectory that starts at rest on the first layers and lasts about ``max_s``.

    Starts at the first standstill (two equal samples) below ``z_below_m``.  Ends at the last
    standstill in the second half of the window; without one, at the slowest sample of its last
    third (a corner), from where a straight stop at ``stop_accel_m_s2`` is appended (a plannable
    continuation: cutting a moving reference would be an infinite deceleration).  The end position
    is then held for ``pad_s``.  ``geom`` maps the appended positions to carriage heights.
    """
    x = traj.xyz_m
    dt = float(traj.t_s[1] - traj.t_s[0])
    still = np.zeros(len(x), bool)
    still[1:] = np.all(x[1:] == x[:-1], axis=1)
    cand = np.flatnonzero(still & (x[:, 2] < z_below_m))
    i0 = int(cand[0]) if cand.size else 0
    i_max = min(len(x) - 1, i0 + int(round(max_s / dt)))
    ends = np.flatnonzero(still[i0 + 1:i_max + 1]) + i0 + 1
    tail = np.empty((0, 3))
    if ends.size and ends[-1] > i0 + 0.5 * (i_max - i0):
        i1 = int(ends[-1])
    elif i_max == len(x) - 1:
        i1 = i_max
    else:
        lo = i0 + int(2 * (i_max - i0) / 3)
        speed = np.linalg.norm(x[lo:i_max + 1] - x[lo - 1:i_max], axis=1) / dt
        i1 = lo + int(np.argmin(speed))
        vel = (x[i1] - x[i1 - 1]) / dt
        v = float(np.linalg.norm(vel))
        if v > 0:
            tt = np.arange(1, int(np.ceil(v / stop_accel_m_s2 / dt)) + 1) * dt
            tt = np.minimum(tt, v / stop_accel_m_s2)
            tail = x[i1] + (vel / v) * (v * tt - 0.5 * stop_accel_m_s2 * tt**2)[:, None]
    end = tail[-1:] if tail.size else x[i1:i1 + 1]
    n_pad = int(round(pad_s / dt))
    xyz = np.vstack([x[i0:i1 + 1], tail, np.repeat(end, n_pad, axis=0)])
    q = np.vstack([traj.q_m[i0:i1 + 1], inverse(geom, xyz[i1 - i0 + 1:])])
    t = np.arange(len(xyz)) * dt
    base = traj.name.split("[")[0]
    return Trajectory(f"{base}[{traj.t_s[i0]:.2f}+{t[i1 - i0]:.2f} s]", t, xyz, q)


def _find_samples() -> list[Path]:
    roots = [Path.cwd(), Path(__file__).resolve().parents[2]]
    for r in roots:
        d = r / "samples" / "gcode"
        files = sorted(d.glob("stress_*.gcode")) if d.is_dir() else []
        if files:
            return files
    return []


def gcode_cases(profile, *, max_s: float = 4.0, files=None) -> list[Trajectory]:
    """Windows (:func:`crop_at_rest`) of the stress G-code samples (none when they are missing)."""
    from ..errors import KinematicsError

    out = []
    for f in (files if files is not None else _find_samples()):
        try:
            tr = load_gcode_trajectory(profile, f)
        except KinematicsError:  # the sample does not fit this printer's bed
            if files is not None:
                raise
            continue
        out.append(crop_at_rest(tr, max_s, profile.geometry_si()))
    return out


# --------------------------------------------------------------------------- running

@dataclass(frozen=True)
class CaseResult:
    """One case: the reference, every variant's actual nozzle path and its error report."""

    trajectory: Trajectory
    names: tuple[str, ...]
    xyz_act_m: np.ndarray  # (R, N, 3)
    reports: tuple  # ErrorReport per variant
    seconds: float  # wall time of the batched simulation


@dataclass
class BenchResult:
    """All cases; :meth:`summary` aggregates per variant."""

    profile_name: str
    tuning: ShaperTuning
    variants: list[dict]
    cases: list[CaseResult] = field(default_factory=list)
    sim_seconds: float = 0.0
    simulated_s: float = 0.0

    def summary(self) -> list[dict]:
        """Per variant: lag-aligned RMS (mean over cases), max, contour RMS/max (um), mean lag (ms)."""
        rows = []
        for k, info in enumerate(self.variants):
            reps = [c.reports[k] for c in self.cases]
            worst = max(range(len(reps)), key=lambda i: reps[i].lag.rms_norm_um)
            rows.append({
                **info,
                "lag_rms_um": float(np.mean([r.lag.rms_norm_um for r in reps])),
                "lag_p95_um": float(max(r.lag.p95_norm_um for r in reps)),
                "lag_max_um": float(max(r.lag.max_norm_um for r in reps)),
                "contour_rms_um": float(np.mean([r.contour.rms_norm_um for r in reps])),
                "contour_max_um": float(max(r.contour.max_norm_um for r in reps)),
                "lag_ms": float(np.mean([r.lag_s for r in reps]) * 1e3),
                "worst_case": self.cases[worst].trajectory.name,
            })
        return rows

    def to_dict(self) -> dict:
        return {
            "profile": self.profile_name,
            "tuning": {"centre_hz": self.tuning.centre_hz, "avg_hz": self.tuning.avg_hz,
                       "centre_damping": self.tuning.centre_damping, "z_mm": self.tuning.z_m * 1e3},
            "summary": self.summary(),
            "cases": {c.trajectory.name: {
                "duration_s": c.trajectory.duration_s, "sim_wall_s": c.seconds,
                "variants": {n: r.to_dict() for n, r in zip(c.names, c.reports, strict=True)}}
                for c in self.cases},
            "cost": {"wall_s": self.sim_seconds, "simulated_s": self.simulated_s,
                     "wall_per_simulated_s": self.sim_seconds / max(self.simulated_s, 1e-12)},
        }


def run_case(plant: DeltaPlant, profile, traj: Trajectory, names, *, quantize: bool = False) -> CaseResult:
    """All ``names`` (keys of :data:`VARIANTS`) on one trajectory, integrated together."""
    cmds = np.stack([np.asarray(VARIANTS[n](profile, traj.t_s, traj.xyz_m, traj.q_m), float) for n in names])
    spm = profile.limits.steps_per_mm if quantize else None
    t0 = time.perf_counter()
    res = plant.simulate(traj.t_s, cmds, steps_per_mm=spm, hold=HOLD)
    wall = time.perf_counter() - t0
    reports = tuple(metrics.evaluate(traj.t_s, traj.xyz_m, res.xyz_m[k]) for k in range(len(names)))
    return CaseResult(traj, tuple(names), res.xyz_m, reports, wall)


def run_bench(profile, *, quick: bool = False, variants=None, include_gcode: bool | None = None,
              gcode_max_s: float = 4.0, progress: Callable[[str], None] | None = None,
              plant_profile=None) -> BenchResult:
    """Run the bench (see the module notes).

    Parameters
    ----------
    quick : bool
        Three short synthetic cases only (seconds); otherwise ten synthetic cases plus the stress
        samples' windows.
    variants : list of str, optional
        Rows to run (default: all of :data:`VARIANTS`, in registration order).
    include_gcode : bool, optional
        Add the stress samples (default: not in quick mode).
    gcode_max_s : float
        Length of each stress-sample window, s.
    progress : callable, optional
        Called with a short message per case.
    plant_profile : PrinterProfile, optional
        The simulated printer when it is not the one the rows compensate for (e.g. an identified
        profile compensated, its "truth" simulated); default ``profile``.
    """
    load_providers()
    names = list(VARIANTS) if variants is None else list(variants)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise ValueError(f"unknown bench variant(s) {unknown}; known: {', '.join(VARIANTS)}")
    plant = DeltaPlant.from_profile(plant_profile if plant_profile is not None else profile)
    cases = bench_cases(profile, quick=quick)
    if include_gcode if include_gcode is not None else not quick:
        cases += gcode_cases(profile, max_s=gcode_max_s)
    out = BenchResult(profile.name, shaper_tuning(profile), [describe_variant(n, profile) for n in names])
    for traj in cases:
        c = run_case(plant, profile, traj, names)
        out.cases.append(c)
        out.sim_seconds += c.seconds
        out.simulated_s += traj.duration_s
        if progress:
            progress(f"{traj.name}: {traj.duration_s:.2f} s simulated x {len(names)} in {c.seconds:.1f} s")
    return out


def markdown_table(result: BenchResult) -> str:
    """The bench summary (one row per variant) and the per-case lag-aligned RMS, as Markdown."""
    rows = result.summary()
    tu = result.tuning
    lines = [f"Profile: {result.profile_name}. Shaper tuning: centre {tu.centre_hz:.2f} Hz "
             f"(x/y mode at (0, 0, {tu.z_m * 1e3:g}) mm, damping {tu.centre_damping:.3f}), "
             f"bed average {tu.avg_hz:.2f} Hz. {len(result.cases)} cases, "
             f"{result.simulated_s:.1f} s simulated per variant.", "",
             "| variant | f (Hz) | smoothing (mm) | lag RMS (um) | lag p95 (um) | lag max (um) | "
             "contour RMS (um) | contour max (um) | lag (ms) | worst case |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]

    def num(v, fmt="{:.2f}"):
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)

    for r in rows:
        lines.append(f"| {r['name']} | {num(r.get('freq_hz'))} | {num(r.get('smoothing_mm'), '{:.3f}')} | "
                     f"{r['lag_rms_um']:.1f} | {r['lag_p95_um']:.1f} | {r['lag_max_um']:.1f} | "
                     f"{r['contour_rms_um']:.1f} | {r['contour_max_um']:.1f} | {r['lag_ms']:.2f} | "
                     f"{r['worst_case']} |")
    lines += ["", "Lag-aligned RMS error per case (um):", ""]
    names = [c.trajectory.name for c in result.cases]
    lines.append("| variant | " + " | ".join(names) + " |")
    lines.append("|---|" + "---:|" * len(names))
    for k, info in enumerate(result.variants):
        vals = " | ".join(f"{c.reports[k].lag.rms_norm_um:.2f}" for c in result.cases)
        lines.append(f"| {info['name']} | {vals} |")
    ratios = limit_ratios(result)
    if ratios is not None:
        lines += ["", f"Distance from the physical limit (row `{LIMIT_ROW}`): lag-aligned RMS / the limit's, per case:",
                  "", "| variant | worst | " + " | ".join(names) + " |", "|---|---:|" + "---:|" * len(names)]
        for info, rr in zip(result.variants, ratios, strict=True):
            if info["name"] != LIMIT_ROW:
                lines.append(f"| {info['name']} | {max(rr):.2f}x | " + " | ".join(f"{v:.2f}x" for v in rr) + " |")
    return "\n".join(lines) + "\n"


def limit_ratios(result: BenchResult) -> list[list[float]] | None:
    """Per variant and case: lag-aligned RMS over the physical-limit row's (None without that row)."""
    names = [v["name"] for v in result.variants]
    if LIMIT_ROW not in names:
        return None
    k0 = names.index(LIMIT_ROW)
    return [[c.reports[k].lag.rms_norm_um / max(c.reports[k0].lag.rms_norm_um, 1e-12) for c in result.cases]
            for k in range(len(names))]
