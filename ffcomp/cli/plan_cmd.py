"""``ffcomp plan IN.gcode``: parse and plan a G-code file the way the firmware would, and report it."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer
from rich.markup import escape
from rich.table import Table

from .common import JsonOpt, PlotOpt, ProfileOpt, app, console, err_console, load_profile_opt, print_json

_CSV_HEADER = "t_s,x_mm,y_mm,z_mm,e_mm,qA_mm,qB_mm,qC_mm"


def _fmt_time(s: float) -> str:
    h, rem = divmod(s, 3600.0)
    m, sec = divmod(rem, 60.0)
    return f"{int(h)}:{int(m):02d}:{sec:06.3f}" if h else f"{int(m)}:{sec:06.3f}"


def _write_csv(path: Path, gcode: Path, prof, lenient: bool, firmware: Optional[str]) -> int:
    """Stream the sampled trajectory to ``path``; returns the number of rows."""
    from ..gcode.sampler import sample_gcode
    from ..io_atomic import atomic_open

    rows = 0
    with atomic_open(path, "w") as f:
        f.write(_CSV_HEADER + "\n")
        for b in sample_gcode(gcode, prof, lenient=lenient, firmware=firmware):
            sl = b.new_rows()
            data = np.column_stack([b.t_s[sl], b.xyz_m[sl] * 1e3, b.e_mm[sl], b.q_m[sl] * 1e3])
            np.savetxt(f, data, fmt=["%.6f"] + ["%.6f"] * 7, delimiter=",")
            rows += data.shape[0]
    return rows


def _plot(path: Path, summary, trace) -> None:
    """XY path and speed profile as a PNG (matplotlib imported here only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io_atomic import atomic_open

    fig, (ax_xy, ax_v) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1, 1.4]})
    xy = trace.xy_mm
    if len(xy) > 1:
        from matplotlib.collections import LineCollection

        seg = np.stack([xy[:-1], xy[1:]], axis=1)
        ok = np.isfinite(seg).all(axis=(1, 2))
        ext = trace.extruding[1:]
        ax_xy.add_collection(LineCollection(seg[ok & ~ext], lw=0.3, colors="0.75", label="travel"))
        ax_xy.add_collection(LineCollection(seg[ok & ext], lw=0.5, colors="C0", label="extruding"))
        ax_xy.autoscale()
        ax_xy.legend(loc="upper right", fontsize=8)
    ax_xy.set_aspect("equal", adjustable="datalim")
    ax_xy.set_xlabel("x (mm)")
    ax_xy.set_ylabel("y (mm)")
    ax_xy.set_title("XY path")
    ax_v.plot(trace.t_s, trace.speed_mm_s, lw=0.5, color="C1")
    ax_v.set_xlabel("print time (s)")
    ax_v.set_ylabel("speed along path (mm/s)")
    ax_v.set_title(f"speed profile ({summary.planner} planner)")
    ax_v.grid(alpha=0.3)
    fig.suptitle(f"{Path(summary.path).name}: {summary.moves} moves, {_fmt_time(summary.duration_s)}")
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=120)
    plt.close(fig)


@app.command("plan")
def plan(
    gcode: Annotated[Path, typer.Argument(help="G-code file to plan.", exists=True, dir_okay=False,
                                          readable=True)],
    profile: ProfileOpt = None,
    csv: Annotated[Optional[Path], typer.Option(
        "--csv", help="Write the sampled trajectory (t, x, y, z, e, qA, qB, qC; s and mm) at the profile's "
        "sample rate.")] = None,
    plot: PlotOpt = None,
    json: JsonOpt = False,
    lenient: Annotated[bool, typer.Option("--lenient", help="Skip malformed lines with a warning instead of "
                                          "stopping.")] = False,
    planner: Annotated[Optional[str], typer.Option(
        "--planner", help="Override the profile's firmware planner (klipper or marlin).")] = None,
) -> None:
    """Plan a G-code file by the firmware's rules: duration, speeds, distances; optional samples and plot."""
    from ..gcode.planner import PLANNERS
    from ..gcode.summary import summarize_gcode

    if planner is not None and planner not in PLANNERS:
        raise typer.BadParameter(f"unknown planner {planner!r} (known: {', '.join(PLANNERS)})",
                                 param_hint="--planner")
    from ..io_atomic import check_output_path

    for p, what in ((csv, "CSV"), (plot, "plot")):
        if p is not None:
            check_output_path(p, what)
    prof = load_profile_opt(profile)
    res = summarize_gcode(gcode, prof, lenient=lenient, firmware=planner, trace=plot is not None)
    s, trace = res if plot is not None else (res, None)
    rows = _write_csv(csv, gcode, prof, lenient, planner) if csv is not None else None
    if plot is not None:
        _plot(plot, s, trace)
    if json:
        d = s.to_dict()
        d["csv"] = None if csv is None else {"path": str(csv), "rows": rows}
        d["plot"] = None if plot is None else str(plot)
        print_json(d)
        return
    t = Table(title=f"{s.path}", show_header=False, title_justify="left")
    t.add_row("firmware planner", s.planner)
    cc = s.command_counts
    t.add_row("lines", f"{s.lines:,}" + (f"  ({cc['skipped']} malformed, skipped)" if cc.get("skipped") else ""))
    if cc.get("stop") or cc.get("unknown"):
        t.add_row("stops", f"{cc.get('stop', 0)} (M600, T<n>, G29, ...), {cc.get('unknown', 0)} unknown commands")
    t.add_row("moves", f"{s.moves:,} XYZ, {s.extrude_only_moves:,} extruder-only, {s.dwells:,} dwells")
    t.add_row("duration", f"{_fmt_time(s.duration_s)}  ({s.duration_s:.3f} s, dwells {s.dwell_time_s:.3f} s)")
    t.add_row("peak speed", f"{s.peak_speed_mm_s:.1f} mm/s")
    t.add_row("peak acceleration", f"{s.peak_accel_mm_s2:.0f} mm/s^2")
    t.add_row("distance", f"{s.distance_mm:,.1f} mm  (extruding {s.extruding_distance_mm:,.1f}, travel "
              f"{s.travel_distance_mm:,.1f})")
    t.add_row("filament", f"{s.extruded_mm:,.2f} mm extruded, {s.retracted_mm:,.2f} mm retracted")
    lo, hi = s.bbox_min_mm, s.bbox_max_mm
    t.add_row("extent",
              f"x {lo[0]:.2f}..{hi[0]:.2f}, y {lo[1]:.2f}..{hi[1]:.2f}, z {lo[2]:.2f}..{hi[2]:.2f} mm")
    if s.ignored_commands:
        t.add_row("ignored by firmware", f"{s.ignored_commands} limit command(s)")
    if csv is not None:
        t.add_row("samples", f"{rows:,} rows -> {csv}")
    if plot is not None:
        t.add_row("plot", str(plot))
    console.print(t)
    from ..gcode.flavour import detect_flavour, flavour_mismatch

    flavour_note = flavour_mismatch(detect_flavour(str(gcode)), s.planner, str(gcode), prof.name)
    for msg in list(s.warning_messages) + ([flavour_note] if flavour_note else []):
        err_console.print(f"[yellow]warning:[/] {escape(str(msg))}", highlight=False, soft_wrap=True)
