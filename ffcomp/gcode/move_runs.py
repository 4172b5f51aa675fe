"""Runs of plain ``G1 X Y Z [E] F`` lines parsed as arrays (the compensated file's bulk).

A compensated file is millions of lines of one shape, ``G1 X.. Y.. Z.. E.. F..``.  Parsing them
one by one (a record per line, then a planner call per line) was most of the self-check's time.
:meth:`GcodeParser.runs <ffcomp.gcode.parser.GcodeParser.runs>` gathers consecutive lines that
match :data:`RUN_LINE` exactly and turns them into one :class:`MoveRun` with Klipper's ``cmd_G1``
arithmetic done on arrays (:func:`to_run`): the same numbers, bit for bit, as the line-by-line path
(``tests/test_klipper_chains.py``).  Where the parser's state makes the arithmetic anything but the
plain case (G91, G20, before the first motion, a feed below the slow-move guard), the lines go the
line-by-line way.
"""

from __future__ import annotations

import re

import numpy as np

__all__ = ["RUN_LINE", "RUN_MAX", "MoveRun", "to_run"]

#: a line a run takes: all of X, Y, Z and F, an optional E, plain decimals, nothing else
_NUM = r"(-?[0-9]+(?:\.[0-9]*)?)"  # ASCII digits only (``\d`` would take any script's digits)
RUN_LINE = re.compile(rf"G1 X{_NUM} Y{_NUM} Z{_NUM}(?: E{_NUM})? F([0-9]*\.?[0-9]+|[0-9]+\.)\r?\n?\Z")

#: lines per run at most (memory and latency stay bounded)
RUN_MAX = 4096


class MoveRun:
    """Consecutive ``G1`` lines as arrays.

    Attributes
    ----------
    lineno : (n,) int64
        Line numbers (1-based).
    raws : list of str
        The lines as read.
    start : tuple of 4 float
        (x, y, z, e) before the first line, mm.
    ends : (n, 4) float
        (x, y, z, e) after each line, mm.
    speeds : (n,) float
        Requested speed of each line, mm/s.
    """

    __slots__ = ("lineno", "raws", "start", "ends", "speeds")

    def __init__(self, lineno, raws, start, ends, speeds):
        self.lineno, self.raws, self.start, self.ends, self.speeds = lineno, raws, start, ends, speeds

    @property
    def op(self) -> "MoveRun":
        """The run itself (a run stands where a :class:`~ffcomp.gcode.records.GcodeLine` would)."""
        return self

    def __len__(self) -> int:
        return len(self.lineno)


def to_run(rows: list, start: list, base: list, e_relative: bool, extrude_factor: float, unit: float,
           speed_factor: float) -> MoveRun:
    """The :class:`MoveRun` of matched lines ``rows`` ((line number, raw line, match) each), in
    absolute coordinates from ``start`` (x, y, z, e) with G92 offsets ``base``; the same arithmetic
    as the parser's ``_apply_move`` (and the same rounding: products and sums in the same order,
    relative E summed line after line)."""
    n = len(rows)
    groups = [r[2].groups() for r in rows]
    has_e = np.fromiter((g[3] is not None for g in groups), bool, n)
    V = np.array([float(v) for g in groups for v in (g[0], g[1], g[2], g[4], g[3] or "0")]).reshape(n, 5)
    ends = np.empty((n, 4))
    for c in range(3):
        ends[:, c] = V[:, c] * unit + base[c] if unit != 1.0 else V[:, c] + base[c]
    ve = V[:, 4] * unit if unit != 1.0 else V[:, 4]
    v = ve * extrude_factor
    if e_relative:
        acc = np.empty(n + 1)
        acc[0] = start[3]
        acc[1:] = np.where(has_e, v, 0.0)
        ends[:, 3] = np.cumsum(acc)[1:]
    else:
        e_abs = v + base[3]
        last = np.maximum.accumulate(np.where(has_e, np.arange(n), -1))
        ends[:, 3] = np.where(last >= 0, e_abs[np.maximum(last, 0)], start[3])
    speeds = V[:, 3] * unit * speed_factor
    return MoveRun(np.fromiter((r[0] for r in rows), np.int64, n), [r[1] for r in rows], tuple(start), ends, speeds)
