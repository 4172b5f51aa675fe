"""One-pass statistics of a planned G-code file (what ``ffcomp plan`` prints), and an optional trace.

:func:`summarize_gcode` streams the file through the parser and the planner and returns a
:class:`PlanSummary`; with ``trace=True`` it also returns a :class:`PlanTrace` (XY path and the exact
piecewise-linear speed profile) for plotting.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable

import numpy as np

from .moves import DWELL, EXTRUDE, FIRMWARE, MOVE, PlannedMove
from .planner import GcodePlan

__all__ = ["PlanSummary", "PlanTrace", "summarize_gcode"]


@dataclass(frozen=True)
class PlanSummary:
    """Statistics of a planned file (mm, s).

    Attributes
    ----------
    path, planner : str
        Source and firmware planner used.
    lines, warnings, ignored_commands : int
        Input lines, warnings (malformed lines skipped in lenient mode, unknown commands), limit commands
        the firmware ignores.
    moves, extrude_only_moves, dwells : int
        Planned XYZ moves (arc chords counted singly), extruder-only moves, dwells.
    duration_s, dwell_time_s : float
        Total print time (moves + dwells) and the part of it spent dwelling.
    distance_mm, extruding_distance_mm, travel_distance_mm : float
        XYZ path length, split into moves that extrude and moves that do not.
    extruded_mm, retracted_mm : float
        Filament pushed (sum of positive E steps) and pulled back (sum of negative steps, positive).
    peak_speed_mm_s, peak_accel_mm_s2 : float
        Highest cruise speed and acceleration actually used by XYZ moves.
    bbox_min_mm, bbox_max_mm : tuple of 3 float
        Extent of the XYZ path.
    warning_messages : tuple of str
    command_counts : dict
        Non-motion commands per class (``pass``, ``state``, ``stop``, ``unknown``, ``skipped``; see
        :mod:`ffcomp.gcode.commands`).
    """

    path: str
    planner: str
    lines: int
    warnings: int
    ignored_commands: int
    moves: int
    extrude_only_moves: int
    dwells: int
    duration_s: float
    dwell_time_s: float
    distance_mm: float
    extruding_distance_mm: float
    travel_distance_mm: float
    extruded_mm: float
    retracted_mm: float
    peak_speed_mm_s: float
    peak_accel_mm_s2: float
    bbox_min_mm: tuple
    bbox_max_mm: tuple
    warning_messages: tuple = field(default=())
    command_counts: dict = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["bbox_min_mm"] = list(self.bbox_min_mm)
        d["bbox_max_mm"] = list(self.bbox_max_mm)
        d["warning_messages"] = list(self.warning_messages)
        return d


@dataclass(frozen=True)
class PlanTrace:
    """Data for a plot of the plan.

    Attributes
    ----------
    xy_mm : ndarray, shape (n, 2)
        XY end points of consecutive XYZ moves (``NaN`` rows separate runs).
    extruding : ndarray of bool, shape (n,)
        Whether the move ending at that point extrudes.
    t_s, speed_mm_s : ndarray, shape (m,)
        Breakpoints of the (piecewise-linear) speed profile along the path.
    """

    xy_mm: np.ndarray
    extruding: np.ndarray
    t_s: np.ndarray
    speed_mm_s: np.ndarray


class _Acc:
    __slots__ = ("moves", "extrude_only", "dwells", "dwell_t", "dist", "dist_ext", "extruded", "retracted",
                 "peak_v", "peak_a", "lo", "hi", "t_end", "trace", "xy", "ext", "tt", "vv", "last_xy")

    def __init__(self, trace: bool):
        self.moves = self.extrude_only = self.dwells = 0
        self.dwell_t = self.dist = self.dist_ext = self.extruded = self.retracted = 0.0
        self.peak_v = self.peak_a = 0.0
        self.lo = [math.inf] * 3
        self.hi = [-math.inf] * 3
        self.t_end = 0.0
        self.trace = trace
        self.xy: list = []
        self.ext: list = []
        self.tt: list = []
        self.vv: list = []
        self.last_xy = None

    def add(self, m: PlannedMove) -> None:
        self.t_end = m.t_start_s + m.accel_t_s + m.cruise_t_s + m.decel_t_s
        kind = m.kind
        de = m.end_mm[3] - m.start_mm[3]
        if de > 0:
            self.extruded += de
        elif de < 0:
            self.retracted -= de
        if kind == MOVE:
            self.moves += 1
            self.dist += m.distance_mm
            if de > 0:
                self.dist_ext += m.distance_mm
            if m.cruise_v_mm_s > self.peak_v:
                self.peak_v = m.cruise_v_mm_s
            if (m.accel_t_s > 0 or m.decel_t_s > 0) and m.accel_mm_s2 > self.peak_a:
                self.peak_a = m.accel_mm_s2
            for p in (m.start_mm, m.end_mm):
                for i in range(3):
                    if p[i] < self.lo[i]:
                        self.lo[i] = p[i]
                    if p[i] > self.hi[i]:
                        self.hi[i] = p[i]
            if self.trace:
                if self.last_xy != (m.start_mm[0], m.start_mm[1]):
                    self.xy.append((math.nan, math.nan))
                    self.ext.append(False)
                    self.xy.append((m.start_mm[0], m.start_mm[1]))
                    self.ext.append(False)
                self.xy.append((m.end_mm[0], m.end_mm[1]))
                self.ext.append(de > 0)
                self.last_xy = (m.end_mm[0], m.end_mm[1])
        elif kind == EXTRUDE or kind == FIRMWARE:
            self.extrude_only += 1
        elif kind == DWELL:
            self.dwells += 1
            self.dwell_t += m.cruise_t_s
        if self.trace:
            t0 = m.t_start_s
            v = m.cruise_v_mm_s if kind == MOVE else 0.0
            if kind == MOVE:
                self.tt += [t0, t0 + m.accel_t_s, t0 + m.accel_t_s + m.cruise_t_s, self.t_end]
                self.vv += [m.start_v_mm_s, v, v, m.end_v_mm_s]
            else:
                self.tt += [t0, self.t_end]
                self.vv += [0.0, 0.0]


def _accumulate(moves: Iterable[PlannedMove], *, trace: bool = False) -> _Acc:
    acc = _Acc(trace)
    for m in moves:
        acc.add(m)
    return acc


def summarize_gcode(source, profile, *, lenient: bool = False, firmware: str | None = None,
                    trace: bool = False, **plan_kw):
    """Parse and plan ``source`` and summarise the plan.

    Parameters
    ----------
    source : path or iterable of str
    profile : PrinterProfile
    lenient : bool
    firmware : str, optional
        Planner name (default: the profile's).
    trace : bool
        Also collect a :class:`PlanTrace` (memory grows with the file: use for plotting only).
    **plan_kw
        Passed to :class:`~ffcomp.gcode.planner.GcodePlan`.

    Returns
    -------
    PlanSummary, or (PlanSummary, PlanTrace) when ``trace`` is true.
    """
    plan = GcodePlan(source, profile, lenient=lenient, firmware=firmware, **plan_kw)
    acc = _accumulate(plan, trace=trace)
    finite = all(math.isfinite(v) for v in acc.lo)
    s = PlanSummary(
        path=plan.path,
        planner=plan.firmware,
        lines=plan.parser.lines_read,
        warnings=plan.parser.warnings,
        ignored_commands=plan.planner.ignored_commands,
        moves=acc.moves,
        extrude_only_moves=acc.extrude_only,
        dwells=acc.dwells,
        duration_s=max(acc.t_end, plan.planner.print_time),
        dwell_time_s=acc.dwell_t,
        distance_mm=acc.dist,
        extruding_distance_mm=acc.dist_ext,
        travel_distance_mm=acc.dist - acc.dist_ext,
        extruded_mm=acc.extruded,
        retracted_mm=acc.retracted,
        peak_speed_mm_s=acc.peak_v,
        peak_accel_mm_s2=acc.peak_a,
        bbox_min_mm=tuple(acc.lo) if finite else (0.0, 0.0, 0.0),
        bbox_max_mm=tuple(acc.hi) if finite else (0.0, 0.0, 0.0),
        warning_messages=tuple(plan.parser.warning_messages),
        command_counts=dict(plan.parser.counts),
    )
    if not trace:
        return s
    tr = PlanTrace(
        xy_mm=np.asarray(acc.xy, dtype=float).reshape(-1, 2),
        extruding=np.asarray(acc.ext, dtype=bool),
        t_s=np.asarray(acc.tt, dtype=float),
        speed_mm_s=np.asarray(acc.vv, dtype=float),
    )
    return s, tr
