"""Motion planning: G-code records in, :class:`~ffcomp.gcode.moves.PlannedMove` out, firmware-exact.

The firmware variants live in :data:`PLANNERS` (name -> planner class); the profile's
``limits.planner`` picks one (``firmware=`` overrides it).  Every variant has the same interface:

``move(end, speed_mm_s, line)``, ``dwell(seconds, lineno)``, ``sync(reason, lineno)``,
``stop(command, lineno)``, ``home(position, lineno)``, ``limits(op, line)``, ``finish()`` and ``take()``
(the moves finalized so far, in order).

A stop (:class:`~ffcomp.gcode.records.Stop`: M600, PAUSE, T1, G29, G10, an unknown macro...) flushes the
lookahead like M400, so the toolhead is at rest when the firmware runs the command; the planner counts
it (``stops``) and reports its print time to ``on_stop(t_s, lineno)`` if that is set.  ``sync`` (M400,
M18/M84) reports its rest to ``on_stop`` too: the firmware waits there for the queue to drain.

Planning streams: the lookahead queue holds only the moves that can still change (Klipper: about
0.25-2 s of motion; Marlin: the block buffer), so memory does not grow with the file.

>>> from ffcomp.profile import default_profile
>>> moves = list(plan_gcode(["G1 X10 F6000\\n"], default_profile()))
>>> round(moves[0].t_end_s, 6)
0.11
"""

from __future__ import annotations

import os
from typing import Iterable, Iterator

from ..errors import GcodeError
from .klipper import KlipperPlanner
from .klipper_chains import BLOCK, KlipperChainPlanner
from .marlin import MarlinPlanner
from .move_runs import MoveRun
from .moves import DWELL, PlannedMove
from .parser import MAX_MOVE_S, GcodeParser, parse_gcode
from .records import ArcMove, Dwell, FirmwareMove, GcodeLine, Home, LimitsChange, LinearMove, ModeChange, Stop, Sync

__all__ = ["PLANNERS", "plan_moves", "plan_gcode", "GcodePlan", "make_planner"]

PLANNERS: dict[str, type] = {
    "klipper": KlipperPlanner,
    "marlin": MarlinPlanner,
}


def _linear(p, op: LinearMove, line: GcodeLine) -> None:
    p.move(op.end, op.speed_mm_s, line)


def _arc(p, op: ArcMove, line: GcodeLine) -> None:
    for seg in op.segments:
        p.move(seg.end, seg.speed_mm_s, line)


def _dwell(p, op: Dwell, line: GcodeLine) -> None:
    p.dwell(op.seconds, line.lineno)


def _home(p, op: Home, line: GcodeLine) -> None:
    p.home(op.position, line.lineno)


def _sync(p, op: Sync, line: GcodeLine) -> None:
    p.sync(op.reason, line.lineno)


def _stop(p, op: Stop, line: GcodeLine) -> None:
    p.stop(op.command, line.lineno)


def _limits(p, op: LimitsChange, line: GcodeLine) -> None:
    p.limits(op, line)


def _nothing(p, op, line) -> None:
    return None


def _move_run(p, run: MoveRun, _line) -> None:
    p.move_run(run)


_OPS = {
    LinearMove: _linear,
    FirmwareMove: _linear,
    ArcMove: _arc,
    Dwell: _dwell,
    Home: _home,
    Sync: _sync,
    Stop: _stop,
    LimitsChange: _limits,
    ModeChange: _nothing,
    MoveRun: _move_run,
}


def make_planner(profile, *, firmware: str | None = None, **kw):
    """Instantiate the planner variant for ``firmware`` (default: the profile's ``limits.planner``)."""
    name = firmware or profile.limits.planner
    try:
        cls = PLANNERS[name]
    except KeyError:
        raise ValueError(f"unknown planner {name!r} (known: {', '.join(PLANNERS)})") from None
    return cls(profile, **kw)


def plan_moves(records: Iterable[GcodeLine], profile, *, firmware: str | None = None,
               path: str = "<gcode>", **kw) -> Iterator[PlannedMove]:
    """Plan parsed records; yields moves (and dwells) in execution order as they become final.

    Parameters
    ----------
    records : iterable of GcodeLine
        Usually a :class:`~ffcomp.gcode.parser.GcodeParser` with the same dialect.
    profile : PrinterProfile
    firmware : str, optional
        Key of :data:`PLANNERS`; default ``profile.limits.planner``.
    path : str
        File name for error messages.
    **kw
        Passed to the planner class (e.g. ``max_extrude_only_distance_mm``, ``block_buffer_size``).
    """
    return _run(make_planner(profile, firmware=firmware, path=path, **kw), records)


def _run(p, records: Iterable[GcodeLine]) -> Iterator[PlannedMove]:
    """Feed parsed lines to planner ``p``; yield its moves as they become final.

    A planned move lasting longer than :data:`~ffcomp.gcode.parser.MAX_MOVE_S` (e.g. under an absurd
    ``SET_VELOCITY_LIMIT ACCEL=0.001``) is a :class:`GcodeError` naming its line.
    """
    ops = _OPS
    move = p.move
    for line in records:
        op = line.op
        if op is None:
            continue
        if type(op) is LinearMove:  # most lines: _linear without the lookup and the call
            move(op.end, op.speed_mm_s, line)
        else:
            ops[type(op)](p, op, line)
        if p.out:
            yield from _checked(p, p.take())
    p.finish()
    yield from _checked(p, p.take())


def _checked(p, moves: list[PlannedMove]) -> list[PlannedMove]:
    if not moves or moves[-1].t_end_s - moves[0].t_start_s <= MAX_MOVE_S:  # moves follow without gaps
        return moves
    for m in moves:
        if m.kind != DWELL and m.kind != BLOCK and m.accel_t_s + m.cruise_t_s + m.decel_t_s > MAX_MOVE_S:
            raise GcodeError(getattr(p, "path", "<gcode>"), m.lineno,
                             f"this move would last {m.duration_s:.0f} s (over {m.distance_mm:.4g} mm at up to "
                             f"{m.cruise_v_mm_s:.3g} mm/s, {m.accel_mm_s2:.3g} mm/s^2), longer than the "
                             f"{MAX_MOVE_S:g} s allowed for one move")
    return moves


class GcodePlan:
    """Parse and plan a G-code source in one stream; iterate it for :class:`PlannedMove` objects.

    After iteration, :attr:`parser` holds the line and warning counts and :attr:`planner` the firmware
    state (``print_time``, ``ignored_commands``).

    Parameters
    ----------
    source : path or iterable of str
    profile : PrinterProfile
    lenient : bool
        Malformed lines become counted warnings instead of errors.
    firmware : str, optional
        Planner (and G-code dialect) name; default ``profile.limits.planner``.
    arc_resolution_mm : float, optional
        Klipper ``[gcode_arcs] resolution``; default the profile's ``limits.arc_resolution_mm``.
    start_position_mm : (x, y, z, e), optional
        Position before the first line (the machine is assumed homed there).  Default: for a file,
        where :func:`ffcomp.gcode.start.resolve_start` puts it (home if the file homes first, else the
        profile's ``start_position_mm`` or the target of the first move), so that ``plan``,
        ``simulate`` and ``compensate`` start a file at the same place; (0, 0, 0) for other sources.
    path : str, optional
        Name for error messages when ``source`` is not a file name.
    unknown_policy : str
        What an unknown macro or G code is (``stop``, ``pass`` or ``refuse``; see
        :mod:`ffcomp.gcode.commands`).
    chains : bool
        Plan runs of straight moves between rests vectorised
        (:class:`~ffcomp.gcode.klipper_chains.KlipperChainPlanner`, Klipper only): iteration then
        yields :class:`~ffcomp.gcode.klipper_chains.MoveBlock` items among the moves.  Default False.
    **planner_kw
        Passed to the planner class.
    """

    def __init__(self, source, profile, *, lenient: bool = False, firmware: str | None = None,
                 arc_resolution_mm: float | None = None, start_position_mm=None,
                 path: str | None = None, unknown_policy: str = "stop", chains: bool = False, **planner_kw):
        self.profile = profile
        self.firmware = firmware or profile.limits.planner
        if self.firmware not in PLANNERS:
            raise ValueError(f"unknown planner {self.firmware!r} (known: {', '.join(PLANNERS)})")
        if start_position_mm is None:
            if isinstance(source, (str, os.PathLike)):
                from .start import resolve_start

                start_position_mm = resolve_start(str(source), profile, dialect=self.firmware).position_mm
            else:
                start_position_mm = (0.0, 0.0, 0.0, 0.0)
        pkw = {} if path is None else {"path": path}
        if arc_resolution_mm is None:
            arc_resolution_mm = profile.limits.arc_resolution_mm
        self.parser: GcodeParser = parse_gcode(
            source, **pkw, lenient=lenient, dialect=self.firmware, arc_resolution_mm=arc_resolution_mm,
            home_position_mm=(0.0, 0.0, profile.geometry.z_max_mm), start_position_mm=start_position_mm,
            unknown_policy=unknown_policy, firmware_retraction=profile.firmware_retraction)
        if chains and self.firmware == "klipper":
            self.planner = KlipperChainPlanner(profile, path=self.parser.path, start_position_mm=start_position_mm,
                                               **planner_kw)
        else:
            self.planner = make_planner(profile, firmware=self.firmware, path=self.parser.path,
                                        start_position_mm=start_position_mm, **planner_kw)
        self._used = False

    @property
    def path(self) -> str:
        return self.parser.path

    def __iter__(self) -> Iterator[PlannedMove]:
        if self._used:
            raise RuntimeError("a GcodePlan can be iterated only once (it streams its source)")
        self._used = True
        if isinstance(self.planner, KlipperChainPlanner):  # runs of G1 lines parsed as arrays
            yield from _run(self.planner, self.parser.runs())
        else:
            yield from _run(self.planner, self.parser)


def plan_gcode(source, profile, **kw) -> GcodePlan:
    """Parse + plan ``source`` (a path or lines); see :class:`GcodePlan` for the keywords."""
    return GcodePlan(source, profile, **kw)
