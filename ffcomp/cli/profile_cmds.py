"""``ffcomp profile show|import``: printer profiles."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, List, Optional

import typer
from rich.markup import escape

from .common import ProfileOpt, app, console, err_console, load_profile_opt

profile_app = typer.Typer(help="Printer profiles: print the default, import firmware geometry.",
                          no_args_is_help=True)
app.add_typer(profile_app, name="profile")


@profile_app.command("dump")
def dump(profile: ProfileOpt = None,
         output: Annotated[Optional[Path], typer.Option("--output", "-o", help="Write here.")] = None) -> None:
    """Print (or write) a profile as TOML; without --profile the embedded default."""
    from ..profile import profile_to_toml, save_profile

    prof = load_profile_opt(profile)
    if output:
        from ..io_atomic import check_output_path

        check_output_path(output, "profile")
        save_profile(prof, output)
        console.print(f"wrote {output}")
    else:
        typer.echo(profile_to_toml(prof), nl=False)


@profile_app.command("import")
def import_cmd(
    klipper: Annotated[Optional[Path], typer.Option("--klipper", help="Klipper printer.cfg (delta).")] = None,
    m665: Annotated[Optional[str], typer.Option("--m665", help="A Marlin/RRF M665 line, quoted.")] = None,
    firmware: Annotated[str, typer.Option(help="With --m665: marlin or reprap.")] = "marlin",
    print_radius: Annotated[Optional[float], typer.Option(help="With --m665: print radius, mm.")] = None,
    output: Annotated[Path, typer.Option("--output", "-o", help="Profile TOML to write.")] = Path("printer.toml"),
    frame: Annotated[str, typer.Option(help="Tower-angle frame: firmware (A/B/C at 210/330/90, as G-code sees the "
                                       "printer) or paper (0/120/240, tower A on +x, as FRF files are written).")]
    = "firmware",
    profile: ProfileOpt = None,
) -> None:
    """Import geometry and limits from firmware configuration; dynamics come from --profile."""
    from ..profile import save_profile
    from ..profile_import import from_klipper_cfg, from_m665

    if (klipper is None) == (m665 is None):
        raise typer.BadParameter("give exactly one of --klipper or --m665")
    from ..profile_set import FRAMES, to_frame

    if frame not in FRAMES:
        raise typer.BadParameter(f"expected one of {', '.join(FRAMES)}, got {frame!r}", param_hint="--frame")
    from ..io_atomic import check_output_path

    if firmware not in ("marlin", "reprap"):
        raise typer.BadParameter(f"--firmware must be marlin or reprap, got {firmware!r}")
    check_output_path(output, "profile")
    base = load_profile_opt(profile)
    notes: list[str] = []
    prof = (from_klipper_cfg(klipper, base, notes=notes) if klipper
            else from_m665(m665, base, print_radius_mm=print_radius, firmware=firmware))
    prof = to_frame(prof, frame)
    save_profile(prof, output)
    g = prof.geometry

    def mm(v):
        return ", ".join(f"{x:g}" for x in dict.fromkeys(v)) if isinstance(v, tuple) else f"{v:g}"

    fr = prof.firmware_retraction
    retraction = (f", firmware retraction {fr.retract_length_mm:g} mm at {fr.retract_speed_mm_s:g} mm/s"
                  if fr is not None else "")
    sh = prof.input_shaper
    if sh is not None:  # what a compensated file switches back on at its end
        retraction += (f", input shaper {sh.shaper_type_x} {sh.shaper_freq_x_hz:g} Hz / {sh.shaper_type_y} "
                       f"{sh.shaper_freq_y_hz:g} Hz")
    console.print(f"wrote {output}: arms {mm(g.arm_length_mm)} mm, radius {mm(g.delta_radius_mm)} mm, towers at "
                  f"{mm(g.tower_angles_deg)} deg, print radius {g.print_radius_mm:.2f} mm, planner "
                  f"{prof.limits.planner}, arc chords {prof.limits.arc_resolution_mm:g} mm{retraction}",
                  highlight=False)
    for n in notes:
        err_console.print(f"[yellow]note:[/] {escape(n)}", highlight=False, soft_wrap=True)


@profile_app.command("set")
def set_cmd(
    args: Annotated[List[str], typer.Argument(help="[PROFILE.toml] KEY=VALUE ...: section.key=value "
                                              "(geometry.delta_radius_mm=155, geometry.tower_angles_deg=0,120,240), "
                                              "name=TEXT or effects.NAME.PARAM=VALUE.")],
    output: Annotated[Optional[Path], typer.Option("--output", "-o", help="Write here (default: in place).")] = None,
    profile: ProfileOpt = None,
) -> None:
    """Set profile values, validated like a loaded profile; writes the TOML atomically."""
    from ..errors import ProfileError
    from ..profile import save_profile
    from ..profile_set import set_values

    path = profile
    if args and "=" not in args[0]:
        path, args = Path(args[0]), args[1:]
    if not args:
        raise typer.BadParameter("nothing to set: give KEY=VALUE ...")
    target = output or path
    if target is None:
        raise typer.BadParameter("give the profile to edit (or -o to write the edited default somewhere)")
    prof = load_profile_opt(path)
    try:
        new = set_values(prof, args)
    except ProfileError as e:
        raise typer.BadParameter(str(e)) from None
    save_profile(new.with_(source=None), target)
    console.print(f"wrote {target}: " + ", ".join(args), highlight=False)
