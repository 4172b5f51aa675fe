"""A model of Marlin's planner (``Marlin/src/module/planner.cpp``, 2.1.x with junction deviation).

Modelled
    * Blocks in a ring buffer of ``block_buffer_size`` (16): the planner only sees the queued blocks.  The
      model assumes the buffer is kept full (printing from SD or a fast host): when a block arrives and
      the buffer is full, the oldest block is executed with the exit speed planned at that moment, and
      the next block's entry speed is frozen (Marlin never changes the first non-busy block).
    * Per block: nominal speed = F (with M220) limited by the per-axis maximum feed rates (M203) and
      the minimum feed rates (M205 S/T); acceleration = print (M204 P) or travel (M204 T) acceleration for
      moves with XYZ travel, limited by the per-axis maxima (M201) along the move; retract acceleration
      (M204 R) for extruder-only moves.
    * Junction deviation (M205 J) with the axis-limited junction acceleration and
      ``JD_HANDLE_SMALL_SEGMENTS`` (:func:`ffcomp.gcode.junction.marlin_corner_v2`); the junction vector
      includes E when the block extrudes.
    * ``minimum_planner_speed_sqr = 0.5 a / steps_per_mm`` (capped by the nominal speed) as the lowest
      entry speed; the newest block plans to stop.
    * The reverse pass (``entry^2 = min(max_entry^2, next_entry^2 + 2 a L)``) and the forward pass
      (``next_entry^2 <= entry^2 + 2 a L``, which also freezes that junction), then the trapezoid of
      each block in continuous time.
    * Software endstops: a target outside the printable radius or the Z range is clamped (radially in XY),
      as Marlin's ``apply_motion_limits`` does for a delta; :attr:`MarlinPlanner.clamped` counts them.

Not modelled: step rounding (Marlin computes trapezoids in whole steps), S-curve acceleration, classic
jerk, delta segmentation (``DELTA_SEGMENTS_PER_SECOND``) and per-tower limits (limits act on the
Cartesian X/Y/Z/E components here), the buffer-draining SLOWDOWN and the first-move delivery delay.
"""

from __future__ import annotations

import math

from .junction import JUNCTION_RULES
from .moves import DWELL, EXTRUDE, MOVE, PlannedMove

__all__ = ["MarlinPlanner"]


class _Block:
    __slots__ = ("lineno", "start", "end", "unit", "millimeters", "nominal_speed", "accel", "max_entry_sqr",
                 "entry_sqr", "min_entry_sqr", "is_kin")


def _trapezoid(d: float, v0: float, v1: float, vn: float, a: float):
    """Continuous trapezoid over ``d`` mm from ``v0`` to ``v1`` with peak ``vn`` and acceleration ``a``.

    Returns (start_v, cruise_v, end_v, accel_t, cruise_t, decel_t).
    """
    v0 = min(v0, vn)
    v1 = min(v1, vn)
    half_inv = 0.5 / a
    accel_d = (vn * vn - v0 * v0) * half_inv
    decel_d = (vn * vn - v1 * v1) * half_inv
    if accel_d + decel_d > d:
        accel_d = (2.0 * a * d - v0 * v0 + v1 * v1) * 0.5 * half_inv
        accel_d = min(max(accel_d, 0.0), d)
        vc = math.sqrt(v0 * v0 + 2.0 * a * accel_d)
        decel_d = d - accel_d
        # speeds that a single block cannot join are clipped (Marlin's passes prevent this)
        if vc < v1:
            v1 = vc
        cruise_d = 0.0
    else:
        vc = vn
        cruise_d = d - accel_d - decel_d
    accel_t = accel_d / ((v0 + vc) * 0.5) if accel_d > 0.0 else 0.0
    decel_t = decel_d / ((v1 + vc) * 0.5) if decel_d > 0.0 else 0.0
    cruise_t = cruise_d / vc if cruise_d > 0.0 else 0.0
    return v0, vc, v1, accel_t, cruise_t, decel_t


class MarlinPlanner:
    """Marlin's planner buffer, fed one G-code record at a time (interface of :class:`KlipperPlanner`).

    Parameters
    ----------
    profile : PrinterProfile
        Limits map to Marlin settings: max feed rate X/Y = ``max_velocity_mm_s``, Z = ``max_z_velocity_mm_s``,
        E = ``max_extrude_only_velocity_mm_s``; max acceleration X/Y = ``max_accel_mm_s2``,
        Z = ``max_z_accel_mm_s2``, E = ``max_extrude_only_accel_mm_s2``; print and travel acceleration =
        ``max_accel_mm_s2``; retract acceleration = ``max_extrude_only_accel_mm_s2``; junction deviation
        = ``junction_deviation_mm``; steps/mm = ``steps_per_mm``.
    block_buffer_size : int
        ``BLOCK_BUFFER_SIZE`` (16).
    small_segments : bool
        ``JD_HANDLE_SMALL_SEGMENTS`` (on in Marlin's default configuration).
    """

    name = "marlin"

    def __init__(self, profile, *, path: str = "<gcode>", block_buffer_size: int = 16,
                 small_segments: bool = True, start_position_mm=(0.0, 0.0, 0.0, 0.0), **_ignored):
        lim = profile.limits
        if block_buffer_size < 3:
            raise ValueError("block_buffer_size must be >= 3")
        self.path = path
        self.max_feedrate = [lim.max_velocity_mm_s, lim.max_velocity_mm_s, lim.max_z_velocity_mm_s,
                             lim.max_extrude_only_velocity_mm_s]
        self.max_accel = [lim.max_accel_mm_s2, lim.max_accel_mm_s2, lim.max_z_accel_mm_s2,
                          lim.max_extrude_only_accel_mm_s2]
        self.print_accel = lim.max_accel_mm_s2
        self.travel_accel = lim.max_accel_mm_s2
        self.retract_accel = lim.max_extrude_only_accel_mm_s2
        self.junction_deviation = lim.junction_deviation_mm
        self.min_feedrate = 0.0
        self.min_travel_feedrate = 0.0
        self.steps_per_mm = lim.steps_per_mm
        g = profile.geometry
        self.max_radius2 = g.print_radius_mm ** 2
        self.z_min, self.z_max = g.z_min_mm, g.z_max_mm
        self.clamped = 0
        self.small_segments = small_segments
        self._corner_v2 = JUNCTION_RULES[self.name]
        self.capacity = block_buffer_size - 2  # one slot stays empty, one block is executing
        self.commanded_pos = [float(v) for v in start_position_mm]
        self.stops = 0  # stop commands met (see stop())
        self.on_stop = None  # callable(t_s, lineno) told the print time of every stop
        self.queue: list[_Block] = []
        self.prev_unit = (0.0, 0.0, 0.0, 0.0)
        self.prev_nominal_speed = 0.0
        self.print_time = 0.0
        self.out: list[PlannedMove] = []
        self.n_out = 0
        #: limit commands Marlin ignores, by name (see :attr:`ignored_commands`)
        self.ignored: dict[str, int] = {}
        self._limits = {"M201": self._m201, "M203": self._m203, "M204": self._m204, "M205": self._m205}

    # ------------------------------------------------------------------ limits
    def limits(self, op, line) -> None:
        h = self._limits.get(op.command)
        if h is None:  # SET_VELOCITY_LIMIT is unknown to Marlin
            self.ignored[op.command] = self.ignored.get(op.command, 0) + 1
            return
        h(op)

    @property
    def ignored_commands(self) -> int:
        """How many limit commands Marlin ignored (:attr:`ignored` says which)."""
        return sum(self.ignored.values())

    def _m201(self, op) -> None:
        for i, v in enumerate(op.max_accel_axes_mm_s2 or ()):
            if v is not None:
                self.max_accel[i] = v

    def _m203(self, op) -> None:
        for i, v in enumerate(op.max_feedrate_axes_mm_s or ()):
            if v is not None:
                self.max_feedrate[i] = v

    def _m204(self, op) -> None:
        if op.accel_mm_s2 is not None:
            self.print_accel = self.travel_accel = op.accel_mm_s2
        if op.print_accel_mm_s2 is not None:
            self.print_accel = op.print_accel_mm_s2
        if op.retract_accel_mm_s2 is not None:
            self.retract_accel = op.retract_accel_mm_s2
        if op.travel_accel_mm_s2 is not None:
            self.travel_accel = op.travel_accel_mm_s2

    def _m205(self, op) -> None:
        if op.junction_deviation_mm is not None:
            self.junction_deviation = op.junction_deviation_mm
        if op.min_feedrate_mm_s is not None:
            self.min_feedrate = op.min_feedrate_mm_s
        if op.min_travel_feedrate_mm_s is not None:
            self.min_travel_feedrate = op.min_travel_feedrate_mm_s

    # ------------------------------------------------------------------ blocks
    def _clamp(self, end):
        """Software endstops: Marlin clamps a delta target to the printable radius and Z range."""
        x, y, z = end[0], end[1], end[2]
        r2 = x * x + y * y
        if r2 > self.max_radius2:
            f = math.sqrt(self.max_radius2 / r2)
            x, y = x * f, y * f
            self.clamped += 1
        if z < self.z_min or z > self.z_max:
            z = min(max(z, self.z_min), self.z_max)
            self.clamped += 1
        return (x, y, z, end[3])

    def move(self, end, speed: float, line) -> None:
        # (the loops over the four axes are written out: the same arithmetic in the same order, at
        # a third of the cost; the feed re-timing plans a Marlin file several times)
        sp = self.commanded_pos
        end = self._clamp(end)
        d0, d1, d2, d3 = end[0] - sp[0], end[1] - sp[1], end[2] - sp[2], end[3] - sp[3]
        mm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        is_kin = mm >= 1e-9
        if not is_kin:
            if not d3:
                return
            d0 = d1 = d2 = 0.0
            end = (sp[0], sp[1], sp[2], end[3])
            mm = abs(d3)
        b = _Block()
        b.lineno = line.lineno
        b.start = tuple(sp)
        b.end = (end[0], end[1], end[2], end[3])
        b.is_kin = is_kin
        b.millimeters = mm
        inv_mm = 1.0 / mm
        fr = max(speed, self.min_feedrate if d3 else self.min_travel_feedrate)
        inv_secs = fr * inv_mm
        nominal = fr
        factor = 1.0
        mf = self.max_feedrate
        for di, mfi in ((d0, mf[0]), (d1, mf[1]), (d2, mf[2]), (d3, mf[3])):
            cs = abs(di * inv_secs)
            if cs > mfi:
                factor = min(factor, mfi / cs)
        nominal *= factor
        b.nominal_speed = nominal
        ma = self.max_accel
        if not is_kin:
            accel = self.retract_accel
        else:
            accel = self.print_accel if d3 else self.travel_accel
            for di, mai in ((d0, ma[0]), (d1, ma[1]), (d2, ma[2]), (d3, ma[3])):
                if di:
                    accel = min(accel, mai * mm / abs(di))
        b.accel = accel
        min_v2 = min(0.5 * accel / self.steps_per_mm, nominal * nominal)
        # unit vector for the junction: XYZE normalised when the block extrudes, else XYZ / millimeters
        if d3:
            n = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3)
            unit = (d0 / n, d1 / n, d2 / n, d3 / n)
        else:
            unit = (d0 * inv_mm, d1 * inv_mm, d2 * inv_mm, 0.0)
        if self.queue and self.prev_nominal_speed > 1e-9:
            pu = self.prev_unit
            u0, u1, u2, u3 = unit
            cos_t = -(pu[0] * u0 + pu[1] * u1 + pu[2] * u2 + pu[3] * u3)
            j0, j1, j2, j3 = u0 - pu[0], u1 - pu[1], u2 - pu[2], u3 - pu[3]
            jn = math.sqrt(j0 * j0 + j1 * j1 + j2 * j2 + j3 * j3)
            ja = accel
            if jn > 0.0:
                for ji, mai in ((j0, ma[0]), (j1, ma[1]), (j2, ma[2]), (j3, ma[3])):
                    c = abs(ji / jn)
                    if c and ja * c > mai:
                        ja = mai / c
            v2 = self._corner_v2(cos_t, ja, self.junction_deviation, mm, min_v2, self.small_segments)
            v2 = min(v2, nominal * nominal, self.prev_nominal_speed ** 2)
        else:
            v2 = min_v2
        b.max_entry_sqr = max(v2, min_v2)
        b.entry_sqr = min_v2
        b.min_entry_sqr = min_v2
        self.prev_unit = unit
        self.prev_nominal_speed = nominal
        self.commanded_pos = list(b.end)
        if len(self.queue) >= self.capacity:
            self._execute_oldest()
        self.queue.append(b)
        self._recalculate()

    def _recalculate(self) -> None:
        q = self.queue
        n = len(q)
        # reverse pass: the newest block plans to stop; queue[0]'s entry is frozen
        next_entry = 0.0
        for i in range(n - 1, 0, -1):
            b = q[i]
            e = next_entry + 2.0 * b.accel * b.millimeters
            mx = b.max_entry_sqr
            next_entry = b.entry_sqr = mx if mx < e else e
        # forward pass
        p = q[0]
        for i in range(1, n):
            b = q[i]
            if p.entry_sqr < b.entry_sqr:
                new_exit = p.entry_sqr + 2.0 * p.accel * p.millimeters
                if new_exit < b.entry_sqr:
                    new_exit = max(new_exit, b.min_entry_sqr)
                    b.entry_sqr = new_exit
                    b.max_entry_sqr = new_exit
            b.min_entry_sqr = b.entry_sqr
            p = b

    def _emit(self, b: _Block, exit_sqr: float) -> None:
        v0, vc, v1, ta, tc, td = _trapezoid(b.millimeters, math.sqrt(b.entry_sqr), math.sqrt(exit_sqr),
                                            b.nominal_speed, b.accel)
        if b.is_kin:
            e, st, mm = b.end, b.start, b.millimeters
            unit = ((e[0] - st[0]) / mm, (e[1] - st[1]) / mm, (e[2] - st[2]) / mm, (e[3] - st[3]) / mm)
        else:
            unit = (0.0, 0.0, 0.0, math.copysign(1.0, b.end[3] - b.start[3]))
        t = self.print_time
        self.out.append(PlannedMove(self.n_out, b.lineno, MOVE if b.is_kin else EXTRUDE, t, b.start, b.end,
                                    b.millimeters, unit, v0, vc, v1, b.accel, ta, tc, td))
        self.n_out += 1
        self.print_time = t + ta + tc + td

    def _execute_oldest(self) -> None:
        q = self.queue
        b = q.pop(0)
        self._emit(b, q[0].entry_sqr if q else 0.0)

    def _drain(self) -> None:
        while self.queue:
            self._execute_oldest()

    # ------------------------------------------------------------------ other records
    def dwell(self, delay_s: float, lineno: int) -> None:
        self._drain()
        if delay_s > 0.0:
            p = tuple(self.commanded_pos)
            self.out.append(PlannedMove(self.n_out, lineno, DWELL, self.print_time, p, p, 0.0,
                                        (0.0, 0.0, 0.0, 0.0), 0.0, 0.0, 0.0, 0.0, 0.0, delay_s, 0.0))
            self.n_out += 1
            self.print_time += delay_s

    def sync(self, reason: str, lineno: int) -> None:
        self._drain()
        if self.on_stop is not None:
            self.on_stop(self.print_time, lineno)

    def stop(self, command: str, lineno: int) -> None:
        """A command that stops or moves the machine on its own: drain the buffer first (as M400)."""
        self.sync("M400", lineno)
        self.stops += 1

    def home(self, position, lineno: int) -> None:
        self._drain()
        self.commanded_pos = [position[0], position[1], position[2], self.commanded_pos[3]]

    def finish(self) -> None:
        self._drain()

    def take(self) -> list[PlannedMove]:
        out = self.out
        self.out = []
        return out
