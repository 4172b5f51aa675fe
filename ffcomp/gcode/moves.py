"""The planner's output: :class:`PlannedMove`, a trapezoidal velocity profile along a straight line.

A planned move starts at ``start_mm`` at print time ``t_start_s``, accelerates at ``accel_mm_s2`` from
``start_v_mm_s`` to ``cruise_v_mm_s`` for ``accel_t_s``, cruises for ``cruise_t_s`` and decelerates to
``end_v_mm_s`` for ``decel_t_s``.  The distance travelled along the move, ``s(t)``, maps to the four
axes through ``position = start_mm + unit * s`` (``unit`` is ``d(x, y, z, e)/ds``): for an XYZ move
``s`` is the Cartesian path length and ``unit`` holds the direction cosines plus the extrusion ratio;
for an extruder-only move ``s`` is the filament length and ``unit = (0, 0, 0, +-1)`` (kind ``extrude``,
or ``firmware`` where the firmware makes it of a command line: Klipper's ``G10``/``G11``); a dwell has
``unit = 0`` and lasts ``cruise_t_s``.  Moves follow each other without gaps: ``t_start_s`` of one is
``t_end_s`` of the previous.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["PlannedMove", "MOVE", "EXTRUDE", "FIRMWARE", "DWELL"]

MOVE = "move"
EXTRUDE = "extrude"
#: an extruder-only move the firmware makes of a command (``G10``/``G11``): timed like ``extrude``, and
#: written as its own line (the firmware, not the file, sets its length and speed)
FIRMWARE = "firmware"
DWELL = "dwell"


class PlannedMove(NamedTuple):
    """One executed move (or dwell) with its exact timing (immutable; a named tuple, because the
    planners make one per move and a tuple is several times cheaper to build than a frozen
    dataclass).

    Attributes
    ----------
    index : int
        Position in the plan, 0-based.
    lineno : int
        Source line number (1-based) of the G-code line that produced it.
    kind : str
        ``"move"`` (XYZ, with or without extrusion), ``"extrude"`` (extruder only), ``"firmware"`` (extruder
        only, made by the firmware of a ``G10``/``G11`` line) or ``"dwell"``.
    t_start_s : float
        Print time at which the move starts, s.
    start_mm, end_mm : tuple of 4 float
        (x, y, z, e) at start and end, mm.
    distance_mm : float
        Length of the move along which the speeds are measured (XYZ length, or filament length).
    unit : tuple of 4 float
        ``d(x, y, z, e) / d(distance)``.
    start_v_mm_s, cruise_v_mm_s, end_v_mm_s : float
        Speeds along the move, mm/s.
    accel_mm_s2 : float
        Acceleration used for both ramps, mm/s^2.
    accel_t_s, cruise_t_s, decel_t_s : float
        Durations of the three phases, s.
    quiet : bool
        Planned with quiet ramps (ffcomp's own plan of a z move next to a hold, not the firmware's:
        :class:`ffcomp.gcode.klipper.KlipperPlanner`'s ``quiet_z_period_s``).
    """

    index: int
    lineno: int
    kind: str
    t_start_s: float
    start_mm: tuple
    end_mm: tuple
    distance_mm: float
    unit: tuple
    start_v_mm_s: float
    cruise_v_mm_s: float
    end_v_mm_s: float
    accel_mm_s2: float
    accel_t_s: float
    cruise_t_s: float
    decel_t_s: float
    quiet: bool = False

    @property
    def duration_s(self) -> float:
        return self.accel_t_s + self.cruise_t_s + self.decel_t_s

    @property
    def t_end_s(self) -> float:
        return self.t_start_s + self.accel_t_s + self.cruise_t_s + self.decel_t_s

    @property
    def accel_d_mm(self) -> float:
        """Distance covered while accelerating, mm."""
        return (self.start_v_mm_s + self.cruise_v_mm_s) * 0.5 * self.accel_t_s

    @property
    def decel_d_mm(self) -> float:
        return (self.end_v_mm_s + self.cruise_v_mm_s) * 0.5 * self.decel_t_s

    def distance_at(self, t_s: float) -> float:
        """Distance along the move at print time ``t_s`` (clamped to the move), mm."""
        tau = min(max(t_s - self.t_start_s, 0.0), self.duration_s)
        a = self.accel_mm_s2
        if tau < self.accel_t_s:
            return self.start_v_mm_s * tau + 0.5 * a * tau * tau
        s = self.accel_d_mm
        tau -= self.accel_t_s
        if tau < self.cruise_t_s:
            return s + self.cruise_v_mm_s * tau
        s += self.cruise_v_mm_s * self.cruise_t_s
        tau -= self.cruise_t_s
        return s + self.cruise_v_mm_s * tau - 0.5 * a * tau * tau

    def speed_at(self, t_s: float) -> float:
        """Speed along the move at print time ``t_s`` (clamped to the move), mm/s."""
        tau = min(max(t_s - self.t_start_s, 0.0), self.duration_s)
        if tau < self.accel_t_s:
            return self.start_v_mm_s + self.accel_mm_s2 * tau
        tau -= self.accel_t_s
        if tau < self.cruise_t_s:
            return self.cruise_v_mm_s
        tau -= self.cruise_t_s
        return self.cruise_v_mm_s - self.accel_mm_s2 * tau

    def position_at(self, t_s: float) -> tuple:
        """(x, y, z, e) at print time ``t_s``, mm."""
        s = self.distance_at(t_s)
        return tuple(p + u * s for p, u in zip(self.start_mm, self.unit, strict=True))
