"""Simulation flow: G-code or variants -> nonlinear simulator -> tracking-error metrics, plots, files.

The only place that composes the simulation stages (G-code sampler, shapers, :mod:`ffcomp.sim.plant`,
:mod:`ffcomp.sim.metrics`, :mod:`ffcomp.sim.bench`, :mod:`ffcomp.sim.measure`, the figures);
the CLI calls one function per command and prints or writes what it returns.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..compensate.predict import predict_lpv
from ..gcode.signature import scan_gcode
from ..kinematics import forward, inverse
from ..model.lpv import LpvModel
from ..sim import bench, metrics, shapers
from ..sim.moves import Trajectory, load_gcode_trajectory, longest_piece
from ..sim.plant import DeltaPlant

__all__ = ["load_gcode_trajectory", "longest_piece", "RunResult", "SimReport", "extruding_samples",
           "simulate_commands", "simulate_gcode", "write_sim_plots", "bench_to_dir", "virtual_measure"]


@dataclass(frozen=True)
class RunResult:
    """One simulated command set scored against the reference.

    Attributes
    ----------
    name : str
    q_cmd_m, xyz_act_m : ndarray, shape (N, 3)
        Commands applied (after quantisation) and actual nozzle positions ``forward(q)``, m.
    report : metrics.ErrorReport
    err_lag_m : ndarray, shape (N, 3)
        Lag-aligned error, m.
    contour_m : ndarray, shape (N,)
        Contour error, m.
    peak_hz, peak_um : float
        Largest peak (above 5 Hz) of the lag-aligned error's amplitude spectrum, over the axes.
    extruded_um : (float, float) or None
        Lag-aligned and contour RMS (um) over the samples where the plan extrudes while it moves
        (:func:`extruding_samples`: what marks the part); None without extrusion data.
    """

    name: str
    q_cmd_m: np.ndarray
    xyz_act_m: np.ndarray
    report: metrics.ErrorReport
    err_lag_m: np.ndarray
    contour_m: np.ndarray
    peak_hz: float
    peak_um: float
    extruded_um: tuple[float, float] | None = None

    def to_dict(self) -> dict:
        ext = {} if self.extruded_um is None else {"extruded_lag_rms_um": self.extruded_um[0],
                                                   "extruded_contour_rms_um": self.extruded_um[1]}
        return {"name": self.name, "spectrum_peak_hz": self.peak_hz, "spectrum_peak_um": self.peak_um,
                **self.report.to_dict(), **ext}


@dataclass(frozen=True)
class SimReport:
    """Reference trajectory and the scored runs."""

    reference: Trajectory
    runs: tuple[RunResult, ...]
    wall_s: float
    quantized: bool

    #: share of the samples where the plan extrudes while it moves (None without E data)
    extruded_share: float | None = None

    def to_dict(self) -> dict:
        return {"reference": self.reference.name, "duration_s": self.reference.duration_s,
                "samples": int(self.reference.t_s.shape[0]), "quantized": self.quantized,
                "extruded_share": self.extruded_share,
                "sim_wall_s": self.wall_s, "runs": [r.to_dict() for r in self.runs]}


def extruding_samples(ref: Trajectory) -> np.ndarray | None:
    """Samples where the reference extrudes while it moves (E rises over the sample and the nozzle
    moves faster than 1 mm/s): the printed lines.  None where the trajectory has no E."""
    if ref.e_mm is None or len(ref.e_mm) < 2:
        return None
    return metrics.extruding_mask(ref.xyz_m, ref.e_mm, float(ref.t_s[1] - ref.t_s[0]))


def _score(name: str, ref: Trajectory, q_cmd: np.ndarray, xyz_act: np.ndarray,
           printed: np.ndarray | None = None) -> RunResult:
    rep = metrics.evaluate(ref.t_s, ref.xyz_m, xyz_act)
    err, _ = metrics.lag_aligned_error(ref.t_s, ref.xyz_m, xyz_act)
    contour = metrics.contour_error(ref.xyz_m, xyz_act)
    f, amp = metrics.error_spectrum(ref.t_s, err)
    band = f >= 5.0
    if band.any():
        k, ax = np.unravel_index(np.argmax(amp[band]), amp[band].shape)
        peak_hz, peak_um = float(f[band][k]), float(amp[band][k, ax] * 1e6)
    else:
        peak_hz = peak_um = float("nan")
    m = printed
    ext = None if m is None or not m.any() else (float(np.sqrt(np.mean(np.sum(err[m] ** 2, axis=1)))) * 1e6,
                                                 float(np.sqrt(np.mean(contour[m] ** 2))) * 1e6)
    return RunResult(name, q_cmd, xyz_act, rep, err, contour, peak_hz, peak_um, ext)


def simulate_commands(profile, ref: Trajectory, commands: dict[str, np.ndarray], *, quantize: bool = False,
                      plant: DeltaPlant | None = None) -> SimReport:
    """Simulate named carriage command sets (each (N, 3) on ``ref.t_s``) together and score them."""
    import time

    plant = plant or DeltaPlant.from_profile(profile)
    names = list(commands)
    cmds = np.stack([np.asarray(commands[n], float) for n in names])
    t0 = time.perf_counter()
    res = plant.simulate(ref.t_s, cmds, steps_per_mm=profile.limits.steps_per_mm if quantize else None,
                         hold=bench.HOLD)
    wall = time.perf_counter() - t0
    printed = extruding_samples(ref)  # the printed lines, once for every run
    runs = tuple(_score(n, ref, res.q_cmd_m[k], res.xyz_m[k], printed) for k, n in enumerate(names))
    return SimReport(ref, runs, wall, quantize, None if printed is None else float(np.mean(printed)))


#: how far (s) ``simulate --compare`` searches for the time offset between the two files
COMPARE_WINDOW_S = 1.0


def _stop_times(profile, path) -> list[float]:
    """Plan times (s) of the file's stops (M109, M400, a tool change...: where a compensation stream
    ends at rest and the next one starts)."""
    from ..gcode.planner import GcodePlan

    plan = GcodePlan(str(path), profile, lenient=True)
    times: list[float] = []
    plan.planner.on_stop = lambda t_s, lineno: times.append(float(t_s))
    for _ in plan:
        pass
    return times


def _offset(ref_xyz: np.ndarray, xyz: np.ndarray, s0: int, a: int, b: int, window: int) -> float:
    """Where ``ref_xyz[a:b]`` runs in ``xyz`` (samples, to a fraction: the offset of ``xyz`` against the
    reference), searched within ``window`` samples of ``s0 - a`` (the best whole sample, then the
    vertex of the squared error's parabola through it and its neighbours)."""
    seg = xyz[s0:b + s0 - a + 2 * window]
    k = s0 - a + metrics.time_offset_samples(ref_xyz[a:b], seg, window)

    def mse(kk):
        A, B = ref_xyz[a:b], xyz[max(a + kk, 0):b + kk]
        m = min(len(A), len(B))
        return float(np.mean(np.sum((A[:m] - B[:m]) ** 2, axis=1))) if m > 1 and a + kk >= 0 else np.inf

    e0, e1, e2 = mse(k - 1), mse(k), mse(k + 1)
    den = e0 - 2.0 * e1 + e2
    return k + (0.5 * (e0 - e2) / den if np.isfinite(den) and den > 0 else 0.0)


def _reference_on_other_clock(ref_xyz: np.ndarray, xyz: np.ndarray, cuts, window: int) -> np.ndarray:
    """The reference's (fractional) sample index at every sample of another record (a compensated
    output; and after its end, should the reference go on), which starts later (its pre-roll) and
    rests longer at each stop (its stream settles and starts again; not a whole number of samples:
    the stop falls between two).

    The reference is cut at ``cuts`` (sample indices where the machine stands at a stop); each
    stretch with motion gets its own offset (:func:`_offset`, searched within ``window`` samples of
    where the other record's rest before it begins; the first, from the start of both records); a
    stretch without motion keeps the offset before it.  Where the other record rests longer, the
    index stays on the stop.
    """
    n = len(ref_xyz)
    edges = [0] + sorted({int(c) for c in cuts if 0 < int(c) < n}) + [n]
    phi = None  # the offset so far (none before the first stretch with motion)
    r = np.full(len(xyz), np.nan)
    for a, b in zip(edges[:-1], edges[1:]):
        if np.ptp(ref_xyz[a:b], axis=0).max() > 1e-6:
            if phi is None:  # the first stretch with motion: from the start of both records
                phi = _offset(ref_xyz, xyz, 0, 0, b, window)
            elif 0 <= a + int(round(phi)) < len(xyz):  # a stop never shortens the rest
                phi = max(_offset(ref_xyz, xyz, a + int(round(phi)), a, b, window), phi)
        if phi is None:
            continue
        j0, j1 = max(int(np.ceil(a + phi - 1e-9)), 0), min(int(np.floor(b - 1 + phi + 1e-9)), len(xyz) - 1)
        if j1 >= j0:
            r[j0:j1 + 1] = np.arange(j0, j1 + 1) - phi
    # before the first stretch, between stretches (the longer rest at a stop) and after the last: the
    # reference stands where it stands next (or last)
    known = np.flatnonzero(~np.isnan(r))
    if not known.size:
        return np.zeros(len(xyz))
    nxt = np.minimum(np.searchsorted(known, np.arange(len(xyz))), known.size - 1)
    fill = np.where(np.arange(len(xyz)) > known[-1], n - 1, np.ceil(r[known[nxt]] - 1e-9))
    r = np.clip(np.where(np.isnan(r), fill, r), 0, n - 1)
    # the other record ended first: the reference's rest goes on, the other standing where it ended
    return np.concatenate([r, np.arange(int(np.floor(r[-1])) + 1, n, dtype=float)])


def _rows_at(a: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Rows of ``a`` at fractional indices ``r`` (linear between samples: a planned path's error is
    at most ``accel dt^2 / 8``, 1.25 um at 10,000 mm/s^2 and 1 kHz, where its acceleration changes)."""
    i = np.minimum(np.floor(r).astype(int), len(a) - 1)
    f = (r - i)[:, None]
    return a[i] * (1.0 - f) + a[np.minimum(i + 1, len(a) - 1)] * f


def simulate_gcode(profile, path, *, compare=None, shaper: str | None = None, shape_z: bool = False,
                   quantize: bool = False) -> SimReport:
    """Simulate a G-code file as planned; optionally a second file and/or a Klipper shaper.

    Parameters
    ----------
    path : path
        G-code whose planned nozzle path is the reference (and the first run, ``planned``).
    compare : path, optional
        Another G-code (e.g. the compensated output) run on the printer and scored against the
        *same* reference; the shorter record is extended at rest.  An ffcomp output written with
        rest margins around retractions (``--hold-margin-ms``) has them added to the reference too, and
        one written with quiet z moves (``--quiet-z``) its z moves planned the same way.
    shaper : str, optional
        ``"name@freq_hz"`` (e.g. ``"mzv@62"``): the reference shaped on X and Y as Klipper does.
    shape_z : bool
        Shape Z with the same shaper too (Klipper's optional ``shaper_type_z``).
    quantize : bool
        Round commands to whole steps (``limits.steps_per_mm``).
    """
    from .header import settings_hold_margin_s, settings_quiet_z_period_s

    # an output written with rest margins around retractions runs on a longer clock: the reference
    # (and every run derived from it) gets the same rest; and one written with quiet z moves
    # (--quiet-z) the same z moves
    margin_s = settings_hold_margin_s(compare) if compare else 0.0
    quiet_s = settings_quiet_z_period_s(compare) if compare and profile.limits.planner == "klipper" else None
    ref = load_gcode_trajectory(profile, path, hold_margin_s=margin_s, quiet_z_period_s=quiet_s)
    commands: dict[str, np.ndarray] = {"planned": ref.q_m}
    if shaper:
        name, f = shapers.parse_shaper_spec(shaper)
        A, T = shapers.shaper_impulses(name, f)
        xyz = shapers.shape_cartesian(ref.t_s, ref.xyz_m, (A, T), (A, T), (A, T) if shape_z else None)
        commands[f"{name}@{f:g}{'+z' if shape_z else ''}"] = inverse(profile.geometry_si(), xyz)
    if compare:
        other = load_gcode_trajectory(profile, compare)
        dt = float(ref.t_s[1] - ref.t_s[0])
        # a compensated file starts with a pre-roll (rest and pre-actuation before the first move) and
        # rests longer at every stop (the stream settles and starts again): align the records stretch
        # by stretch between the source's stops, each by its own time offset
        cuts = [] if margin_s > 0 else np.searchsorted(ref.t_s, _stop_times(profile, path), side="right")
        along = other.xyz_m
        if scan_gcode(str(compare)).mark_line is not None:
            # an ffcomp output's command leads its nozzle by design (the compensation's pre-actuation):
            # aligned on the command, the reference ran that lead early and the nozzle read as lagging
            # it (2.5 ms on stress_square): align on the output's nozzle instead, which is meant to run
            # on the source's clock (within a stretch, lag and drift still count); the model's linear
            # prediction of it finds the offsets (about a tenth of the simulator's time)
            q_pred = predict_lpv(LpvModel.from_profile(profile), other.q_m, other.xyz_m, dt)
            along = forward(profile.geometry_si(), q_pred)
        r = _reference_on_other_clock(ref.xyz_m, along, cuts, int(round(COMPARE_WINDOW_S / dt)))
        e = None if ref.e_mm is None else _rows_at(ref.e_mm[:, None], r)[:, 0]
        ref = Trajectory(ref.name, np.arange(len(r)) * dt, _rows_at(ref.xyz_m, r), _rows_at(ref.q_m, r), e)
        commands = {name: (ref.q_m if name == "planned" else _rows_at(c, r)) for name, c in commands.items()}
        label = Path(compare).name
        q_other = np.vstack([other.q_m, np.repeat(other.q_m[-1:], max(len(r) - len(other.q_m), 0), axis=0)])
        commands[label if label not in commands else f"compare:{label}"] = q_other
    return simulate_commands(profile, ref, commands, quantize=quantize)


def write_sim_plots(report: SimReport, prefix, *, print_radius_mm: float | None = None) -> list[Path]:
    """``PREFIX_time.png`` (error over time) and ``PREFIX_bed.png`` (error over the bed)."""
    from ..report.sim_plots import error_bed_png, error_time_png

    prefix = str(prefix)
    ref = report.reference
    p1 = error_time_png(f"{prefix}_time.png", ref.t_s,
                        [(r.name, r.err_lag_m, r.contour_m) for r in report.runs], title=ref.name)
    p2 = error_bed_png(f"{prefix}_bed.png", ref.xyz_m, [(r.name, r.contour_m) for r in report.runs],
                       title=ref.name, print_radius_mm=print_radius_mm)
    return [p1, p2]


def bench_to_dir(profile, out_dir, *, quick: bool = False, progress=None) -> tuple[object, list[Path]]:
    """Run :func:`ffcomp.sim.bench.run_bench` and write ``bench.md``, ``bench.json`` and PNGs."""
    from ..report.sim_plots import bench_bars_png, error_bed_png, error_time_png
    from ..sim.bench import markdown_table, run_bench

    res = run_bench(profile, quick=quick, progress=progress)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "bench.md", out / "bench.json"]
    files[0].write_text(markdown_table(res), encoding="utf-8")
    files[1].write_text(json.dumps(res.to_dict(), indent=1, default=float), encoding="utf-8")
    names = [v["name"] for v in res.variants]
    cases = [c.trajectory.name for c in res.cases]
    vals = np.array([[c.reports[k].lag.rms_norm_um for c in res.cases] for k in range(len(names))])
    files.append(bench_bars_png(out / "bench_rms.png", names, cases, vals))
    # the hardest case (largest error without compensation): error over time and over the bed
    k0 = names.index("none") if "none" in names else 0
    hard = max(res.cases, key=lambda c: c.reports[k0].lag.rms_norm_um)
    best = min(range(len(names)), key=lambda k: hard.reports[k].lag.rms_norm_um)
    sel = sorted({k0, best})
    ref = hard.trajectory
    runs = []
    for k in sel:
        err, _ = metrics.lag_aligned_error(ref.t_s, ref.xyz_m, hard.xyz_act_m[k])
        runs.append((names[k], err, metrics.contour_error(ref.xyz_m, hard.xyz_act_m[k])))
    files.append(error_time_png(out / "bench_time.png", ref.t_s, runs, title=f"{ref.name} (hardest case)"))
    # all cases of the 'none' row on one bed map
    xyz = np.vstack([c.trajectory.xyz_m for c in res.cases])
    cont = np.concatenate([metrics.contour_error(c.trajectory.xyz_m, c.xyz_act_m[k0]) for c in res.cases])
    files.append(error_bed_png(out / "bench_bed.png", xyz, [(names[k0], cont)],
                               title="contour error, all cases",
                               print_radius_mm=profile.geometry.print_radius_mm))
    return res, files


def virtual_measure(profile, at_mm, input_: str, output: str, *, kind: str = "assembled", spec=None,
                    out_path=None):
    """Virtual FRF measurement on the nonlinear simulator (:func:`ffcomp.sim.measure.virtual_frf`).

    Returns the :class:`~ffcomp.measure.frf_file.FrfMeasurement` and the model's prediction at its
    frequencies (complex (F,)); writes the FRF file when ``out_path`` is given.
    """
    from ..measure.frf_file import save_frf
    from ..model.lpv import AXES, frequency_response
    from ..sim.measure import virtual_frf
    from .model_flow import frame_for

    plant = DeltaPlant.from_profile(profile)
    meas = virtual_frf(plant, at_mm, input_, output, kind=kind, spec=spec)
    model = plant.carriage_only().model if kind == "carriage" else plant.model
    pos = np.asarray(at_mm, float)[None] * 1e-3
    H = frequency_response(model, pos, meas.freq_hz, frame=frame_for(input_, output),
                           delay="pade")[0, AXES[output], AXES[input_]]
    if out_path is not None:
        save_frf(meas, out_path)
    return meas, H
