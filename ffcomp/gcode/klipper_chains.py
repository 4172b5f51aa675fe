"""Klipper's plan of a long G-code file, with its runs of straight moves planned vectorised.

:class:`~ffcomp.gcode.klipper.KlipperPlanner` plans move by move in Python, as Klipper does; a
compensated file holds millions of short segments and re-planning it (the self-check) was a quarter
of a run.  :class:`KlipperChainPlanner` gives the same plan faster where the lookahead allows a
closed form:

* A **chain** is a run of XYZ moves that starts and ends at rest: Klipper's junction between a move
  and an extruder-only move is zero, and a dwell, ``M400``, a stop or homing flushes the lookahead
  to rest.  With ``minimum_cruise_ratio = 0`` (the compensated file's header sets it) the plan of a
  chain is :func:`~ffcomp.gcode.chain_plan.trapezoids` (the writer's model, equal to the move-by-move
  planner to 1e-9 s: ``tests/test_chain_plan.py``), computed once for the whole chain.
* Everything else goes through the move-by-move planner unchanged: extruder-only moves, chains
  under a non-zero cruise ratio, and a chain within which the limits change
  (``SET_VELOCITY_LIMIT``, ``M204``: its moves so far are handed to the move-by-move planner and the
  chain continues there until the next rest).  A chain whose end points leave the workspace, or
  whose retraction is longer than ``max_extrude_only_distance``, is handed over the same way, so
  that the error is the move-by-move planner's own (line and message).
* A chain longer than :data:`MAX_CHAIN` moves is handed over too (memory stays bounded).

The planned chains come out as :class:`MoveBlock` objects (arrays, one row per move) among the
:class:`~ffcomp.gcode.moves.PlannedMove` items of the other moves, in execution order.
"""

from __future__ import annotations

import numpy as np

from ..errors import GcodeError
from .chain_plan import ChainLimits, extruder_limited, junction_v2, segment_limits, trapezoids
from .klipper import KlipperPlanner
from .move_runs import MoveRun
from .parser import MAX_MOVE_S
from .records import GcodeLine, LinearMove

__all__ = ["KlipperChainPlanner", "MoveBlock", "BLOCK", "MAX_CHAIN"]

#: the ``kind`` of a :class:`MoveBlock`
BLOCK = "block"

#: chains longer than this (moves) are planned move by move
MAX_CHAIN = 20_000


class MoveBlock:
    """A planned chain of XYZ moves, as arrays (one row per move, in execution order).

    Attributes
    ----------
    lineno : (n,) int64
    t_start : (n,) float, s
    start, unit : (n, 4) float
        (x, y, z, e) at each move's start, mm, and its direction per mm of XYZ travel.
    distance : (n,) float, mm
    accel : (n,) float, mm/s^2
    start_v, cruise_v, end_v : (n,) float, mm/s
    accel_t, cruise_t, decel_t : (n,) float, s
    """

    kind = BLOCK
    __slots__ = ("lineno", "t_start", "start", "unit", "distance", "accel", "start_v", "cruise_v", "end_v",
                 "accel_t", "cruise_t", "decel_t")

    def __init__(self, **kw):
        for k, v in kw.items():
            setattr(self, k, v)

    def __len__(self) -> int:
        return len(self.lineno)

    @property
    def t_start_s(self) -> float:
        return float(self.t_start[0])

    @property
    def t_end_s(self) -> float:
        return float(self.t_start[-1] + self.accel_t[-1] + self.cruise_t[-1] + self.decel_t[-1])


class KlipperChainPlanner(KlipperPlanner):
    """:class:`~ffcomp.gcode.klipper.KlipperPlanner` with chains planned vectorised (see the module).

    The same parameters and interface; :meth:`take` returns :class:`MoveBlock` items among the
    :class:`~ffcomp.gcode.moves.PlannedMove` ones.
    """

    def __init__(self, profile, **kw):
        if kw.get("quiet_z_period_s") is not None:  # (its runs are planned without KlipperPlanner.move)
            raise ValueError("quiet_z_period_s: not with the vectorised chain planner (a re-plan of written "
                             "G-code needs Klipper's own plan)")
        super().__init__(profile, **kw)
        self._lim = ChainLimits(profile, self.max_accel, self.square_corner_velocity)
        # the pending chain: arrays of runs ((k, 5) end x, y, z, e and speed; line numbers; raw
        # lines) and, after them, single moves (x, y, z, e, speed, line number, raw line)
        self._chunks: list = []
        self._rows: list = []
        self._n_pend = 0
        self._chain_start = None  # (x, y, z, e) where the pending chain starts
        self._general = False  # the current chain is planned move by move (until the next rest)
        self.chains = 0  # chains planned vectorised
        self.chain_moves = 0  # their moves

    # ------------------------------------------------------------------ moves
    def move(self, end, speed: float, line) -> None:
        sx, sy, sz, se = self.commanded_pos
        dx, dy, dz = end[0] - sx, end[1] - sy, end[2] - sz
        if dx * dx + dy * dy + dz * dz < 1e-18:  # extruder-only (KlipperPlanner: move_d < 1e-9)
            if end[3] == se:  # no move at all: Klipper ignores it (the lookahead goes on through it)
                return
            if self._n_pend:
                self._plan_pending()
            super().move(end, speed, line)
            self._general = False  # the next XYZ move starts from rest
            return
        if self._general:
            super().move(end, speed, line)
            return
        if not self._n_pend:
            if self.queue:  # an extruder-only move before: the chain starts from rest after it
                super()._process()
            if self.min_cruise_ratio != 0.0:
                self._general = True
                super().move(end, speed, line)
                return
            self._chain_start = tuple(self.commanded_pos)
        self._rows.append((end[0], end[1], end[2], end[3], speed, line.lineno, line.raw))
        self._n_pend += 1
        self.commanded_pos = [end[0], end[1], end[2], end[3]]
        if self._n_pend > MAX_CHAIN:
            self._hand_over()

    def move_run(self, run: MoveRun) -> None:
        """A run of parsed ``G1`` lines (:meth:`GcodeParser.runs <ffcomp.gcode.parser.GcodeParser.runs>`):
        its XYZ moves join the pending chain as arrays; the rest goes through :meth:`move`."""
        ends, speeds = run.ends, run.speeds
        n = len(ends)
        prev = np.empty((n, 3))
        prev[0] = self.commanded_pos[:3]
        prev[1:] = ends[:-1, :3]
        d = ends[:, :3] - prev
        still = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2] < 1e-18  # extruder-only or none
        stops = np.flatnonzero(still)
        i = 0
        while i < n:
            if self._general or not self._n_pend or still[i]:
                self._one(run, i)
                i += 1
                continue
            k = np.searchsorted(stops, i)
            j = int(stops[k]) if k < stops.size else n
            E = np.empty((j - i, 5))
            E[:, :4] = ends[i:j]
            E[:, 4] = speeds[i:j]
            if self._rows:
                self._rows_to_chunk()
            self._chunks.append((E, run.lineno[i:j], run.raws[i:j]))
            self._n_pend += j - i
            self.commanded_pos = [float(v) for v in ends[j - 1]]
            if self._n_pend > MAX_CHAIN:
                self._hand_over()
            i = j

    def _one(self, run: MoveRun, i: int) -> None:
        end = tuple(float(v) for v in run.ends[i])
        speed = float(run.speeds[i])
        op = LinearMove(tuple(self.commanded_pos), end, speed, False)
        self.move(end, speed, GcodeLine(int(run.lineno[i]), run.raws[i], "G1", op))

    def _rows_to_chunk(self) -> None:
        rows, self._rows = self._rows, []
        E = np.array([r[:5] for r in rows], float).reshape(-1, 5)
        self._chunks.append((E, np.fromiter((r[5] for r in rows), np.int64, len(rows)), [r[6] for r in rows]))

    def _take_pending(self) -> tuple:
        """The pending chain (emptied): end points and speeds (n, 5), line numbers, raw lines."""
        if self._rows:
            self._rows_to_chunk()
        chunks, self._chunks, self._n_pend = self._chunks, [], 0
        if len(chunks) == 1:
            return chunks[0]
        return (np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks]),
                [r for c in chunks for r in c[2]])

    def limits(self, op, line) -> None:
        if self._n_pend:  # the moves so far keep the old limits: planned move by move from here
            self._hand_over()
        super().limits(op, line)
        self._lim.accel = self.max_accel
        self._lim.jd = self.junction_deviation
        self._lim.max_velocity = self.max_velocity

    def _hand_over(self, pending: tuple | None = None) -> None:
        """Give the pending chain (or ``pending``, taken already) to the move-by-move planner; it plans
        the chain to its end."""
        E, lineno, raws = self._take_pending() if pending is None else pending
        self.commanded_pos = list(self._chain_start)
        self._general = True
        for r, ln, raw in zip(E.tolist(), lineno.tolist(), raws):
            super().move(tuple(r[:4]), r[4], GcodeLine(ln, raw, "G1", None))

    def _process(self, lazy: bool = False) -> None:
        if self._n_pend:
            self._plan_pending()
        super()._process(lazy)
        if not lazy:
            self._general = False

    # ------------------------------------------------------------------ the vectorised plan
    def _plan_pending(self) -> None:
        P, lineno, raws = self._take_pending()
        n = len(P)
        E = np.empty((n + 1, 5))
        E[0, :4] = self._chain_start
        E[1:] = P
        a, b = E[:-1, :3], E[1:, :3]
        de = E[1:, 3] - E[:-1, 3]
        d = b - a
        dist = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
        ext = extruder_limited(d, de)
        if self.kin.out_of_range(b) or (self.max_e_dist is not None and ext.any()
                                        and float(np.max(np.abs(de[ext]))) > self.max_e_dist):
            self._hand_over((P, lineno, raws))  # the move-by-move planner raises the error, naming the line
            return
        lim = self._lim
        vmax, acc = segment_limits(lim, a, b, de)
        speed = np.minimum(E[1:, 4], lim.max_velocity)
        cruise_v2 = np.minimum(speed, vmax) ** 2
        inv = 1.0 / dist
        unit = np.empty((n, 4))
        unit[:, :3] = d * inv[:, None]
        unit[:, 3] = de * inv
        jv = np.empty(n)
        jv[0] = 0.0
        jv[1:] = junction_v2(lim, unit[:, :3], unit[:, 3], acc, 2.0 * dist * acc)
        t1, t2, t3, vi, vc, vo = trapezoids(dist, cruise_v2, acc, jv, 0.0, 0.0)
        dur = t1 + t2 + t3
        if float(dur.max()) > MAX_MOVE_S:
            i = int(np.argmax(dur))
            raise GcodeError(self.path, int(lineno[i]), f"this move would last {dur[i]:.0f} s (over "
                             f"{dist[i]:.4g} mm at up to {vc[i]:.3g} mm/s, {acc[i]:.3g} mm/s^2), longer than the "
                             f"{MAX_MOVE_S:g} s allowed for one move")
        T = np.empty(n + 1)  # the print time, summed move by move as KlipperPlanner does
        T[0] = self.print_time
        T[1:] = dur
        T = np.cumsum(T)
        t_start, ends = T[:-1], T[1:]
        self.out.append(MoveBlock(
            lineno=lineno, t_start=t_start, start=E[:-1, :4].copy(),
            unit=unit, distance=dist, accel=acc, start_v=vi, cruise_v=vc, end_v=vo, accel_t=t1, cruise_t=t2,
            decel_t=t3))
        self.n_out += n
        self.chains += 1
        self.chain_moves += n
        self.need_prime = False
        if ends[-1] > self.print_time:
            self.print_time = float(ends[-1])
