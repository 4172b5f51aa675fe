"""``ffcomp firmware-config OUT.gcode``: the Klipper printer.cfg values a compensated file is timed for."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import ProfileOpt, app, load_profile_opt


@app.command("firmware-config")
def firmware_config(
    gcode: Annotated[Path, typer.Argument(help="A G-code file compensated by ffcomp.")],
    profile: ProfileOpt = None,
) -> None:
    """Print the printer.cfg snippet (max_accel, max_z_accel, ...) the compensated file is timed for."""
    from ..pipeline.header import klipper_snippet, read_firmware_needs

    if not gcode.is_file():
        raise typer.BadParameter(f"{gcode}: no such file")
    try:
        needs = read_firmware_needs(str(gcode))
    except ValueError as e:
        typer.echo(str(e), err=True)
        raise typer.Exit(2) from None
    if needs is None:
        typer.echo(f"{gcode}: no ffcomp firmware line in its header (not compensated by this ffcomp, or "
                   "compensated for Marlin)", err=True)
        raise typer.Exit(2)
    typer.echo(klipper_snippet(needs, load_profile_opt(profile) if profile else None), nl=False)
