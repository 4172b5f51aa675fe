"""``ffcomp simulate``, ``ffcomp bench``, ``ffcomp sim-measure``: the nonlinear simulator from the shell."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from .common import JsonOpt, ProfileOpt, app, console, err_console, load_profile_opt, parse_triple, print_json


def _fmt(v: float, spec: str = "{:.1f}") -> str:
    return "-" if v != v else spec.format(v)  # NaN -> "-"


@app.command("simulate")
def simulate_cmd(
    gcode: Annotated[Path, typer.Argument(help="G-code file; its planned nozzle path is the reference.")],
    profile: ProfileOpt = None,
    compare: Annotated[Optional[Path], typer.Option(
        "--compare", help="Another G-code (e.g. the compensated output) scored against the same reference."
    )] = None,
    shaper: Annotated[Optional[str], typer.Option(
        "--shaper", help="Also run a Klipper input shaper on X/Y, NAME@FREQ_HZ (e.g. mzv@62).")] = None,
    shape_z: Annotated[bool, typer.Option(
        "--shape-z", help="Apply the --shaper to Z too (Klipper shapes only X and Y unless configured).")] = False,
    quantize: Annotated[bool, typer.Option(
        "--quantize", help="Round the carriage commands to whole steps (limits.steps_per_mm).")] = False,
    plot: Annotated[Optional[str], typer.Option(
        "--plot", help="Write PREFIX_time.png (error over time) and PREFIX_bed.png (error over the bed)."
    )] = None,
    json: JsonOpt = False,
) -> None:
    """Run G-code through the nonlinear printer simulator and report the tracking error."""
    from ..pipeline import sim_flow
    from ..sim.shapers import parse_shaper_spec

    if shaper:
        try:
            parse_shaper_spec(shaper)
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--shaper") from None
    for p, hint in ((gcode, "GCODE"), (compare, "--compare")):
        if p is not None and not Path(p).is_file():
            raise typer.BadParameter(f"no such file: {p}", param_hint=hint)
    if plot:  # before the simulation, not after it
        from ..io_atomic import check_output_path

        check_output_path(f"{plot}_time.png", "plot")
    prof = load_profile_opt(profile)
    rep = sim_flow.simulate_gcode(prof, gcode, compare=compare, shaper=shaper, shape_z=shape_z, quantize=quantize)
    files = sim_flow.write_sim_plots(rep, plot, print_radius_mm=prof.geometry.print_radius_mm) if plot else []
    if json:
        print_json({**rep.to_dict(), "plots": [str(f) for f in files]})
        return
    t = Table(title=f"{rep.reference.name}: {rep.reference.duration_s:.2f} s, errors in um"
                    f"{' (commands quantised)' if rep.quantized else ''}", title_justify="left")
    for col in ("run", "lag ms", "time RMS", "lag RMS", "contour RMS", "contour max", "worst (x, y) mm",
                "peak Hz / um"):
        t.add_column(col, justify="left" if col == "run" else "right")
    for r in rep.runs:
        e = r.report
        t.add_row(r.name, f"{e.lag_s * 1e3:.2f}", f"{e.time.rms_norm_um:.1f}", f"{e.lag.rms_norm_um:.1f}",
                  f"{e.contour.rms_norm_um:.1f}", f"{e.contour.max_norm_um:.1f}",
                  f"{e.worst.x_mm:.0f}, {e.worst.y_mm:.0f}", f"{_fmt(r.peak_hz)} / {_fmt(r.peak_um)}")
    console.print(t)
    t = Table(title="lag-aligned error per axis, um (RMS / 95th pct / max)", title_justify="left")
    for col in ("run", "x", "y", "z", "norm"):
        t.add_column(col, justify="left" if col == "run" else "right")
    for r in rep.runs:
        e = r.report.lag
        t.add_row(r.name, *(f"{e.rms_um[j]:.1f} / {e.p95_um[j]:.1f} / {e.max_um[j]:.1f}" for j in range(3)),
                  f"{e.rms_norm_um:.1f} / {e.p95_norm_um:.1f} / {e.max_norm_um:.1f}")
    console.print(t)
    share = rep.extruded_share
    if share:
        t = Table(title=f"printed lines ({share * 100:.0f} % of the samples), um", title_justify="left")
        for col in ("run", "lag RMS", "contour RMS"):
            t.add_column(col, justify="left" if col == "run" else "right")
        for r in rep.runs:
            if r.extruded_um is not None:
                t.add_row(r.name, f"{r.extruded_um[0]:.2f}", f"{r.extruded_um[1]:.2f}")
        console.print(t)
    console.print(f"simulated {len(rep.runs)} run(s) x {rep.reference.duration_s:.2f} s "
                  f"in {rep.wall_s:.1f} s")
    if compare is not None:
        from ..pipeline.header import settings_hold_margin_s, settings_quiet_z_period_s

        added = []
        margin_s = settings_hold_margin_s(compare)
        if margin_s:
            added.append(f"rest margins of {margin_s * 1e3:g} ms around retractions")
        if settings_quiet_z_period_s(compare) is not None:
            added.append("quiet z moves next to retractions")
        if added:  # (sim_flow planned the reference with them: the runs share one clock)
            console.print(f"note: {Path(compare).name} was written with {' and '.join(added)}; the reference "
                          "above has them too. Against the source as written, the time they add counts as "
                          "error (bench_gcode_fidelity.py's source-clock columns).")
    for f in files:
        console.print(f"wrote {f}")


@app.command("bench")
def bench_cmd(
    out: Annotated[Path, typer.Option(
        "--out", "-o", help="Directory for bench.md, bench.json and PNGs.")] = Path("bench_out"),
    quick: Annotated[bool, typer.Option(
        "--quick", help="Three short synthetic cases only (seconds).")] = False,
    profile: ProfileOpt = None,
    json: JsonOpt = False,
) -> None:
    """Run every registered variant (none, Klipper shapers, compensation) on the stress cases."""
    from ..pipeline import sim_flow

    prof = load_profile_opt(profile)
    progress = None if json else (lambda msg: err_console.print(msg, highlight=False))
    res, files = sim_flow.bench_to_dir(prof, out, quick=quick, progress=progress)
    if json:
        print_json({**res.to_dict(), "files": [str(f) for f in files]})
        return
    t = Table(title=f"bench: {len(res.cases)} cases, {res.simulated_s:.1f} s simulated per variant "
                    f"(errors in um, lag-aligned)", title_justify="left")
    for col in ("variant", "f (Hz)", "smoothing (mm)", "lag RMS", "lag max", "contour RMS", "contour max",
                "worst case"):
        t.add_column(col, justify="left" if col in ("variant", "worst case") else "right")
    for r in res.summary():
        f = r.get("freq_hz")
        s = r.get("smoothing_mm")
        t.add_row(r["name"], "-" if f is None else f"{f:.2f}", "-" if s is None else f"{s:.3f}",
                  f"{r['lag_rms_um']:.1f}", f"{r['lag_max_um']:.1f}", f"{r['contour_rms_um']:.1f}",
                  f"{r['contour_max_um']:.1f}", r["worst_case"])
    console.print(t)
    runs_s = res.simulated_s * len(res.variants)
    console.print(f"simulation cost: {res.sim_seconds:.1f} s wall for {runs_s:.1f} s of runs "
                  f"({len(res.variants)} variants batched)")
    for f in files:
        console.print(f"wrote {f}")


@app.command("sim-measure")
def sim_measure_cmd(
    output_file: Annotated[Path, typer.Option("--out", "-o", help="FRF file to write (FRF_FORMAT).")],
    at: Annotated[str, typer.Option("--at", help="Nozzle position X,Y,Z of the sweep, mm.")] = "0,0,30",
    input_: Annotated[str, typer.Option("--input", help="Swept coordinate: x, y, z, qA, qB, qC.")] = "z",
    output: Annotated[str, typer.Option("--output", help="Measured coordinate: x, y, z, qA, qB, qC.")] = "qA",
    kind: Annotated[str, typer.Option(
        "--kind", help="assembled (complete printer) or carriage (effector detached: m_nt = b_nt = 0)."
    )] = "assembled",
    fmin: Annotated[float, typer.Option(help="Lowest swept frequency, Hz.")] = 5.0,
    fmax: Annotated[float, typer.Option(help="Highest swept frequency, Hz.")] = 300.0,
    period: Annotated[float, typer.Option(help="Chirp period, s (resolution 1/period).")] = 1.0,
    periods: Annotated[int, typer.Option(help="Periods averaged (one more runs first).")] = 3,
    amplitude: Annotated[float, typer.Option("--amplitude-mm", help="Chirp amplitude, mm.")] = 0.02,
    noise: Annotated[float, typer.Option("--noise-um", help="RMS output noise added, um.")] = 0.0,
    seed: Annotated[int, typer.Option(help="Noise seed.")] = 0,
    profile: ProfileOpt = None,
    plot: Annotated[Optional[Path], typer.Option(
        "--plot", help="Bode plot of the estimate and the model (PNG).")] = None,
    json: JsonOpt = False,
) -> None:
    """Virtual FRF measurement: a periodic chirp through the nonlinear simulator, H1 with coherence."""
    import numpy as np

    from ..pipeline import sim_flow
    from ..sim.measure import SweepSpec

    spec = SweepSpec(f_lo_hz=fmin, f_hi_hz=fmax, period_s=period, periods=periods, amplitude_mm=amplitude,
                     noise_um=noise, seed=seed)
    try:
        spec.validate()
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    from ..io_atomic import check_output_path

    for p, what in ((output_file, "FRF file"), (plot, "plot")):
        if p is not None:
            check_output_path(p, what)
    prof = load_profile_opt(profile)
    pos = parse_triple(at)
    try:
        meas, H_model = sim_flow.virtual_measure(prof, pos, input_, output, kind=kind, spec=spec,
                                                 out_path=output_file)
    except ValueError as e:
        if isinstance(e, typer.BadParameter) or type(e).__module__.startswith("ffcomp.errors"):
            raise
        raise typer.BadParameter(str(e)) from None
    if plot:
        from ..report.plots import bode_png

        bode_png(plot, meas.freq_hz, [("model", H_model)], measured=[("simulated H1", meas.freq_hz, meas.H)],
                 title=f"{kind} {input_}->{output} at ({at}) mm")
    rel = np.abs(meas.H - H_model) / np.maximum(np.abs(H_model), 1e-12)
    k = int(np.argmax(np.abs(meas.H)))
    summary = {"file": str(output_file), "kind": kind, "input": input_, "output": output,
               "position_mm": list(pos), "n_freq": int(meas.freq_hz.size),
               "peak_hz": float(meas.freq_hz[k]), "peak_mag": float(abs(meas.H[k])),
               "min_coherence": float(np.min(meas.coherence)),
               "max_rel_dev_from_model": float(rel.max()), "median_rel_dev_from_model": float(np.median(rel))}
    if json:
        print_json(summary)
        return
    console.print(f"wrote {output_file}: {kind} {input_}->{output} at ({at}) mm, {meas.freq_hz.size} bins "
                  f"{meas.freq_hz[0]:g}-{meas.freq_hz[-1]:g} Hz")
    console.print(f"peak |H| = {summary['peak_mag']:.4f} at {summary['peak_hz']:g} Hz; min coherence "
                  f"{summary['min_coherence']:.4f}; deviation from the linear model: median "
                  f"{summary['median_rel_dev_from_model']:.2e}, max {summary['max_rel_dev_from_model']:.2e}")
