"""``ffcomp hook FILE``: the slicer post-processing hook (edit the G-code file in place).

PrusaSlicer, SuperSlicer and OrcaSlicer run each post-processing script through a shell with the
G-code path appended as the last argument, and expect the file to be edited in place (in the GUI it
is a temporary copy; ``SLIC3R_PP_OUTPUT_NAME`` names the final file).  Set the slicer's
post-processing script to, for example::

    /usr/local/bin/ffcomp hook --profile /home/me/printer.toml

A failure leaves the file untouched and exits non-zero with the reason on stderr, which the slicer
shows.  Cura: copy ``ffcomp/data/FfcompPostProcessing.py`` (``ffcomp hook --cura-script`` prints its
path) into Cura's ``scripts`` folder and enable it under Extensions > Post Processing.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Optional

import typer

from .common import JobsOpt, ProfileOpt, app, err_console, load_profile_opt, resolve_jobs


@app.command("hook")
def hook_cmd(
    gcode: Annotated[Optional[Path], typer.Argument(help="G-code file the slicer passes (edited in place).")] = None,
    method: Annotated[str, typer.Option(help="Inverse variant: lpv or lti-centre.")] = "lpv",
    tol_um: Annotated[float, typer.Option("--tol-um", help="Point placement tolerance, um.")] = 5.0,
    z_mode: Annotated[str, typer.Option("--z-mode", help="keep or hold (see ffcomp compensate).")] = "keep",
    hold_margin_ms: Annotated[float, typer.Option("--hold-margin-ms", help="Rest (ms) added around retractions "
                                                  "(see ffcomp compensate). 0: none.")] = 0.0,
    quiet_z: Annotated[bool, typer.Option("--quiet-z/--no-quiet-z", help="Quiet z moves next to retractions "
                                          "(see ffcomp compensate; off by default).")] = False,
    cura_script: Annotated[bool, typer.Option("--cura-script", help="Print the path of the Cura "
                                              "post-processing script and exit.")] = False,
    jobs: JobsOpt = 1,
    profile: ProfileOpt = None,
) -> None:
    """Slicer post-processing hook: compensate the G-code file in place."""
    from importlib import resources

    if cura_script:
        typer.echo(str(resources.files("ffcomp").joinpath("data/FfcompPostProcessing.py")))
        return
    if gcode is None:
        raise typer.BadParameter("the slicer passes the G-code path as the last argument")
    from ..compensate.inverse import InverseConfig
    from ..pipeline.compensate_flow import CompensateOptions, compensate_file

    if not 0.0 <= hold_margin_ms <= 1000.0:
        raise typer.BadParameter(f"--hold-margin-ms must be between 0 and 1000, got {hold_margin_ms}")
    prof = load_profile_opt(profile)
    final = os.environ.get("SLIC3R_PP_OUTPUT_NAME")
    opts = CompensateOptions(method=method, tol_um=tol_um, z_mode=z_mode, inverse=InverseConfig(method=method),
                             jobs=resolve_jobs(jobs), hold_margin_s=hold_margin_ms * 1e-3, quiet_z=quiet_z)
    summ = compensate_file(str(gcode), str(gcode), prof, opts)
    name = f" (final file {final})" if final else ""
    reduction = ""
    if summ.rms_before_um:
        reduction = (f", predicted vibration {summ.rms_before_um:.1f} -> {summ.rms_after_um:.2f} um RMS")
    warn = f", {summ.warnings} warning(s)" if summ.warnings else ""
    err_console.print(f"ffcomp: compensated {gcode}{name} for {summ.firmware} in {summ.wall_time_s:.1f} s "
                      f"({summ.speed_ratio:.0f}x print time){reduction}{warn}", highlight=False, markup=False)
    for msg in summ.notes:
        err_console.print(f"ffcomp: warning: {msg}", highlight=False, markup=False, soft_wrap=True)
