"""Where the toolhead is when a file starts: the plan's start position, and the travel that gets there.

A file that homes (G28) before its first move starts at home, whatever came before.  Most Klipper
users home inside a ``PRINT_START`` macro, though, so their sliced files move before any G28 and the
toolhead then stands wherever the macro left it.  The plan needs a known start, so:

* ``--start X,Y,Z`` (``start_mm``) or the profile's ``start_position_mm`` says where the toolhead is;
* otherwise the plan starts at the target of the file's first move: the first line is a travel from
  an unknown place, and the compensation can only begin once the toolhead is somewhere known;

and either way the output's first motion is an ordinary travel to that start at the speed the file
asks for its first move (at least :data:`MIN_START_TRAVEL_MM_S`), never a crawl at the speed of a
micrometre-sized compensated segment.  A file that moves before homing gets a warning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import GcodeError
from .parser import parse_gcode
from .records import ArcMove

__all__ = ["MIN_START_TRAVEL_MM_S", "StartInfo", "resolve_start", "parse_start"]

#: slowest travel to the start, mm/s (F600): fast enough never to crawl, slow enough for any printer
MIN_START_TRAVEL_MM_S = 10.0


@dataclass(frozen=True)
class StartInfo:
    """The start of a file's plan.

    position_mm : (x, y, z, e) the plan starts at
    homed_first : the file homes before its first move (the start position does not matter)
    origin : ``"home"``, ``"--start"``, ``"profile"``, ``"first move"`` or ``"default"`` (the origin, when
        the first move is an arc: its centre is given relative to where it starts)
    first_motion_line : line of the file's first move (None: no move)
    travel_mm_s : speed of the output's travel to the start (None when the file homes first)
    """

    position_mm: tuple
    homed_first: bool
    origin: str
    first_motion_line: int | None
    travel_mm_s: float | None

    def warning(self, path: str) -> str | None:
        """The warning for a file that moves before homing (None if it homes first)."""
        if self.homed_first or self.first_motion_line is None:
            return None
        x, y, z = self.position_mm[:3]
        how = {"--start": "as --start says",
               "profile": "as the profile's start_position_mm says (--start X,Y,Z overrides it)",
               "default": "as its first move is an arc from there (use --start X,Y,Z if the toolhead stands "
                          "elsewhere)"}.get(
            self.origin, "the target of its first move (use --start X,Y,Z or the profile's start_position_mm "
            "if the toolhead stands elsewhere)")
        return (f"{path}:{self.first_motion_line}: the file moves before any G28: the plan assumes the toolhead "
                f"starts at ({x:g}, {y:g}, {z:g}) mm, {how}; the output first travels there at "
                f"{self.travel_mm_s * 60:.0f} mm/min")


def parse_start(text: str) -> tuple[float, float, float]:
    """``"X,Y,Z"`` (mm) -> a tuple; raises ValueError naming the problem."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise ValueError(f"--start needs X,Y,Z in mm (three numbers), got {text!r}")
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        raise ValueError(f"--start needs X,Y,Z in mm (three numbers), got {text!r}") from None
    if not all(v == v and abs(v) != float("inf") for v in vals):
        raise ValueError(f"--start values must be finite, got {text!r}")
    return vals


def resolve_start(src: str, profile, start_mm=None, *, dialect: str | None = None) -> StartInfo:
    """Read ``src`` up to its first move or G28 and decide the plan's start (see the module docstring).

    Parameters
    ----------
    src : path of the G-code file
    profile : PrinterProfile
    start_mm : (x, y, z), optional
        Where the toolhead stands before the file (``--start``); default: the profile's
        ``start_position_mm``, if it has one.
    dialect : str, optional
        G-code dialect (default: the profile's planner).
    """
    home = (0.0, 0.0, profile.geometry.z_max_mm)
    origin = "--start"
    if start_mm is None and getattr(profile, "start_position_mm", None) is not None:
        start_mm, origin = profile.start_position_mm, "profile"
    base = tuple(float(v) for v in start_mm) if start_mm is not None else (0.0, 0.0, 0.0)
    p = parse_gcode(src, lenient=True, dialect=dialect or profile.limits.planner, home_position_mm=home,
                    arc_resolution_mm=profile.limits.arc_resolution_mm,
                    start_position_mm=(*base, 0.0), unknown_policy="pass")
    for _ in p:
        if p.first_home_line is not None or p.first_motion_line is not None:
            break
    homed = p.first_home_line is not None and (p.first_motion_line is None
                                               or p.first_home_line < p.first_motion_line)
    if homed:
        return StartInfo((*home, 0.0), True, "home", p.first_motion_line, None)
    if p.first_motion is None:
        return StartInfo((*base, 0.0), False, origin, None, None)
    mv = p.first_motion
    arc = isinstance(mv, ArcMove)
    speed = mv.segments[0].speed_mm_s if arc else mv.speed_mm_s
    travel = min(max(speed, MIN_START_TRAVEL_MM_S), profile.limits.max_velocity_mm_s)
    if start_mm is not None or arc:  # an arc's centre is relative to its start: keep the start as it is
        return StartInfo((*base, 0.0), False, origin if start_mm is not None else "default",
                         p.first_motion_line, travel)
    g = profile.geometry
    x, y, z = mv.end[0], mv.end[1], mv.end[2]
    if math.hypot(x, y) > g.print_radius_mm + 1e-9 or not g.z_min_mm <= z <= g.z_max_mm:
        raise GcodeError(src, p.first_motion_line, f"Move out of range: the first move's target ({x:g}, {y:g}, "
                         f"{z:g}) mm is outside the print volume (radius {g.print_radius_mm:g} mm, z "
                         f"{g.z_min_mm:g}..{g.z_max_mm:g} mm)")
    return StartInfo((x, y, z, 0.0), False, "first move", p.first_motion_line, travel)
