"""Records the G-code parser yields: one :class:`GcodeLine` per input line, with the parsed meaning.

Every input line becomes exactly one :class:`GcodeLine` (line number, raw text with its line ending,
command word) so a writer can re-emit each line in place.  Lines that move the machine or change the
planner's state also carry an ``op``; every other line (temperatures, fans, comments, slicer labels,
unknown commands) has ``op=None`` and passes through untouched.

Units: positions mm (machine coordinates: G92 / G-code offsets already applied, E after the M221 flow
factor), speeds mm/s (F converted from mm/min once, M220 speed factor applied), accelerations mm/s^2,
times s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Union

Pos4 = tuple  # (x, y, z, e) in mm

__all__ = [
    "Pos4",
    "LinearMove",
    "FirmwareMove",
    "ArcMove",
    "Dwell",
    "Home",
    "Sync",
    "LimitsChange",
    "ModeChange",
    "Stop",
    "Op",
    "GcodeLine",
]


class LinearMove(NamedTuple):
    """A straight move (G0/G1, or one segment of a split arc); a named tuple, as one is made per
    line.

    Attributes
    ----------
    start, end : tuple of 4 float
        Machine position (x, y, z, e) before and after the move, mm.
    speed_mm_s : float
        Requested feed rate (F with the M220 factor applied), mm/s.
    rapid : bool
        True for G0 (planned exactly like G1 by Klipper and Marlin).
    """

    start: Pos4
    end: Pos4
    speed_mm_s: float
    rapid: bool = False


class FirmwareMove(NamedTuple):
    """The extruder-only move the firmware makes of a ``G10``/``G11`` (Klipper's ``firmware_retraction``):
    planned like a :class:`LinearMove`, written as its own line.

    Attributes
    ----------
    start, end : tuple of 4 float
        Machine position (x, y, z, e) before and after, mm (only e changes).
    speed_mm_s : float
        The retraction's feed rate with the M220 factor applied, mm/s.
    speed_percent, extrude_percent : float
        The M220 and M221 factors in force (percent): the output bakes them into its own moves, so it
        sets them again around this line for the firmware to apply them as it would to the source.
    """

    start: Pos4
    end: Pos4
    speed_mm_s: float
    speed_percent: float = 100.0
    extrude_percent: float = 100.0


@dataclass(frozen=True, slots=True)
class ArcMove:
    """A G2/G3 arc split into straight segments (Klipper's ``gcode_arcs`` rule).

    Attributes
    ----------
    segments : tuple of LinearMove
        The chords, in order; the last one ends exactly at the programmed target.
    clockwise : bool
    center : tuple of 2 float
        Arc centre in the plane's two axes (machine coordinates), mm.
    radius_mm : float
    angle_rad : float
        Signed angular travel (negative: clockwise).
    plane : str
        ``"XY"``, ``"XZ"`` or ``"YZ"``.
    """

    segments: tuple
    clockwise: bool
    center: tuple
    radius_mm: float
    angle_rad: float
    plane: str = "XY"


@dataclass(frozen=True, slots=True)
class Dwell:
    """G4: time with no motion.  ``seconds`` follows the dialect (Klipper: P ms only; Marlin: S or P)."""

    seconds: float


@dataclass(frozen=True, slots=True)
class Home:
    """G28: the machine homes and ends at ``position`` (x, y, z, e), mm.  Homing time is not modelled."""

    position: Pos4


@dataclass(frozen=True, slots=True)
class Sync:
    """Wait for all queued moves (M400, M18/M84): the planner flushes its lookahead queue.

    ``reason`` is the command word; the firmware variant decides any extra time it costs.
    """

    reason: str


@dataclass(frozen=True, slots=True)
class LimitsChange:
    """A motion-limit command (SET_VELOCITY_LIMIT, M204, M201, M203, M205) with the values it names.

    Fields the command did not give are None.  The firmware variant decides which ones it honours
    (Klipper ignores M201/M203/M205; Marlin ignores SET_VELOCITY_LIMIT).

    Attributes
    ----------
    command : str
    velocity_mm_s, accel_mm_s2, accel_to_decel_mm_s2, square_corner_velocity_mm_s, minimum_cruise_ratio
        SET_VELOCITY_LIMIT VELOCITY / ACCEL / ACCEL_TO_DECEL / SQUARE_CORNER_VELOCITY / MINIMUM_CRUISE_RATIO;
        ``accel_mm_s2`` is also M204 S.
    print_accel_mm_s2, travel_accel_mm_s2, retract_accel_mm_s2
        M204 P / T / R.
    junction_deviation_mm
        M205 J.
    jerk_mm_s : tuple of 4 (float or None) or None
        M205 X / Y / Z / E (recorded; only classic-jerk Marlin builds use them).
    min_feedrate_mm_s, min_travel_feedrate_mm_s, min_segment_time_s
        M205 S / T / B.
    max_accel_axes_mm_s2 : tuple of 4 (float or None) or None
        M201 X / Y / Z / E.
    max_feedrate_axes_mm_s : tuple of 4 (float or None) or None
        M203 X / Y / Z / E (converted from mm/s as Marlin reads them: M203 is in units/s).
    """

    command: str
    velocity_mm_s: float | None = None
    accel_mm_s2: float | None = None
    accel_to_decel_mm_s2: float | None = None
    square_corner_velocity_mm_s: float | None = None
    minimum_cruise_ratio: float | None = None
    print_accel_mm_s2: float | None = None
    travel_accel_mm_s2: float | None = None
    retract_accel_mm_s2: float | None = None
    junction_deviation_mm: float | None = None
    jerk_mm_s: tuple | None = None
    min_feedrate_mm_s: float | None = None
    min_travel_feedrate_mm_s: float | None = None
    min_segment_time_s: float | None = None
    max_accel_axes_mm_s2: tuple | None = None
    max_feedrate_axes_mm_s: tuple | None = None


@dataclass(frozen=True, slots=True)
class ModeChange:
    """A modal state change the parser applied itself (the planner needs nothing from it).

    ``name`` is one of ``absolute_coord`` (G90/G91), ``absolute_extrude`` (M82/M83), ``units_mm_per_unit``
    (G20/G21), ``plane`` (G17/G18/G19), ``set_position`` (G92: the new G-code position, axes not named
    are None), ``gcode_offset`` (SET_GCODE_OFFSET), ``speed_factor`` (M220, percent), ``extrude_factor``
    (M221, percent), ``feedrate_mm_s`` (a G0/G1 with only F).
    """

    name: str
    value: object


@dataclass(frozen=True, slots=True)
class Stop:
    """A command after which the machine has stopped, moved or changed on its own (M600, PAUSE, T1,
    G29, G10, an unknown macro...; see :mod:`ffcomp.gcode.commands`).  The planner brings the toolhead to
    rest before it; the line itself passes through, unless ``baked``: a command whose effect the
    compensated output must not have (``SET_INPUT_SHAPER``: the output runs with shaping off, see
    :data:`ffcomp.gcode.commands.BAKED_STOPS`) is kept as a comment.  ``unknown`` is True for a command the
    table does not know (treated as a stop by the unknown-command policy)."""

    command: str
    unknown: bool = False
    baked: bool = False


Op = Union[LinearMove, FirmwareMove, ArcMove, Dwell, Home, Sync, LimitsChange, ModeChange, Stop]


class GcodeLine(NamedTuple):
    """One input line (a named tuple: cheap to make, one per line).

    Attributes
    ----------
    lineno : int
        1-based line number in the input.
    raw : str
        The line exactly as read, line terminator included (``"".join(raw)`` restores the file).
    command : str
        Upper-case command word (``"G1"``, ``"M104"``, ``"SET_VELOCITY_LIMIT"``); ``""`` for blank and
        comment-only lines.
    op : Op or None
        The parsed meaning for motion/state lines; None for pass-through lines.
    error : str or None
        Set only in lenient mode: why this line could not be executed (it is then passed through).
    """

    lineno: int
    raw: str
    command: str
    op: Op | None = None
    error: str | None = None

    @property
    def text(self) -> str:
        """The line without its line terminator."""
        return self.raw.rstrip("\r\n")
