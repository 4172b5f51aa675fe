"""A model of Klipper's motion planning (``klippy/toolhead.py``, ``kinematics/delta.py``,
``kinematics/extruder.py``): the same arithmetic, so the planned times match a Klipper host.

Modelled (Klipper 0.12 / 2024-2025 sources)
    * ``Move``: speed capped at ``max_velocity``; moves shorter than 1e-9 mm in XYZ are extruder-only moves
      (accel 99999999.9, speed not capped by ``max_velocity``); ``delta_v2 = 2 d a``,
      ``smooth_delta_v2 = 2 d max_accel_to_decel`` with ``max_accel_to_decel = max_accel (1 -
      minimum_cruise_ratio)``; ``limit_speed``.
    * ``calc_junction``: cruise speeds of both moves, the previous move's reachable speed, the extruder's
      ``instantaneous_corner_velocity / |delta extrusion ratio|``, and the corner rule of
      :func:`ffcomp.gcode.junction.klipper_corner_v2` (junction deviation from
      ``square_corner_velocity``, centripetal limit); ``max_smoothed_v2``.
    * ``LookAheadQueue``: the backward pass with the smoothed ("accel_to_decel") profile and the delayed
      full-acceleration moves, lazy flushing once ``junction_flush`` (0.25 s of queued minimum move
      time; 2 s after a full flush) is used up, full flush on G4 / M400 / M84 / G28 and at the end;
      print time advanced by each flushed move's accel_t + cruise_t + decel_t; G4 adds its delay after the
      last move.
    * Delta ``check_move``: out-of-range end points (print radius, ``arm - radius``, the tower-ratio
      limit, z range, the cone above ``limit_z``) raise; moves with Z travel are limited to
      ``max_z_velocity * d/|dz|`` and ``max_z_accel * d/|dz|``; moves reaching past ``slow_xy2`` /
      ``very_slow_xy2`` (from ``ratio_to_xy``) are limited to half / a quarter of the configured
      ``max_velocity`` and ``max_accel``.
    * Extruder ``check_move``: retractions and moves without XY travel are limited by
      ``max_extrude_only_velocity`` / ``_accel`` scaled by the extrusion ratio;
      ``max_extrude_only_distance`` raises.
    * ``SET_VELOCITY_LIMIT`` (VELOCITY, ACCEL, SQUARE_CORNER_VELOCITY, MINIMUM_CRUISE_RATIO, and
      ACCEL_TO_DECEL converted to a cruise ratio) and ``M204`` (S; else min(P, T) when both are given;
      otherwise ignored, as Klipper does).  M201 / M203 / M205 are unknown to Klipper and ignored.

Not Klipper's: ``quiet_z_period_s`` (ffcomp's own plan of a source, off by default) slows the ramps
of the z moves next to extruder-only moves (:func:`quiet_accel`).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import GcodeError, KinematicsError
from .junction import JUNCTION_RULES, klipper_junction_deviation
from .moves import DWELL, EXTRUDE, FIRMWARE, MOVE, PlannedMove
from .records import FirmwareMove

__all__ = ["KlipperPlanner", "KlipperDelta", "LOOKAHEAD_FLUSH_TIME", "BUFFER_TIME_HIGH", "SLOW_RATIO", "quiet_accel",
           "rest_to_rest_s"]

LOOKAHEAD_FLUSH_TIME = 0.250
BUFFER_TIME_HIGH = 2.0
SLOW_RATIO = 3.0
MOTOR_OFF_DWELL_S = 0.1  # DISABLE_STALL_TIME, applied before and after M18/M84


def quiet_accel(d_mm: float, v_mm_s: float, period_s: float) -> float:
    """The acceleration (mm/s^2) at which a move of ``d_mm`` at up to ``v_mm_s`` ramps from rest to
    its cruise speed, or to its peak on a move too short to cruise, in exactly ``period_s``.

    A constant-acceleration ramp lasting one period of a resonance has a spectral zero at its
    frequency, so a rest-to-rest move planned at this acceleration leaves no ringing of that mode
    (of an undamped one exactly, of a lightly damped one almost).
    """
    return min(d_mm / period_s ** 2, v_mm_s / period_s)


def rest_to_rest_s(d_mm: float, v_mm_s: float, accel_mm_s2: float) -> float:
    """Duration (s) of a trapezoidal move of ``d_mm`` from rest to rest at up to ``v_mm_s``."""
    if v_mm_s * v_mm_s >= d_mm * accel_mm_s2:  # a triangle: no cruise
        return 2.0 * math.sqrt(d_mm / accel_mm_s2)
    return d_mm / v_mm_s + v_mm_s / accel_mm_s2


def _flows_on(a, b) -> bool:
    """Whether move ``b`` continues move ``a`` within 60 degrees (the junction keeps much of the speed)."""
    ra, rb = a.axes_r, b.axes_r
    return ra[0] * rb[0] + ra[1] * rb[1] + ra[2] * rb[2] > 0.5


def _steep(m) -> bool:
    """A move that travels more in z than in XY (a layer change's z move, a z-hop)."""
    dx, dy, dz = m.axes_d[0], m.axes_d[1], m.axes_d[2]
    return dz != 0.0 and dz * dz >= dx * dx + dy * dy


class _Move:
    """Klipper's ``Move`` (mutable, internal)."""

    __slots__ = ("lineno", "start", "end", "axes_d", "axes_r", "move_d", "accel", "jd", "is_kin", "kind",
                 "min_move_t", "max_start_v2", "max_cruise_v2", "delta_v2", "max_smoothed_v2",
                 "smooth_delta_v2", "next_junction_v2", "start_v", "cruise_v", "end_v", "accel_t",
                 "cruise_t", "decel_t", "quiet", "loud")

    def limit_speed(self, speed: float, accel: float) -> None:
        speed2 = speed ** 2
        if speed2 < self.max_cruise_v2:
            self.max_cruise_v2 = speed2
            self.min_move_t = self.move_d / speed
        # min() written out (the same value: min keeps the first of equals): a planner hot path
        if accel < self.accel:
            self.accel = accel
        self.delta_v2 = delta_v2 = 2.0 * self.move_d * self.accel
        if delta_v2 < self.smooth_delta_v2:
            self.smooth_delta_v2 = delta_v2

    def set_junction(self, start_v2: float, cruise_v2: float, end_v2: float) -> None:
        half_inv_accel = 0.5 / self.accel
        accel_d = (cruise_v2 - start_v2) * half_inv_accel
        decel_d = (cruise_v2 - end_v2) * half_inv_accel
        cruise_d = self.move_d - accel_d - decel_d
        self.start_v = start_v = math.sqrt(start_v2)
        self.cruise_v = cruise_v = math.sqrt(cruise_v2)
        self.end_v = end_v = math.sqrt(end_v2)
        self.accel_t = accel_d / ((start_v + cruise_v) * 0.5)
        self.cruise_t = cruise_d / cruise_v
        self.decel_t = decel_d / ((end_v + cruise_v) * 0.5)


class KlipperDelta:
    """Klipper's delta ``check_move``: workspace limits and the speed limits near the edge and in Z.

    Built from the profile the way Klipper reads its ``[printer]`` / ``[stepper_*]`` sections:
    ``delta_radius`` = the largest tower radius, ``arm_length`` per tower, ``print_radius``,
    ``position_endstop`` = ``z_max_mm`` (so ``max_z``), ``minimum_z_position`` = ``z_min_mm``, step
    distance ``1 / steps_per_mm``.
    """

    def __init__(self, profile, max_velocity: float, max_accel: float):
        g, lim = profile.geometry, profile.limits
        self.max_velocity = max_velocity
        self.max_accel = max_accel
        self.max_z_velocity = min(lim.max_z_velocity_mm_s, max_velocity)
        self.max_z_accel = min(lim.max_z_accel_mm_s2, max_accel)
        self.radius = radius = max(g.delta_radius_mm)
        arms = list(g.arm_length_mm)
        self.min_arm_length = min_arm = min(arms)
        self.min_arm2 = min_arm ** 2
        self.max_z = g.z_max_mm
        self.min_z = g.z_min_mm
        abs_endstops = [self.max_z + math.sqrt(a ** 2 - radius ** 2) for a in arms]
        self.limit_z = min(ep - a for ep, a in zip(abs_endstops, arms, strict=True))
        half_step = 0.5 / lim.steps_per_mm

        def ratio_to_xy(ratio):
            return ratio * math.sqrt(min_arm ** 2 / (ratio ** 2 + 1.0) - half_step ** 2) + half_step - radius

        self.slow_xy2 = ratio_to_xy(SLOW_RATIO) ** 2
        self.very_slow_xy2 = ratio_to_xy(2.0 * SLOW_RATIO) ** 2
        self.max_xy2 = min(g.print_radius_mm, min_arm - radius, ratio_to_xy(4.0 * SLOW_RATIO)) ** 2
        self.home_position = (0.0, 0.0, self.max_z)
        self.limit_xy2 = -1.0

    def set_position(self) -> None:
        self.limit_xy2 = -1.0

    def out_of_range(self, end) -> bool:
        """Whether any of the end points ``end`` ((n, 3) array, mm) is one :meth:`check_move` refuses
        (the same rules on arrays, for the chain planner)."""
        x, y, z = end[:, 0], end[:, 1], end[:, 2]
        xy2 = x * x + y * y
        limit = np.full(len(z), self.max_xy2)
        above = z - self.limit_z
        hi = above > 0
        if hi.any():
            d2 = self.min_arm2 - (self.min_arm_length - above[hi]) ** 2
            if (d2 < 0).any():
                return True
            limit[hi] = np.minimum(limit[hi], (self.radius - np.sqrt(d2)) ** 2)
        bad = (xy2 > limit) | (z > self.max_z) | (z < self.min_z)
        if not bad.any():
            return False
        hp = self.home_position
        home = (x == hp[0]) & (y == hp[1]) & (z >= self.min_z) & (z <= hp[2])
        return bool((bad & ~home).any())

    def check_move(self, m: _Move) -> str | None:
        """Apply the limits to ``m``; return an error message if the move is out of range."""
        end = m.end
        end_xy2 = end[0] ** 2 + end[1] ** 2
        if end_xy2 <= self.limit_xy2 and not m.axes_d[2]:
            return None
        end_z = end[2]
        limit_xy2 = self.max_xy2
        if end_z > self.limit_z:
            above = end_z - self.limit_z
            d2 = self.min_arm2 - (self.min_arm_length - above) ** 2
            if d2 < 0.0:  # far above the top of the towers (Klipper's sqrt would raise): unreachable
                return "Move out of range: %.3f %.3f %.3f [%.3f]" % tuple(end)
            allowed = self.radius - math.sqrt(d2)
            limit_xy2 = min(limit_xy2, allowed ** 2)
        if end_xy2 > limit_xy2 or end_z > self.max_z or end_z < self.min_z:
            hp = self.home_position
            if (end[0], end[1]) != hp[:2] or end_z < self.min_z or end_z > hp[2]:
                return "Move out of range: %.3f %.3f %.3f [%.3f]" % tuple(end)
            limit_xy2 = -1.0
        if m.axes_d[2]:
            z_ratio = m.move_d / abs(m.axes_d[2])
            m.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio)
            limit_xy2 = -1.0
        start_xy2 = m.start[0] ** 2 + m.start[1] ** 2
        extreme_xy2 = start_xy2 if start_xy2 > end_xy2 else end_xy2  # max(), written out
        if extreme_xy2 > self.slow_xy2:
            r = 0.5
            if extreme_xy2 > self.very_slow_xy2:
                r = 0.25
            m.limit_speed(self.max_velocity * r, self.max_accel * r)
            limit_xy2 = -1.0
        slow_xy2 = self.slow_xy2
        self.limit_xy2 = slow_xy2 if slow_xy2 < limit_xy2 else limit_xy2  # min(), written out
        return None


class KlipperPlanner:
    """Klipper's toolhead + lookahead queue, fed one G-code record at a time.

    Parameters
    ----------
    profile : PrinterProfile
    path : str
        File name for error messages.
    max_extrude_only_distance_mm : float or None
        Klipper's ``max_extrude_only_distance`` (50 mm default); None disables the check.
    start_position_mm : (x, y, z, e)
    quiet_z_period_s : float or None
        Not Klipper's: ffcomp's own plan of a source (``CompensateOptions.quiet_z``).  A move that
        travels more in z than in XY right after or right before an extruder-only move (a layer
        change's z move, a z-hop's lift and its move down) is planned at the acceleration whose ramp
        from rest to its cruise speed (or to its peak, on a short move) lasts this long (the period of
        the printer's z resonance): each ramp's spectrum then has a zero at that frequency, and the
        move leaves (almost) no ringing.  A G-code file cannot compensate these moves (the nozzle
        stands still during the holds around them), so the plan itself must not excite the printer.
        None (the default): Klipper's plan.

    Use :meth:`feed` for every record and :meth:`finish` at the end; both return the moves that became
    final, in order.
    """

    name = "klipper"

    def __init__(self, profile, *, path: str = "<gcode>", max_extrude_only_distance_mm: float | None = 50.0,
                 start_position_mm=(0.0, 0.0, 0.0, 0.0), quiet_z_period_s: float | None = None):
        lim = profile.limits
        self.path = path
        self.max_velocity = lim.max_velocity_mm_s
        self.max_accel = lim.max_accel_mm_s2
        self.min_cruise_ratio = lim.minimum_cruise_ratio
        self.square_corner_velocity = lim.square_corner_velocity_mm_s
        self.junction_deviation = self.max_accel_to_decel = 0.0
        self._calc_junction_deviation()
        self.instant_corner_v = lim.instantaneous_corner_velocity_mm_s
        self.max_e_velocity = lim.max_extrude_only_velocity_mm_s
        self.max_e_accel = lim.max_extrude_only_accel_mm_s2
        self.max_e_dist = max_extrude_only_distance_mm
        self.kin = KlipperDelta(profile, self.max_velocity, self.max_accel)
        self._corner_v2 = JUNCTION_RULES[self.name]
        self.commanded_pos = [float(v) for v in start_position_mm]
        self.stops = 0  # stop commands met (see stop())
        self.on_stop = None  # callable(t_s, lineno) told the print time of every stop
        self.queue: list[_Move] = []
        self.junction_flush = BUFFER_TIME_HIGH
        self.need_prime = True
        self.print_time = 0.0
        self.out: list[PlannedMove] = []
        self.n_out = 0
        #: limit commands Klipper ignores, by what they are (see :attr:`ignored_commands`)
        self.ignored: dict[str, int] = {}
        self.quiet_z_period_s = quiet_z_period_s
        self.quiet_moves = 0  # z moves next to a hold planned with quiet ramps (quiet_z_period_s)
        self.quiet_added_s = 0.0  # the time their ramps add, rest to rest, s
        self._last_kin = True  # whether the last move created was an XYZ move
        self._limits = {
            "SET_VELOCITY_LIMIT": self._set_velocity_limit,
            "M204": self._m204,
        }

    # ------------------------------------------------------------------ limits
    def _calc_junction_deviation(self) -> None:
        self.junction_deviation = klipper_junction_deviation(self.square_corner_velocity, self.max_accel)
        self.max_accel_to_decel = self.max_accel * (1.0 - self.min_cruise_ratio)

    def limits(self, op, line) -> None:
        h = self._limits.get(op.command)
        if h is None:  # (M201, M203, M205: not Klipper commands)
            self.ignored[op.command] = self.ignored.get(op.command, 0) + 1
            return
        h(op)

    @property
    def ignored_commands(self) -> int:
        """How many limit commands Klipper ignored (:attr:`ignored` says which)."""
        return sum(self.ignored.values())

    def _set_velocity_limit(self, op) -> None:
        mcr = op.minimum_cruise_ratio
        if mcr is None and op.accel_to_decel_mm_s2 is not None:
            base = op.accel_mm_s2 if op.accel_mm_s2 is not None else self.max_accel
            mcr = 1.0 - min(1.0, op.accel_to_decel_mm_s2 / base)
        if op.velocity_mm_s is not None:
            self.max_velocity = op.velocity_mm_s
        if op.accel_mm_s2 is not None:
            self.max_accel = op.accel_mm_s2
        if op.square_corner_velocity_mm_s is not None:
            self.square_corner_velocity = op.square_corner_velocity_mm_s
        if mcr is not None:
            self.min_cruise_ratio = mcr
        self._calc_junction_deviation()

    def _m204(self, op) -> None:
        accel = op.accel_mm_s2
        if accel is None:
            p, t = op.print_accel_mm_s2, op.travel_accel_mm_s2
            if p is None or t is None:
                key = "M204 without S or T"  # Klipper: 'Invalid M204 command'
                self.ignored[key] = self.ignored.get(key, 0) + 1
                return
            accel = min(p, t)
        self.max_accel = accel
        self._calc_junction_deviation()

    # ------------------------------------------------------------------ moves
    def move(self, end, speed: float, line) -> None:
        """``toolhead.move(newpos, speed)`` from the commanded position (Klipper's ``Move`` inlined)."""
        sx, sy, sz, se = self.commanded_pos
        ex, ey, ez, ee = end
        dx = ex - sx
        dy = ey - sy
        dz = ez - sz
        de = ee - se
        move_d = math.sqrt(dx * dx + dy * dy + dz * dz)
        m = _Move()
        if move_d < 0.000000001:
            # extruder-only move
            ex, ey, ez = sx, sy, sz
            dx = dy = dz = 0.0
            move_d = abs(de)
            if not move_d:
                return
            inv = 1.0 / move_d
            accel = 99999999.9
            velocity = speed
            m.is_kin = is_kin = False
            m.kind = FIRMWARE if type(line.op) is FirmwareMove else EXTRUDE  # G10/G11 (the parser's call)
        else:
            inv = 1.0 / move_d
            accel = self.max_accel
            velocity = min(speed, self.max_velocity)
            m.is_kin = is_kin = True
        m.lineno = line.lineno
        m.quiet = False
        m.jd = self.junction_deviation
        m.accel = accel
        m.start = (sx, sy, sz, se)
        m.end = (ex, ey, ez, ee)
        m.axes_d = (dx, dy, dz, de)
        m.axes_r = axes_r = (dx * inv, dy * inv, dz * inv, de * inv)
        m.move_d = move_d
        m.min_move_t = move_d / velocity
        m.max_start_v2 = 0.0
        m.max_cruise_v2 = velocity ** 2
        m.delta_v2 = 2.0 * move_d * accel
        m.max_smoothed_v2 = 0.0
        m.smooth_delta_v2 = 2.0 * move_d * self.max_accel_to_decel
        m.next_junction_v2 = 999999999.9
        if is_kin:
            err = self.kin.check_move(m)
            if err is not None:
                raise KinematicsError(f"{self.path}:{line.lineno}: {err}: {line.text.strip()!r}")
        if de and ((not dx and not dy) or axes_r[3] < 0.0):  # (the test of _extruder_check_move)
            self._extruder_check_move(m, line)
        self.commanded_pos = [ex, ey, ez, ee]
        q = self.queue
        if self.quiet_z_period_s is not None:
            self._quiet_rules(q, m)
        if not q:
            q.append(m)
            return
        prev = q[-1]
        q.append(m)
        if is_kin and prev.is_kin:
            self._junction(prev, m)
        self.junction_flush -= m.min_move_t
        if self.junction_flush <= 0.0:
            self._process(lazy=True)

    def _junction(self, prev: _Move, m: _Move) -> None:
        """``Move.calc_junction``: cruise speeds, reachable speed, extruder and corner limits."""
        if not (m.is_kin and prev.is_kin):
            return
        axes_r, pr = m.axes_r, prev.axes_r
        diff_r = axes_r[3] - pr[3]
        extruder_v2 = (self.instant_corner_v / abs(diff_r)) ** 2 if diff_r else m.max_cruise_v2
        max_start_v2 = min(m.max_cruise_v2, prev.max_cruise_v2, prev.next_junction_v2,
                           prev.max_start_v2 + prev.delta_v2, extruder_v2)
        junction_cos_theta = -(axes_r[0] * pr[0] + axes_r[1] * pr[1] + axes_r[2] * pr[2])
        corner = self._corner_v2(junction_cos_theta, m.jd, m.accel, m.delta_v2,
                                 prev.jd, prev.accel, prev.delta_v2)
        if corner < max_start_v2:
            max_start_v2 = corner
        m.max_start_v2 = max_start_v2
        reach_v2 = prev.max_smoothed_v2 + prev.smooth_delta_v2
        m.max_smoothed_v2 = reach_v2 if reach_v2 < max_start_v2 else max_start_v2

    def _quiet_rules(self, q: list, m: _Move) -> None:
        """Which moves ``quiet_z_period_s`` plans quiet, as ``m`` joins the queue ``q``: a steep move
        right after an extruder-only move (when it is made), a steep move right before one (when the
        extruder-only move comes; the move is still queued: the look-ahead keeps its last move), but
        not one that runs on within 60 degrees into the next move or from the one before (it does not
        come to rest).  A move whose acceleration changes gets its junction with the move before it
        again."""
        prev = q[-1] if q and self._last_kin else None  # the move made just before m, if an XYZ one
        before = q[-2] if len(q) > 1 and q[-2].is_kin else None
        if m.is_kin:
            if prev is not None and prev.quiet and _flows_on(prev, m):
                self._loud(prev)
                if before is not None:
                    self._junction(before, prev)
            if not self._last_kin and _steep(m):
                self._quiet(m)
        elif prev is not None and _steep(prev) and not (before is not None and _flows_on(before, prev)):
            if self._quiet(prev) and before is not None:
                self._junction(before, prev)
        self._last_kin = m.is_kin

    def _quiet(self, m: _Move) -> bool:
        """Lower ``m``'s acceleration so that its ramp from rest lasts ``quiet_z_period_s``
        (:func:`quiet_accel`); whether it changed."""
        v = math.sqrt(m.max_cruise_v2)
        a = quiet_accel(m.move_d, v, self.quiet_z_period_s)
        if not a < m.accel:
            return False
        added = rest_to_rest_s(m.move_d, v, a) - rest_to_rest_s(m.move_d, v, m.accel)
        self.quiet_moves += 1
        self.quiet_added_s += added
        m.loud = (m.accel, m.delta_v2, m.smooth_delta_v2, added)
        m.limit_speed(v, a)
        m.quiet = True
        return True

    def _loud(self, m: _Move) -> None:
        """Undo :meth:`_quiet` (the move runs on into the next one, collinear: it does not come to rest,
        and its slow ramp would only slow the z travel)."""
        m.accel, m.delta_v2, m.smooth_delta_v2, added = m.loud
        m.quiet = False
        self.quiet_moves -= 1
        self.quiet_added_s -= added

    def _extruder_check_move(self, m: _Move, line) -> None:
        axis_r = m.axes_r[3]
        if (not m.axes_d[0] and not m.axes_d[1]) or axis_r < 0.0:
            if self.max_e_dist is not None and abs(m.axes_d[3]) > self.max_e_dist:
                msg = "Extrude only move too long (%.3fmm vs %.3fmm)" % (m.axes_d[3], self.max_e_dist)
                raise GcodeError(self.path, line.lineno, msg, line.text)
            inv_extrude_r = 1.0 / abs(axis_r)
            m.limit_speed(self.max_e_velocity * inv_extrude_r, self.max_e_accel * inv_extrude_r)

    # ------------------------------------------------------------------ lookahead
    def _flush_queue(self, lazy: bool) -> list[_Move]:
        """``LookAheadQueue.flush``: finalize the moves whose profile can no longer change."""
        self.junction_flush = LOOKAHEAD_FLUSH_TIME
        update_flush_count = lazy
        queue = self.queue
        flush_count = len(queue)
        delayed: list = []
        next_end_v2 = next_smoothed_v2 = peak_cruise_v2 = 0.0
        for i in range(flush_count - 1, -1, -1):
            move = queue[i]
            # min() written out: this loop is the planner's hot path
            reachable_start_v2 = next_end_v2 + move.delta_v2
            start_v2 = move.max_start_v2
            if not start_v2 <= reachable_start_v2:
                start_v2 = reachable_start_v2
            reachable_smoothed_v2 = next_smoothed_v2 + move.smooth_delta_v2
            smoothed_v2 = move.max_smoothed_v2
            if not smoothed_v2 <= reachable_smoothed_v2:
                smoothed_v2 = reachable_smoothed_v2
            if smoothed_v2 < reachable_smoothed_v2:
                # this move can accelerate
                if smoothed_v2 + move.smooth_delta_v2 > next_smoothed_v2 or delayed:
                    # ... and decelerate, or it is a full-accel move after a full-decel one
                    if update_flush_count and peak_cruise_v2:
                        flush_count = i
                        update_flush_count = False
                    peak_cruise_v2 = min(move.max_cruise_v2, (smoothed_v2 + reachable_smoothed_v2) * 0.5)
                    if delayed:
                        if not update_flush_count and i < flush_count:
                            mc_v2 = peak_cruise_v2
                            for dm, ms_v2, me_v2 in reversed(delayed):
                                mc_v2 = min(mc_v2, ms_v2)
                                dm.set_junction(min(ms_v2, mc_v2), mc_v2, min(me_v2, mc_v2))
                        del delayed[:]
                if not update_flush_count and i < flush_count:
                    cruise_v2 = min((start_v2 + reachable_start_v2) * 0.5, move.max_cruise_v2, peak_cruise_v2)
                    move.set_junction(min(start_v2, cruise_v2), cruise_v2, min(next_end_v2, cruise_v2))
            else:
                # a full-acceleration move: wait until the peak speed is known
                delayed.append((move, start_v2, next_end_v2))
            next_end_v2 = start_v2
            next_smoothed_v2 = smoothed_v2
        if update_flush_count or not flush_count:
            return []
        if delayed and not lazy:  # pragma: no cover - the first queued move can always accelerate
            mc_v2 = min(d[0].max_cruise_v2 for d in delayed)
            for dm, ms_v2, me_v2 in reversed(delayed):
                mc_v2 = min(mc_v2, ms_v2)
                dm.set_junction(min(ms_v2, mc_v2), mc_v2, min(me_v2, mc_v2))
        res = queue[:flush_count]
        del queue[:flush_count]
        return res

    def _process(self, lazy: bool = False) -> None:
        """``_process_lookahead``: flush and queue the finalized moves at the current print time."""
        moves = self._flush_queue(lazy)
        if not moves:
            return
        self.need_prime = False
        t = self.print_time
        out = self.out
        n = self.n_out
        for m in moves:
            out.append(PlannedMove(n, m.lineno, MOVE if m.is_kin else m.kind, t, m.start, m.end, m.move_d,
                                   m.axes_r, m.start_v, m.cruise_v, m.end_v, m.accel, m.accel_t, m.cruise_t,
                                   m.decel_t, m.quiet))
            n += 1
            t = t + m.accel_t + m.cruise_t + m.decel_t
        self.n_out = n
        if t > self.print_time:
            self.print_time = t

    def _flush_lookahead(self) -> None:
        self._process()
        self.need_prime = True
        self.junction_flush = BUFFER_TIME_HIGH

    def get_last_move_time(self) -> float:
        if self.need_prime:
            self._flush_lookahead()
        else:
            self._process()
        return self.print_time

    def dwell(self, delay_s: float, lineno: int) -> None:
        t0 = self.get_last_move_time()
        delay = max(0.0, delay_s)
        if delay > 0.0:
            p = tuple(self.commanded_pos)
            self.out.append(PlannedMove(self.n_out, lineno, DWELL, t0, p, p, 0.0, (0.0, 0.0, 0.0, 0.0),
                                        0.0, 0.0, 0.0, 0.0, 0.0, delay, 0.0))
            self.n_out += 1
        self.print_time = max(self.print_time, t0 + delay)

    def sync(self, reason: str, lineno: int) -> None:
        if reason in ("M84", "M18"):
            self.get_last_move_time()  # (the dwell's own flush, made first to report the rest)
            if self.on_stop is not None:
                self.on_stop(self.print_time, lineno)
            self.dwell(MOTOR_OFF_DWELL_S, lineno)
            self.get_last_move_time()
            self.dwell(MOTOR_OFF_DWELL_S, lineno)
        else:
            self._flush_lookahead()
            if self.on_stop is not None:
                self.on_stop(self.print_time, lineno)

    def stop(self, command: str, lineno: int) -> None:
        """A command that stops or moves the machine on its own: flush to rest first (as M400)."""
        self.sync("M400", lineno)
        self.stops += 1

    def home(self, position, lineno: int) -> None:
        self._flush_lookahead()
        self.commanded_pos = [position[0], position[1], position[2], self.commanded_pos[3]]
        self.kin.set_position()

    def finish(self) -> None:
        self._flush_lookahead()

    def take(self) -> list[PlannedMove]:
        out = self.out
        self.out = []
        return out
