"""``ffcomp validate | diagnose | fit | virtual-measure | frf | effects``: model versus measurement."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, List, Optional

import numpy as np
import typer
from rich.table import Table

from ..pipeline import validate_flow as vf
from .common import JsonOpt, ProfileOpt, app, console, err_console, load_profile_opt, parse_triple, print_json

DataArg = Annotated[Path, typer.Argument(help="Directory of FRF files (FRF_FORMAT *.csv, UFF *.uff), or one file.")]
NoiseOpt = Annotated[Optional[float], typer.Option(
    "--noise-floor", help="Noise floor to use (relative complex residual of a perfect model, e.g. 0.02) instead "
    "of the estimates from the data and the coherence.")]
BaseOpt = Annotated[Optional[bool], typer.Option(
    "--base/--no-base", help="Refit the base dynamics (m, c, b, k, b_nt, drive) with the effects (default: when "
    "the data have sweeps at 3 poses or more).", show_default=False)]

PluginOpt = Annotated[Optional[List[str]], typer.Option(
    "--plugin", help="Load effects from a Python file or an installed module (repeatable); see "
    "docs/effects_example_motor_mount.py.")]


def _load_plugins(refs) -> list[str]:
    """Load the plug-ins; the names of the effects they define."""
    from ..model.effects import load_plugin

    names: list[str] = []
    for r in refs or []:
        try:
            names += load_plugin(r)
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--plugin") from None
    return names


def _noise_notes(note: str, below: str = "") -> None:
    for text in (note, below):
        if text:
            err_console.print(f"[yellow]note[/] {text}", highlight=False)


def _f(v, nd=4) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def _skipped(skipped) -> None:
    for p, why in skipped:
        err_console.print(f"[yellow]skipped[/] {p}: {why}", highlight=False)


def _pos(p) -> str:
    return "(" + ", ".join(f"{v:g}" for v in p) + ")"


def _short(s) -> str:
    p = ",".join(f"{v:g}" for v in s.position_mm)
    return f"{'' if s.kind == 'assembled' else 'carriage '}{s.axis} @({p})"


def _table2(rep) -> None:
    """Rows x-to-x, y-to-y, z-to-z; per position a column "R2 mag  R2 phase  residual" (Table II)."""
    t2 = rep.table2()
    per = max(1, (console.width - 8) // 21)
    for k in range(0, len(t2), per):
        chunk = t2[k:k + per]
        t = Table(title="Table II layout: R^2 magnitude (linear), R^2 phase, complex residual per position (mm)"
                  if k == 0 else None, title_justify="left")
        t.add_column("")
        for p in chunk:
            t.add_column(f"{_pos(p['position_mm'])}\n mag  phase resid", justify="right", no_wrap=True)
        for a in ("x->x", "y->y", "z->z"):
            cells = []
            for p in chunk:
                r = p["rows"][a]
                cells.append("-" if r is None else f"{r['r2_mag']:5.3f} {r['r2_phase']:5.3f} {r['residual']:5.3f}")
            t.add_row(a.replace("->", "-to-"), *cells)
        console.print(t)


@app.command("validate")
def validate_cmd(
    data: DataArg,
    profile: ProfileOpt = None,
    compare: Annotated[Optional[Path], typer.Option("--compare", help="A second profile shown side by side "
                                                    "as 'before' (e.g. the profile before `ffcomp fit`).")] = None,
    report: Annotated[Optional[Path], typer.Option("--report", help="Write one self-contained HTML report.")] = None,
    plot: Annotated[Optional[Path], typer.Option("--plot", help="Write PNGs (Bode overlays, error map) here.")] = None,
    top: Annotated[int, typer.Option(help="Rows in the ranked-failures table.")] = 10,
    bode: Annotated[int, typer.Option(help="Bode overlays in the HTML report (the worst fits).")] = 12,
    noise_floor: NoiseOpt = None,
    plugin: PluginOpt = None,
    json: JsonOpt = False,
) -> None:
    """Compare the profile's model with measured FRFs: R^2 (Eq. 36), complex residual, where it fails."""
    _load_plugins(plugin)
    prof = load_profile_opt(profile)
    before = load_profile_opt(compare) if compare else None
    run = vf.run_validate(data, prof, before, noise_floor=noise_floor)
    rep = run.report
    others = (run.before,) if run.before is not None else ()
    r_mm = prof.geometry.print_radius_mm
    if report:
        from ..report.validate_report import html_report

        html_report(report, rep, others=others, comparison=run.comparison, print_radius_mm=r_mm, data_name=str(data),
                    max_bode=bode)
    if plot:
        from ..report.validate_report import write_plots

        write_plots(plot, rep, others=others, print_radius_mm=r_mm)
    _skipped(run.skipped)
    _noise_notes(rep.noise_note, rep.below_floor)
    if json:
        print_json(run.to_dict())
        return
    src = {s.noise_source for s in rep.scores}
    console.print(f"[bold]{rep.profile}[/] vs {len(rep.scores)} measurements in {data}")
    console.print(f"mean complex residual {_f(rep.mean_residual)} (coherence-weighted; noise floor "
                  f"{_f(rep.noise_floor)} from {'/'.join(sorted(src))}); mean R^2 magnitude {_f(rep.mean_r2_mag, 3)} "
                  f"linear, {_f(rep.mean_r2_mag_db, 3)} dB; phase {_f(rep.mean_r2_phase, 3)}")
    _table2(rep)
    t = Table(title=f"worst fits, ranked by complex residual (top {min(top, len(rep.scores))} of {len(rep.scores)})",
              title_justify="left")
    for c in ("measurement", "residual", "x noise", "R2 mag", "R2 mag dB", "R2 phase", "worst band"):
        t.add_column(c, justify="left" if c in ("measurement", "worst band") else "right",
                     no_wrap=c == "measurement")
    for s in rep.ranked()[:top]:
        wb = s.worst_band
        t.add_row(_short(s), _f(s.residual), _f(s.residual / s.noise, 1) if s.noise > 0 else "-", _f(s.r2_mag, 3),
                  _f(s.r2_mag_db, 3), _f(s.r2_phase, 3), f"{wb.name} ({wb.residual:.3f})" if wb else "-")
    console.print(t)
    w = rep.worst()
    if w["band"]:
        console.print(
            f"fails worst: band [bold]{w['band']['band']}[/] ({w['band']['mean_residual']:.3f}), pose "
            f"[bold]{_pos(w['pose']['position_mm'])}[/] mm ({w['pose']['mean_residual']:.3f}), axis "
            f"[bold]{w['axis']['axis']}[/] ({w['axis']['mean_residual']:.3f}); by band: "
            + ", ".join(f"{b['band']} {b['mean_residual']:.3f}" for b in rep.by_band()))
    if run.comparison:
        c = run.comparison
        t = Table(title="before / after", title_justify="left")
        for col in ("", f"before: {c['before'][:40]}", f"after: {c['after'][:40]}"):
            t.add_column(col, justify="right" if col else "left")
        t.add_row("mean complex residual", _f(c["mean_residual_before"]), _f(c["mean_residual_after"]))
        t.add_row("mean R^2 magnitude (linear)", _f(c["mean_r2_mag_before"], 3), _f(c["mean_r2_mag_after"], 3))
        t.add_row("mean R^2 phase", _f(c["mean_r2_phase_before"], 3), _f(c["mean_r2_phase_after"], 3))
        t.add_row("noise floor", _f(c["noise_floor"]), _f(c["noise_floor"]))
        console.print(t)
        t = Table(title=f"per measurement (worst {min(top, len(c['rows']))} before)", title_justify="left")
        for col in ("measurement", "residual before", "after", "R2 mag before", "after"):
            t.add_column(col, justify="left" if col == "measurement" else "right")
        for x in c["rows"][:top]:
            t.add_row(x["label"], _f(x["residual_before"]), _f(x["residual_after"]), _f(x["r2_mag_before"], 3),
                      _f(x["r2_mag_after"], 3))
        console.print(t)
    for path, what in ((report, "report"), (plot, "plots")):
        if path:
            console.print(f"wrote {what}: {path}")


def _fit_command_for(data, profile):
    """``candidate -> the ffcomp fit command`` with the real data and profile paths."""
    out = (Path(profile).with_name(Path(profile).stem + "_fitted.toml") if profile else Path("fitted.toml"))

    def real(c) -> str:
        if getattr(c, "kind", "effect") == "geometry":
            return f"ffcomp profile set {profile or 'printer.toml'} {c.set_value}"
        add = "" if c.refit else f" --add {c.effect}"
        prof = f" --profile {profile}" if profile else ""
        return f"ffcomp fit {data}{prof}{add} -o {out}"

    return real


def _changed(c) -> str:
    """The candidate's own fitted parameters that moved from their defaults (value ± std. error)."""
    from ..model.effects import EFFECTS

    if getattr(c, "kind", "effect") == "geometry":
        return ", ".join(f"{k}={v:.4g}" for k, v in c.params.items())
    out = []
    for e in c.estimates:
        if not c.refit and e.effect != c.effect:
            continue  # the base and the profile's own effects, refitted alongside
        if e.effect == "base":
            rel = abs(e.value - e.start) / max(abs(e.start), 1e-12)
            if rel > 0.02:
                out.append(f"{e.param}={e.value:.4g}")
            continue
        p = EFFECTS[e.effect].params[e.param]
        se = e.stderr if np.isfinite(e.stderr) else 0.0
        if abs(e.value - p.default) > max(2 * se, 0.005 * (e.hi - e.lo)):
            out.append(f"{e.param}={e.value:.4g}" + (f"±{e.stderr:.2g}" if np.isfinite(e.stderr) else "")
                       + (" (at bound)" if e.at_bound else ""))
    return ", ".join(out) or "(no change from the defaults)"


@app.command("diagnose")
def diagnose_cmd(
    data: DataArg,
    profile: ProfileOpt = None,
    candidates: Annotated[Optional[str], typer.Option(help="Comma-separated effects to try (default: all).")] = None,
    folds: Annotated[int, typer.Option(help="Cross-validation folds (by pose).")] = 4,
    noise_floor: NoiseOpt = None,
    base: BaseOpt = None,
    plugin: PluginOpt = None,
    json: JsonOpt = False,
) -> None:
    """Which physical effect is missing?  Fits each candidate, scores it on held-out poses, explains."""
    extra = _load_plugins(plugin)
    prof = load_profile_opt(profile)
    names = [c.strip() for c in candidates.split(",") if c.strip()] if candidates else None
    try:
        d, skipped = vf.run_diagnose(data, prof, candidates=names, folds=folds, noise_floor=noise_floor,
                                     refit_base=base, extra=extra)
    except ValueError as e:
        if type(e) is not ValueError:
            raise
        raise typer.BadParameter(str(e), param_hint="--candidates") from None
    _skipped(skipped)
    from ..measure.noise import below_floor_note

    _noise_notes(d.noise_note, below_floor_note(float(np.mean(d.base_residual)), d.noise_floor, d.noise_source))
    real = _fit_command_for(data, profile)
    verdict = d.verdict
    for c in d.candidates:
        verdict = verdict.replace(c.command, real(c))
    if json:
        out = d.to_dict()
        out["verdict"] = verdict
        for c, cd in zip(d.candidates, out["candidates"]):
            cd["command"] = real(c)
        print_json(out)
        return
    console.print(f"[bold]{d.profile}[/]: {len(d.labels)} measurements at {d.n_poses} poses; noise floor "
                  f"{d.noise_floor:.4f} (from {d.noise_source}); base model mean residual "
                  f"{np.mean(d.base_residual):.4f}")
    console.print(f"[bold]{verdict}[/]", highlight=False)
    t = Table(title=f"candidates, ranked by held-out residual ({d.folds}-fold cross-validation by pose)"
              if d.folds else "candidates (in-sample: too few poses to hold out)", title_justify="left")
    for c in ("#", "effect", "held-out residual", "drop", "removed", "significant", "fitted parameters"):
        t.add_column(c, justify="left" if c in ("effect", "fitted parameters") else "right")
    m0 = float(np.mean(d.base_residual))
    for i, c in enumerate(d.candidates, 1):
        ps = _changed(c)
        # "removed" is a share of the error above the noise: meaningless when the base is at the floor
        removed = f"{max(c.removed, -9.99):.0%}" if d.base_significant else "-"
        drop = f"{m0 / c.mean_heldout:.2f}x" if c.mean_heldout > 0 else "-"
        t.add_row(str(i), c.label, _f(c.mean_heldout), drop, removed, "yes" if c.significant else "no", ps)
    console.print(t)
    for c in d.candidates[:3]:
        if c.significant:
            console.print(f"[bold]{c.label}[/]: {c.explanation}", highlight=False)
            for e in c.evidence:
                console.print(f"  - {e}", highlight=False)
    if d.evidence:
        console.print("[bold]what the residual looks like[/]")
        for e in d.evidence:
            console.print(f"  - {e.text}", highlight=False)


def _set_values(items):
    from ..loop.fit import parse_assignment

    out = []
    for s in items or []:
        try:
            name, param, value = parse_assignment(s)
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--set") from None
        if value is None:
            raise typer.BadParameter(f"{s!r}: expected EFFECT:PARAM=VALUE", param_hint="--set")
        out.append((name, param, value))
    return out


@app.command("fit")
def fit_cmd(
    data: DataArg,
    add: Annotated[Optional[List[str]], typer.Option("--add", help="Effect to add and fit (repeatable).")] = None,
    output: Annotated[Optional[Path], typer.Option("--output", "-o", help="Write the fitted profile here.")] = None,
    set_: Annotated[Optional[List[str]], typer.Option("--set", help="Fix EFFECT:PARAM=VALUE before fitting.")] = None,
    free: Annotated[Optional[List[str]], typer.Option("--free", help="Also fit EFFECT:PARAM (repeatable).")] = None,
    refit: Annotated[bool, typer.Option(help="Refit the profile's existing effects too.")] = True,
    base: BaseOpt = None,
    noise_floor: NoiseOpt = None,
    plugin: PluginOpt = None,
    profile: ProfileOpt = None,
    json: JsonOpt = False,
) -> None:
    """Add effects to the profile and fit their parameters to the measurements (and the base dynamics)."""
    from ..profile import save_profile

    _load_plugins(plugin)
    prof = load_profile_opt(profile)
    frees = []
    for s in free or []:
        name, _, param = s.partition(":")
        if not param:
            raise typer.BadParameter(f"{s!r}: expected EFFECT:PARAM", param_hint="--free")
        frees.append((name.strip(), param.strip()))
    try:
        run = vf.run_fit(data, prof, add or [], set_values=_set_values(set_), free=frees, refit=refit, base=base,
                         noise_floor=noise_floor)
    except ValueError as e:
        if type(e) is not ValueError:
            raise
        raise typer.BadParameter(str(e), param_hint="--add/--set/--free") from None
    if output:
        save_profile(run.profile, output)
    _skipped(run.skipped)
    _noise_notes(run.noise_note)
    if json:
        print_json({**run.to_dict(), "output": str(output) if output else None})
        return
    r = run.result
    t = Table(title="fitted parameters", title_justify="left")
    for c in ("effect", "parameter", "value", "std. error", "unit", "start", "note"):
        t.add_column(c, justify="right" if c in ("value", "std. error", "start") else "left")
    for e in r.estimates:
        t.add_row(e.effect, e.param, f"{e.value:.5g}", f"{e.stderr:.2g}" if np.isfinite(e.stderr) else "-", e.unit,
                  f"{e.start:.4g}", f"at bound [{e.lo:g}, {e.hi:g}]" if e.at_bound else "")
    console.print(t)
    console.print(f"mean complex residual {np.mean(r.residual_before):.4f} -> {np.mean(r.residual_after):.4f} "
                  f"(noise floor {run.noise_floor:.4f}); {r.nfev} model evaluations"
                  + ("; base dynamics refitted with the effects" if r.base is not None else ""))
    bound = [f"{e.effect}:{e.param}" for e in r.estimates if e.at_bound]
    if bound:
        err_console.print(f"[yellow]warning[/] at a bound of its fit range: {', '.join(bound)} -- the true value may "
                          "lie beyond it, or the effect stands in for another one (diagnose again)", highlight=False)
    if output:
        console.print(f"wrote {output}; check it: ffcomp validate {data} --profile {output}"
                      + (f" --compare {profile}" if profile else ""))


@app.command("virtual-measure")
def virtual_cmd(
    output: Annotated[Path, typer.Option("--output", "-o", help="Directory to write the FRF files into.")],
    effect: Annotated[Optional[List[str]], typer.Option(
        "--effect", help="Hidden effect: NAME, NAME=VALUE (its main parameter) or NAME:PARAM=VALUE; "
                         "repeatable.")] = None,
    noise: Annotated[float, typer.Option(help="Relative complex noise (0.02 = 2 %).")] = 0.02,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    fmin: Annotated[float, typer.Option(help="Lowest frequency, Hz.")] = 5.0,
    fmax: Annotated[float, typer.Option(help="Highest frequency, Hz.")] = 400.0,
    n: Annotated[int, typer.Option(help="Log-spaced frequencies per sweep.")] = 250,
    heights: Annotated[str, typer.Option(help="Nozzle heights of the task sweeps, mm (comma-separated).")] = "30,130",
    offset: Annotated[Optional[float], typer.Option(help="Lateral offset of the off-centre poses, mm.")] = None,
    truth: Annotated[Optional[Path], typer.Option(help="Also write the hidden profile (a spoiler) here.")] = None,
    averages: Annotated[Optional[int], typer.Option(help="Coherence as from this many H1 averages (default: 1).")]
    = None,
    no_averages_key: Annotated[bool, typer.Option("--no-averages-key", help="Do not write the 'averages' header "
                                                  "key (a coherence of unknown averages count).")] = False,
    all_carriages: Annotated[bool, typer.Option("--all-carriages", help="Also the carriage sweeps of towers B and C "
                                                "(at the end).")] = False,
    plugin: PluginOpt = None,
    profile: ProfileOpt = None,
    json: JsonOpt = False,
) -> None:
    """Virtual measurement set from the LPV model with hidden effects (identification + validation sweeps)."""
    _load_plugins(plugin)
    if not (0 < fmin < fmax) or n < 8:
        raise typer.BadParameter("need 0 < fmin < fmax and n >= 8", param_hint="--fmin/--fmax/--n")
    if not 0 <= noise < 1:
        raise typer.BadParameter(f"noise must be in [0, 1), got {noise}", param_hint="--noise")
    try:
        effs = vf.parse_effect_args(effect or [])
        hs = [float(h) for h in heights.split(",") if h.strip()]
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--effect/--heights") from None
    prof = load_profile_opt(profile)
    paths = vf.run_virtual(prof, effs, output, noise=noise, seed=seed, freq_hz=np.geomspace(fmin, fmax, n),
                           heights_mm=hs, offset_mm=offset, truth=truth, averages=averages,
                           averages_key=not no_averages_key, all_carriages=all_carriages)
    if json:
        print_json({"files": [str(p) for p in paths], "noise": noise, "seed": seed,
                    "truth": str(truth) if truth else None})
        return
    console.print(f"wrote {len(paths)} FRF files to {output} ({noise * 100:g}% noise, seed {seed}"
                  + (f"; hidden profile in {truth}" if truth else "") + ")")


@app.command("frf")
def frf_cmd(
    response: Annotated[Path, typer.Argument(help="Measured response CSV (e.g. Klipper raw accelerometer CSV).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="FRF file to write (FRF_FORMAT).")],
    command: Annotated[Optional[Path], typer.Option(help="Command CSV (time + commanded position, mm); default: "
                                                   "the response file.")] = None,
    input_: Annotated[str, typer.Option("--input", help="Swept coordinate: x, y, z, qA, qB, qC.")] = "x",
    output_axis: Annotated[str, typer.Option("--output-axis", help="Measured coordinate.")] = "x",
    command_column: Annotated[Optional[str], typer.Option(help="Command column (default: --input).")] = None,
    response_column: Annotated[Optional[str], typer.Option(help="Response column (default: accel_<axis>).")] = None,
    kind: Annotated[str, typer.Option(help="assembled or carriage.")] = "assembled",
    at: Annotated[str, typer.Option("--at", help="Sweep position X,Y,Z in mm.")] = "0,0,30",
    quantity: Annotated[str, typer.Option(help="Response quantity: auto, position, acceleration.")] = "auto",
    resolution: Annotated[float, typer.Option(help="Frequency resolution, Hz.")] = 1.0,
    fmin: Annotated[Optional[float], typer.Option(help="Lowest frequency kept, Hz.")] = None,
    fmax: Annotated[Optional[float], typer.Option(help="Highest frequency kept, Hz.")] = None,
    scale: Annotated[float, typer.Option(help="Factor on the response (e.g. -1 for a flipped sensor axis).")] = 1.0,
    min_coherence: Annotated[float, typer.Option(help="Drop frequencies below this coherence.")] = 0.0,
    json: JsonOpt = False,
) -> None:
    """FRF (H1, coherence) from a known command and a measured response; acceleration / (j w)^2."""
    from ..measure.frf_file import COORDS, KINDS

    for v, hint in ((input_, "--input"), (output_axis, "--output-axis")):
        if v not in COORDS:
            raise typer.BadParameter(f"must be one of {', '.join(COORDS)}, got {v!r}", param_hint=hint)
    if kind not in KINDS:
        raise typer.BadParameter(f"must be one of {', '.join(KINDS)}", param_hint="--kind")
    rc = response_column or f"accel_{output_axis if output_axis in 'xyz' else 'z'}"
    est, meas = vf.run_frf(response, command, response_column=rc, command_column=command_column or input_, kind=kind,
                           position_mm=parse_triple(at), input_=input_, output=output_axis, out=output,
                           quantity=quantity, resolution_hz=resolution, f_lo_hz=fmin, f_hi_hz=fmax, scale=scale,
                           min_coherence=min_coherence)
    if json:
        print_json({**est.to_dict(), "output": str(output)})
        return
    console.print(f"wrote {output}: {len(est.freq_hz)} frequencies {est.freq_hz[0]:.3g}..{est.freq_hz[-1]:.4g} Hz, "
                  f"{est.averages} averages of {est.nperseg} samples at {est.fs_hz:.1f} Hz ({est.quantity}); "
                  f"median coherence {np.median(est.coherence):.3f}")


@app.command("effects")
def effects_cmd(json: JsonOpt = False) -> None:
    """The library of physical effects and their parameters."""
    cat = vf.effects_catalogue()
    if json:
        print_json(cat)
        return
    for e in cat:
        t = Table(title=f"{e['name']}: {e['summary']}", title_justify="left")
        for c in ("parameter", "default", "unit", "fit range", "fitted", "meaning"):
            t.add_column(c)
        for p in e["params"]:
            t.add_row(p["name"], f"{p['default']:g}", p["unit"], f"{p['search'][0]:g}..{p['search'][1]:g}",
                      "yes" if p["fitted"] else "", p["doc"])
        console.print(t)
