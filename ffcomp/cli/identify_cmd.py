"""``ffcomp identify CARRIAGE.csv ASSEMBLED.csv --m-n .. --m-f .. -o printer.toml``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, List, Optional

import numpy as np
import typer
from rich.table import Table

from .common import JsonOpt, PlotOpt, ProfileOpt, app, console, err_console, load_profile_opt, print_json


@app.command("identify")
def identify_cmd(
    carriage: Annotated[Path, typer.Argument(help="FRF file of the carriage sweep, effector detached.")],
    assembled: Annotated[Path, typer.Argument(help="FRF file of the vertical sweep at the bed centre.")],
    m_n: Annotated[float, typer.Option("--m-n", help="Measured effector mass, kg.")],
    m_f: Annotated[float, typer.Option("--m-f", help="Measured mass of one forearm pair, kg.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Write the identified profile here.")] = None,
    profile: ProfileOpt = None,
    sweep: Annotated[Optional[List[Path]], typer.Option(
        "--sweep", help="More FRF files (or a directory of them) to refine with, repeatable: the carriage sweeps "
        "of towers B and C (kind: carriage, qB->qB, qC->qC) remove the bias of unequal towers; assembled sweeps "
        "elsewhere pin the effector damping b_nt, which the two sweeps determine poorly.")]
    = None,
    json: JsonOpt = False,
    plot: PlotOpt = None,
) -> None:
    """Identify the carriage and effector parameters from the paper's two sweeps (Section IV-A).

    Geometry and limits come from --profile (default: the embedded profile); the dynamics are
    replaced by the identified ones.  The fit is bounded to physical values (c, b, b_nt >= 0,
    m > 0); warnings say when and where the sweeps do not fit the model.
    """
    from ..loop.identify import identify
    from ..measure.frf_file import load_frf
    from ..pipeline.validate_flow import base_name
    from ..profile import save_profile

    if m_n <= 0:
        raise typer.BadParameter(f"effector mass must be > 0 kg, got {m_n}", param_hint="--m-n")
    if m_f < 0:
        raise typer.BadParameter(f"forearm pair mass must be >= 0 kg, got {m_f}", param_hint="--m-f")
    base = load_profile_opt(profile)
    notes = []
    if profile is None:
        g = base.geometry
        notes.append(f"no --profile: used the default geometry (arm {g.arm_length_mm[0]:g} mm, delta radius "
                     f"{g.delta_radius_mm[0]:g} mm, towers {'/'.join(f'{t:g}' for t in g.tower_angles_deg)} deg) of "
                     f"'{base.name}'; give your printer's with --profile (ffcomp profile import --klipper "
                     "printer.cfg, or ffcomp profile set)")
    c, a = load_frf(carriage), load_frf(assembled)
    res = identify(c, a, m_n, m_f)
    new = res.apply_to(base)
    new = new.with_(name=f"{base_name(base.name)} (identified from {carriage.name}, {assembled.name})")
    refined = None
    if sweep:
        from ..loop.identify_refine import refine_identification
        from ..measure.dataset import load_dataset

        same = {Path(carriage).resolve(), Path(assembled).resolve()}
        extra = [m for p in sweep for m in (load_dataset(p) if Path(p).is_dir() else [load_frf(p)])
                 if m.path is None or Path(m.path).resolve() not in same]
        refined = refine_identification(new, [c, a] + extra)
        new = refined.profile.with_(name=f"{base_name(base.name)} (identified from {carriage.name}, "
                                    f"{assembled.name} + {len(extra)} sweeps)")
    if output:
        save_profile(new, output)
    if plot:
        from ..report.plots import fit_overlay_png

        fit_overlay_png(plot, [("carriage", c, res.carriage_fit.response(c.freq_hz)),
                               ("assembled", a, res.assembled_fit.response(a.freq_hz))],
                        title="two-sweep identification (Eq. 22 fits)")
    warns = list(notes) + list(res.warnings)
    if refined is not None:
        warns = [w for w in warns if "assumes three equal towers" not in w]
    if json:
        out = {**res.to_dict(), "profile": str(output) if output else None, "warnings": warns}
        if refined is not None:
            out["refined"] = refined.to_dict()
        print_json(out)
        for w in warns:
            err_console.print(f"[yellow]warning[/] {w}", highlight=False)
        return
    t = Table(title="identified parameters", title_justify="left")
    t.add_column("parameter")
    t.add_column("value")
    t.add_column("unit")
    for k, unit in (("m", "kg"), ("c", "N s/m"), ("b", "N s/m"), ("k", "N/m"), ("b_nt", "N s/m"),
                    ("d0", "1/s^2"), ("d1", "1/s"), ("d2", "1/s"), ("m_nt", "kg")):
        t.add_row(k, f"{getattr(res, k):.6g}", unit)
    console.print(t)
    t = Table(title="fit quality (Eq. 22 fits)", title_justify="left")
    for col in ("sweep", "f_n (Hz)", "zeta", "complex residual", "R2 mag", "R2 mag dB", "R2 phase"):
        t.add_column(col)
    for name, f in (("carriage", res.carriage_fit), ("assembled", res.assembled_fit)):
        t.add_row(name, f"{f.wn / 2 / np.pi:.3f}", f"{f.zeta:.4f}", f"{f.residual:.4f}", f"{f.r2_mag:.4f}",
                  f"{f.r2_mag_db:.4f}", f"{f.r2_phase:.4f}")
    console.print(t)
    if refined is not None:
        console.print(f"refined with {len(refined.residual_before) - 2} more sweeps (towers with a carriage sweep: "
                      f"{', '.join(refined.towers) or 'none besides A'}): mean residual "
                      f"{np.mean(refined.residual_before):.4f} -> {np.mean(refined.residual_after):.4f}; "
                      f"belt stiffness k_B/k_A = {refined.k_ratio[1]:.3f}, k_C/k_A = {refined.k_ratio[2]:.3f}")
    for w in warns:
        err_console.print(f"[yellow]warning[/] {w}", highlight=False)
    if output:
        console.print(f"wrote {output}")
