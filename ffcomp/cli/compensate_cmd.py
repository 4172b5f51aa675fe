"""``ffcomp compensate IN.gcode -o OUT.gcode`` (also the bare ``ffcomp IN.gcode -o OUT.gcode``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from .common import JsonOpt, ProfileOpt, app, err_console, load_profile_opt, print_json

FORMATS = ("gcode", "steps", "steps-csv")


@app.command("compensate")
def compensate_cmd(
    source: Annotated[Path, typer.Argument(help="G-code file to compensate.")],
    output: Annotated[Optional[str], typer.Option("--output", "-o", help="Output file; '-' for stdout; "
                                                  "default: replace the input in place.")] = None,
    fmt: Annotated[str, typer.Option("--format", help="gcode | steps (compact .ffsteps) | steps-csv.")] = "gcode",
    method: Annotated[str, typer.Option(help="Inverse variant: lpv (default) or lti-centre.")] = "lpv",
    tol_um: Annotated[float, typer.Option("--tol-um", help="G-code point placement tolerance, um.")] = 5.0,
    z_mode: Annotated[str, typer.Option("--z-mode", help="keep: compensated z everywhere; hold: keep planned "
                                        "z on layer moves (firmware with low max_z_accel); auto: planned z on "
                                        "moves that travel in z.")] = "keep",
    pin_holds: Annotated[bool, typer.Option("--pin-holds/--no-pin-holds", help="Keep the command on the "
                                            "reference during extruder-only moves and dwells.")] = False,
    plan_where_limited: Annotated[bool, typer.Option(
        "--plan-where-limited/--compensate-where-limited",
        help="Follow the plan where the firmware's limits would make the compensated command run late "
             "(moves bound by the extruder's limits; the z of z-hops right after a retraction).")] = True,
    self_check: Annotated[bool, typer.Option("--self-check/--no-self-check", help="Re-plan the output and "
                                             "compare with the intended commands.")] = True,
    self_check_tol_um: Annotated[float, typer.Option("--self-check-tol-um", help="Self-check limit, um.")] = 50.0,
    predict: Annotated[bool, typer.Option("--predict/--no-predict", help="Predict the residual vibration "
                                          "before/after with the model (summary).")] = True,
    lenient: Annotated[bool, typer.Option(help="Count malformed G-code lines as warnings.")] = False,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Progress bar on stderr.")] = True,
    profile: ProfileOpt = None,
    json: JsonOpt = False,
) -> None:
    """Compensate a G-code file for the printer's vibration (model-based feedforward).

    Writes atomically: on any error the input and any existing output are left untouched.
    """
    from ..compensate.inverse import InverseConfig
    from ..pipeline.compensate_flow import CompensateOptions, compensate_file

    if fmt not in FORMATS:
        raise typer.BadParameter(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if method not in ("lpv", "lti-centre"):
        raise typer.BadParameter(f"--method must be lpv or lti-centre for files, got {method!r}")
    if z_mode not in ("keep", "hold", "auto"):
        raise typer.BadParameter(f"--z-mode must be keep, hold or auto, got {z_mode!r}")
    if tol_um <= 0:
        raise typer.BadParameter(f"--tol-um must be > 0, got {tol_um}")
    prof = load_profile_opt(profile)
    out = str(source) if output is None else (None if output == "-" else output)
    if fmt != "gcode":
        from ..pipeline.steps_flow import steps_file

        if out is None or out == str(source):
            raise typer.BadParameter("--format steps needs an output file (-o FILE)")
        summ = steps_file(str(source), out, prof, method=method, lenient=lenient, csv=(fmt == "steps-csv"))
        _report(summ.to_dict(), json)
        return
    opts = CompensateOptions(method=method, tol_um=tol_um, z_mode=z_mode, self_check=self_check,
                             self_check_tol_um=self_check_tol_um, predict=predict, lenient=lenient,
                             pin_holds=pin_holds, inverse=InverseConfig(method=method),
                             plan_where_limited=plan_where_limited)
    show = progress and not json and os.environ.get("CI") != "true"
    if show:
        with Progress(TextColumn("[bold]compensating[/] {task.description}"), BarColumn(),
                      TextColumn("{task.percentage:>3.0f}%"), TimeElapsedColumn(), console=err_console,
                      transient=True) as bar:
            task = bar.add_task(source.name, total=1)

            def cb(line, total):
                bar.update(task, completed=line, total=max(total, 1))

            summ = compensate_file(str(source), out, prof, opts, progress=cb)
    else:
        summ = compensate_file(str(source), out, prof, opts)
    _report(summ.to_dict(), json, to_stderr=(out is None))


def _report(d: dict, json: bool, to_stderr: bool = False) -> None:
    if json:
        if to_stderr:  # stdout carries the G-code
            import json as _json
            import sys

            sys.stderr.write(_json.dumps(d, indent=2, default=str) + "\n")
        else:
            print_json(d)
        return
    t = Table(title="ffcomp: compensation summary", title_justify="left", show_header=False)
    fmt = {
        "rms_before_um": ("predicted vibration RMS, uncompensated", "{:.1f} um"),
        "rms_after_um": ("predicted vibration RMS, compensated", "{:.2f} um"),
        "max_before_um": ("predicted vibration max, uncompensated", "{:.1f} um"),
        "max_after_um": ("predicted vibration max, compensated", "{:.1f} um"),
        "print_time_s": ("print time, source (planned)", "{:.2f} s"),
        "output_print_time_s": ("print time, output (re-planned)", "{:.2f} s"),
        "wall_time_s": ("processing time", "{:.2f} s"),
        "speed_ratio": ("speed (print time / processing time)", "{:.0f}x"),
        "self_check_max_um": ("self-check: max deviation of re-planned carriages", "{:.1f} um"),
        "self_check_rms_um": ("self-check: RMS deviation", "{:.2f} um"),
        "self_check_catch_up_max_um": ("self-check: max deviation in catch-ups after holds", "{:.1f} um"),
        "self_check_drift_ms": ("self-check: largest drift on the absolute clock", "{:+.3f} ms"),
        "self_check_abs_max_um": ("self-check: max deviation at the same absolute time", "{:.1f} um"),
        "header_accel_mm_s2": ("firmware ACCEL the output sets", "{:.0f} mm/s^2"),
        "lines_in": ("lines in", "{}"),
        "lines_out": ("lines out", "{}"),
        "segments": ("G1 segments written", "{}"),
        "steps": ("steps written", "{}"),
        "max_step_error_steps": ("max reconstruction error", "{:.3f} steps"),
    }
    for k, (label, f) in fmt.items():
        v = d.get(k)
        if v is not None:
            t.add_row(label, f.format(v))
    if d.get("rms_before_um") and d.get("rms_after_um") is not None:
        t.add_row("predicted reduction", f"{(1 - d['rms_after_um'] / d['rms_before_um']) * 100:.1f} %")
    err_console.print(t) if to_stderr else __import__("rich").get_console().print(t)
    for note in d.get("notes") or []:
        (err_console if to_stderr else __import__("rich").get_console()).print(f"note: {note}", markup=False)
