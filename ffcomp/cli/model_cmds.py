"""``ffcomp model show|frf|modes``: inspect the printer's LPV model."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, List, Optional

import numpy as np
import typer
from rich.table import Table

from ..pipeline import model_flow as mf
from .common import JsonOpt, PlotOpt, ProfileOpt, app, console, load_profile_opt, parse_triple, print_json

model_app = typer.Typer(help="Inspect the printer model: parameters, frequency responses, modes.",
                        no_args_is_help=True)
app.add_typer(model_app, name="model")

DEFAULT_POSES = ["0,0,30", "-110,0,30", "0,-110,30", "110,0,30"]


@model_app.command("show")
def show(profile: ProfileOpt = None, json: JsonOpt = False) -> None:
    """Print the profile: geometry, limits, dynamics and the modal quantities they imply."""
    prof = load_profile_opt(profile)
    s = mf.model_summary(prof)
    if json:
        print_json(s)
        return
    console.print(f"[bold]{s['name']}[/]  ({s['source']})")
    for sec in ("geometry", "limits"):
        t = Table(title=sec, show_header=False, title_justify="left")
        for k, v in s[sec].items():
            t.add_row(k, str(v))
        console.print(t)
    t = Table(title="dynamics (SI)", title_justify="left")
    t.add_column("parameter")
    t.add_column("value")
    for k, v in s["dynamics"].items():
        t.add_row(k, ", ".join(f"{x:g}" for x in v) if isinstance(v, list) else f"{v:g}")
    console.print(t)
    t = Table(title="derived (Eqs. 26-32)", title_justify="left")
    for c in ("tower", "f_n (Hz)", "zeta", "f_n loaded (Hz)", "zeta loaded", "drive (Hz)", "drive zeta",
              "RHP zero (Hz)"):
        t.add_column(c)
    for d, dm in zip(s["derived"], s["drive"]):
        t.add_row(d["tower"], f"{d['f_n_hz']:.2f}", f"{d['zeta']:.4f}", f"{d['f_n_loaded_hz']:.2f}",
                  f"{d['zeta_loaded']:.4f}", f"{dm['freq_hz']:.2f}", f"{dm['damping']:.4f}",
                  "-" if dm["rhp_zero_hz"] is None else f"{dm['rhp_zero_hz']:.2f}")
    console.print(t)
    if s["effects"]:
        console.print("effects: " + "; ".join(str(e) for e in s["effects"]))


@model_app.command("frf")
def frf(
    at: Annotated[str, typer.Option("--at", help="Nozzle position X,Y,Z in mm.")] = "0,0,30",
    input_: Annotated[str, typer.Option("--input", help="Commanded coordinate: x, y, z, qA, qB, qC.")] = "x",
    output: Annotated[str, typer.Option("--output", help="Measured coordinate: x, y, z, qA, qB, qC.")] = "x",
    fmin: Annotated[float, typer.Option(help="Lowest frequency, Hz.")] = 1.0,
    fmax: Annotated[float, typer.Option(help="Highest frequency, Hz.")] = 300.0,
    n: Annotated[int, typer.Option(help="Number of log-spaced frequencies.")] = 400,
    csv: Annotated[Optional[Path], typer.Option(help="Write the response as an FRF file (FRF_FORMAT).")] = None,
    profile: ProfileOpt = None,
    json: JsonOpt = False,
    plot: PlotOpt = None,
) -> None:
    """Predicted frequency response from one commanded coordinate to one measured coordinate."""
    if not (0 < fmin < fmax):
        raise typer.BadParameter(f"need 0 < fmin < fmax, got {fmin}, {fmax}", param_hint="--fmin/--fmax")
    if n < 2:
        raise typer.BadParameter(f"need at least 2 frequencies, got {n}", param_hint="--n")
    prof = load_profile_opt(profile)
    pos = parse_triple(at)
    try:
        mf.frame_for(input_, output)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    r = mf.model_frf(prof, pos, input_, output, np.geomspace(fmin, fmax, n))
    if csv:
        from ..measure.frf_file import FrfMeasurement, save_frf

        save_frf(FrfMeasurement(r.freq_hz, r.H, None, "assembled", r.position_mm, input_, output,
                                f"ffcomp model prediction, profile {prof.name!r}"), csv)
    if plot:
        from ..report.plots import bode_png

        bode_png(plot, r.freq_hz, [(f"{input_}->{output}", r.H)], title=f"{prof.name} at {at} mm")
    if json:
        print_json(r.to_dict())
        return
    t = Table(title=f"{input_} -> {output} at ({at}) mm: resonance peaks", title_justify="left")
    t.add_column("freq (Hz)")
    t.add_column("|H|")
    t.add_column("|H| (dB)")
    for f, m in r.peaks():
        t.add_row(f"{f:.2f}", f"{m:.4f}", f"{20 * np.log10(m):.2f}")
    console.print(t)
    dc = r.H[0]
    console.print(f"|H| at {r.freq_hz[0]:g} Hz = {abs(dc):.4f}; at {r.freq_hz[-1]:g} Hz = {abs(r.H[-1]):.4f}")


@model_app.command("modes")
def modes_cmd(
    at: Annotated[Optional[List[str]], typer.Option("--at", help="Pose X,Y,Z in mm (repeatable).")] = None,
    map_: Annotated[bool, typer.Option("--map", help="Map the modes over the bed instead.")] = False,
    z: Annotated[float, typer.Option(help="Height of the map, mm.")] = 30.0,
    step: Annotated[float, typer.Option(help="Grid step of the map, mm.")] = 10.0,
    profile: ProfileOpt = None,
    json: JsonOpt = False,
    plot: PlotOpt = None,
) -> None:
    """Coupled mechanical modes (natural frequency, damping, direction) at poses or over the bed."""
    prof = load_profile_opt(profile)
    if map_:
        ms = mf.mode_map(prof, z, step)
    else:
        poses = [parse_triple(a) for a in (at or DEFAULT_POSES)]
        ms = mf.model_modes(prof, poses)
    if plot:
        from ..report.plots import mode_map_png

        if map_:
            mode_map_png(plot, ms.xyz_m[:, :2] * 1e3, ms.freq_hz, title=f"{prof.name}: modes at z = {z} mm",
                         print_radius_mm=prof.geometry.print_radius_mm)
        else:
            _modes_bar_png(plot, ms)
    if json:
        d = ms.to_dict()
        if map_:
            d = {"z_mm": z, "step_mm": step, "xy_mm": (ms.xyz_m[:, :2] * 1e3).tolist(),
                 "freq_hz": ms.freq_hz.tolist(), "damping": ms.damping.tolist()}
        print_json(d)
        return
    if map_:
        t = Table(title=f"modes over the bed at z = {z} mm ({len(ms.freq_hz)} points)", title_justify="left")
        for c in ("mode", "min (Hz)", "max (Hz)", "at min (x, y mm)", "at max (x, y mm)"):
            t.add_column(c)
        for j in range(3):
            lo, hi = int(np.argmin(ms.freq_hz[:, j])), int(np.argmax(ms.freq_hz[:, j]))
            t.add_row(str(j + 1), f"{ms.freq_hz[lo, j]:.2f}", f"{ms.freq_hz[hi, j]:.2f}",
                      f"({ms.xyz_m[lo, 0] * 1e3:.0f}, {ms.xyz_m[lo, 1] * 1e3:.0f})",
                      f"({ms.xyz_m[hi, 0] * 1e3:.0f}, {ms.xyz_m[hi, 1] * 1e3:.0f})")
        console.print(t)
        return
    t = Table(title="coupled mechanical modes (drive resonance not listed: see `model show`)",
              title_justify="left")
    t.add_column("position (mm)")
    for j in range(3):
        t.add_column(f"mode {j + 1}: Hz (zeta, dir)")
    for p in range(len(ms.freq_hz)):
        pos = ", ".join(f"{v:g}" for v in ms.xyz_m[p] * 1e3)
        t.add_row(f"({pos})", *[f"{ms.freq_hz[p, j]:.2f} ({ms.damping[p, j]:.3f}, {ms.direction[p, j]})"
                                for j in range(3)])
    console.print(t)


def _modes_bar_png(path, ms) -> None:
    from ..report.plots import _plt

    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4))
    P = len(ms.freq_hz)
    for j in range(3):
        ax.bar(np.arange(P) + (j - 1) * 0.25, ms.freq_hz[:, j], width=0.25, label=f"mode {j + 1}")
    ax.set_xticks(np.arange(P), [f"({', '.join(f'{v:g}' for v in ms.xyz_m[p] * 1e3)})" for p in range(P)],
                  rotation=20, fontsize=8)
    ax.set_ylabel("natural frequency (Hz)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
