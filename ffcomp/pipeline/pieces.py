"""Where ``--jobs`` cuts a file: :class:`Piece` and the state a worker keeps while it plans the file
from its start to find its piece's cuts (:mod:`ffcomp.pipeline.parallel_flow` runs the pieces)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..gcode.moves import MOVE

__all__ = ["Piece"]


@dataclass(frozen=True)
class Piece:
    """One part of a file compensated on its own (``--jobs``, :mod:`ffcomp.pipeline.parallel_flow`).

    The piece runs from the first *cut* at or after source line ``lo_line`` (None: the file's start)
    to the first cut at or after ``hi_line`` (None: the file's end).  A cut is a point where the
    planned toolhead stands still: a stop the planner reports (M600, M400, a heater wait, an unknown
    macro: ``planner.on_stop``), or the start of an extruder-only move or dwell that follows a move
    ending at rest (a retraction).  Every piece plans the file from its start, so the pieces find the
    same cuts independently; a compensation stream ends at each cut (``post_s`` of rest) and the next
    begins there (``pre_s`` of rest), as at a stop.
    """

    lo_line: int | None = None
    hi_line: int | None = None


#: a cut within this of a sample time counts as at it (the stream split rule at stops), s
_CUT_EPS_S = 1e-9


def _first_sample_at(t_s: float, fs_hz: float) -> int:
    """Index of the first sample at or after ``t_s`` (the stream split rule of :func:`compensated_stream`)."""
    k = max(int(math.ceil((t_s - _CUT_EPS_S) * fs_hz)), 0)
    while k > 0 and (k - 1) / fs_hz >= t_s - _CUT_EPS_S:
        k -= 1
    while k / fs_hz < t_s - _CUT_EPS_S:
        k += 1
    return k


class _CutFinder:
    """The first cut (see :class:`Piece`) at or after a source line, found as the plan goes by: feed
    it every planned move in order (``check``) and every stop the planner reports (``on_stop``)."""

    def __init__(self, line: int):
        self.line = line
        self.stop: tuple | None = None  # (t, line) of the first stop at or after the line
        self.stops: list[tuple] = []  # every stop reported, (t, line)
        self.v_end = 0.0  # speed at the end of the last XYZ move, mm/s

    def on_stop(self, t_s: float, lineno: int) -> None:
        self.stops.append((t_s, lineno))
        if self.stop is None and lineno >= self.line:
            self.stop = (t_s, lineno, "stop")

    def check(self, mv) -> tuple | None:
        """``(t, line, kind)`` of the cut if it is at the start of ``mv`` (the first move of the next
        piece); kind ``stop`` (a stream ends there anyway) or ``hold`` (a retraction or dwell after a
        move ending at rest: the cut adds a stream end and start there)."""
        if self.stop is not None and mv.t_start_s >= self.stop[0] - _CUT_EPS_S:
            return self.stop
        v = self.v_end
        if mv.kind == MOVE:
            self.v_end = mv.end_v_mm_s
            return None
        if mv.lineno >= self.line and v < 1e-9:
            return (mv.t_start_s, mv.lineno, "hold")
        return None


class _PieceState:
    """Where one piece begins and ends, found while its worker plans the file (see :class:`Piece`)."""

    def __init__(self, piece: Piece):
        self.piece = piece
        self.first = piece.lo_line is None
        self.lo: tuple | None = None  # (t, line) of the cut the piece starts at
        self.hi: tuple | None = None  # (t, line) of the cut it ends at
        self.k_lo = 0
        self.k_hi = 0
        self.empty = False
        self.n_xyz = 0
        self.fs = 1.0
        self._hi = _CutFinder(piece.hi_line) if piece.hi_line is not None else None
        self._skip_check = False  # the piece's first move was checked by the end finder already

    def begin(self, plan, planned, stops: list, fs_hz: float):
        """Skip the moves before the piece's first cut; returns the moves from it on (None: the piece
        is empty).  ``stops`` gets the (time, line) of the stops after the cut."""
        self.fs = float(fs_hz)
        hi = self._hi

        def stop_hook(finder):
            def f(t_s, lineno):
                finder.on_stop(t_s, lineno)
                if hi is not None and finder is not hi:
                    hi.on_stop(t_s, lineno)
            return f

        if self.first:
            if hi is not None:
                plan.planner.on_stop = lambda t_s, lineno: (stops.append((t_s, lineno)), hi.on_stop(t_s, lineno))
            return planned
        lo = _CutFinder(self.piece.lo_line)
        plan.planner.on_stop = stop_hook(lo)
        for mv in planned:
            c = lo.check(mv)
            c_hi = hi.check(mv) if hi is not None else None
            if c is None:
                continue
            self.lo, self.k_lo = c, _first_sample_at(c[0], self.fs)
            if c_hi is not None:  # no cut between the two lines: nothing here
                self.empty = True
                return None
            stops.extend((t, ln) for t, ln in lo.stops if t > c[0] + _CUT_EPS_S)
            if hi is not None:
                plan.planner.on_stop = lambda t_s, lineno: (stops.append((t_s, lineno)), hi.on_stop(t_s, lineno))
            else:
                plan.planner.on_stop = lambda t_s, lineno: stops.append((t_s, lineno))
            self._skip_check = True
            return _prepend(mv, planned)
        self.empty = True
        return None

    def ends_at(self, mv) -> bool:
        """Whether ``mv`` is the first move after the piece's last cut."""
        if self._hi is None:
            return False
        if self._skip_check:
            self._skip_check = False
            return False
        c = self._hi.check(mv)
        if c is not None:
            self.hi, self.k_hi = c, _first_sample_at(c[0], self.fs)
            return True
        return False

    def window(self, lines):
        """The piece's own source lines: from its first cut's line to before its last cut's line."""
        for ln in lines:
            if self.lo is None and not self.first:
                return  # an empty piece (the lines are pulled only after its first cut is known)
            if self.lo is not None and ln.lineno < self.lo[1]:
                continue
            if self.hi is not None and ln.lineno >= self.hi[1]:
                return
            yield ln

    def before_finish(self, writer) -> None:
        """The writer may hold the next piece's first line (read ahead before the cut was known)."""
        nl = writer.next_line
        if self.hi is not None and nl is not None and nl.lineno >= self.hi[1]:
            writer.next_line = None
            writer.lines = iter(())
        elif self.lo is None and not self.first:
            writer.next_line = None
            writer.lines = iter(())


def _prepend(first, rest):
    yield first
    yield from rest
