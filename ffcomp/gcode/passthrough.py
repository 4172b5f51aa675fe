"""The source's lines that are not compensated motion, as the G-code writer passes them on.

Comments, temperatures, fans, homing and object labels pass through byte for byte; lines whose
meaning the compensation bakes in (coordinate and extrusion modes, G92, offsets, speed and flow
factors, motion limits) are commented out with ``; ffcomp (baked in):``; motion lines that
produced no planned motion and lines a lenient parse skipped are kept as comments.  Dwells are
written with their planned move, in time order, not here.
"""

from __future__ import annotations

from .records import ArcMove, FirmwareMove, GcodeLine, LimitsChange, LinearMove, ModeChange, Stop

__all__ = ["BAKED_MODES", "extruder_limit_lines", "passthrough_lines"]

#: ModeChange names whose effect is baked into the output (the line is commented out)
BAKED_MODES = {"absolute_coord", "absolute_extrude", "set_position", "gcode_offset", "speed_factor",
               "extrude_factor", "units_mm_per_unit", "plane", "feedrate_mm_s"}


def extruder_limit_lines(op: LimitsChange) -> list[str]:
    """The Marlin commands that keep the extruder limits of a limit command ``op`` in force (the
    plan was timed with them, and they protect the extruder): the retraction acceleration (M204 R),
    the E axis's acceleration (M201 E) and feed rate (M203 E)."""
    out = []
    if op.retract_accel_mm_s2 is not None:
        out.append(f"M204 R{op.retract_accel_mm_s2:g}")
    for cmd, axes in (("M201", op.max_accel_axes_mm_s2), ("M203", op.max_feedrate_axes_mm_s)):
        if axes is not None and len(axes) > 3 and axes[3] is not None:
            out.append(f"{cmd} E{axes[3]:g}")
    return out


def passthrough_lines(ln: GcodeLine, replaced: set[int], extruder_limits: bool, stats) -> list[str]:
    """What the output carries for source line ``ln`` (not a compensated motion's segments).

    ``replaced``: the source line numbers written as motion; ``extruder_limits``: keep the extruder
    limits of the source's limit commands in force (:func:`extruder_limit_lines`); ``stats``: the
    writer's :class:`~ffcomp.gcode.writer_stats.WriterStats` (lines passed, commented, skipped).
    """
    op = ln.op
    raw = ln.raw if ln.raw.endswith("\n") else ln.raw + "\n"
    if isinstance(op, (LinearMove, ArcMove, FirmwareMove)):
        if ln.lineno not in replaced:  # produced no planned motion (zero length)
            return ["; ffcomp (no motion): " + raw]
        return []
    if ln.error is not None:  # a lenient parse skipped it: it must not run
        stats.lines_skipped += 1
        return ["; ffcomp (skipped): " + raw]
    if isinstance(op, LimitsChange) or (isinstance(op, ModeChange) and op.name in BAKED_MODES) or (
            isinstance(op, Stop) and op.baked):
        stats.lines_commented += 1
        out = ["; ffcomp (baked in): " + raw]
        if isinstance(op, LimitsChange) and extruder_limits:
            out += [cmd + " ; ffcomp: the source's extruder limit (the plan was timed with it)\n"
                    for cmd in extruder_limit_lines(op)]
        return out
    if op is not None and type(op).__name__ == "Dwell":
        return []  # written with its planned move, in time order
    stats.lines_passed += 1
    return [raw]
