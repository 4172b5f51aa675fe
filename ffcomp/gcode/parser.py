"""Streaming G-code parser: one :class:`~ffcomp.gcode.records.GcodeLine` per input line, in order.

The parser is Klipper's ``gcode_move`` layer: it keeps the modal state (absolute/relative XYZ and E,
G92 offsets, feed rate, M220 speed factor, M221 flow factor, arc plane, units) and turns every motion
line into machine-coordinate moves the planner executes.  It never holds more than one line: iterate a
file of any length in constant memory.

Dialects (``dialect=`` keyword, normally the profile's planner name) differ where the firmware do:

=================  =========================================  ======================================
behaviour          ``"klipper"``                              ``"marlin"``
=================  =========================================  ======================================
G90 / G91          XYZ only; in G91 E is relative whatever    also set E absolute / relative (a later
                   M82 says                                   M82 / M83 overrides, also in G91)
G20 (inches)       error (Klipper rejects it)                 inch mode
G2/G3 in G91       error (Klipper rejects it)                 relative target
G4                 ``P`` milliseconds (``S`` ignored)         ``S`` seconds, else ``P`` milliseconds
F <= 0             error ("Invalid speed")                    ignored
=================  =========================================  ======================================

Both accept G2/G3 in the I/J (I/K, J/K) and R forms and split arcs by Klipper's rule
(:mod:`ffcomp.gcode.arcs`, ``arc_resolution_mm`` keyword, 1 mm default).

A malformed motion/state line raises :class:`~ffcomp.errors.GcodeError` (path, line number, reason,
text).  With ``lenient=True`` it is counted as a warning instead, its state changes are discarded and
the line is marked skipped (``op=None``, ``error`` set; the compensated output comments it out).

Every other command is classified by :mod:`ffcomp.gcode.commands` (pass-through, stop, or an unknown
command that the ``unknown_policy`` decides); the counts per class are in :attr:`GcodeParser.counts`.

Guards against pathological input (each names the file and line): a feed rate below
:data:`MIN_FEED_MM_S`, a single move that would last longer than :data:`MAX_MOVE_S`, a dwell longer than
:data:`MAX_DWELL_S`, a line longer than :data:`MAX_LINE_CHARS`, and bytes that are not UTF-8 inside a
command (in comments and pass-through lines they are kept as they are: files are read with
``errors="surrogateescape"``, so writing with the same handler restores the bytes).  A UTF-8
byte-order mark at the start of the file is dropped.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from ..errors import GcodeError
from .arcs import arc_travel, offset_from_radius, plan_arc
from .commands import BAKED_STOPS, PASS, STATE, STOP, TABLE, UNKNOWN, UNKNOWN_POLICIES, classify
from .move_runs import RUN_LINE, RUN_MAX, to_run
from .records import (
    ArcMove,
    Dwell,
    FirmwareMove,
    GcodeLine,
    Home,
    LimitsChange,
    LinearMove,
    ModeChange,
    Stop,
    Sync,
)
from .words import classic_words, extended_params, lex, number

__all__ = ["Dialect", "DIALECTS", "GcodeParser", "parse_gcode", "parse_text", "MIN_FEED_MM_S", "MAX_SLOW_MOVE_S",
           "MAX_MOVE_S", "MAX_DWELL_S", "MAX_ARC_MM", "MAX_LINE_CHARS"]

#: slowest feed rate accepted for a move that lasts, mm/s (F6).  Slicers and start scripts never go
#: below about 1 mm/s (F60, slow probing or purging); F0.001 or F1 are typos or a mm/s-for-mm/min
#: mix-up, and at 1 kHz sampling they would make the compensation generate millions of samples for one
#: line.  ffcomp's own output holds the toolhead still with micrometre moves at lower feed rates for
#: fractions of a second, so the rule applies to moves lasting longer than :data:`MAX_SLOW_MOVE_S`.
MIN_FEED_MM_S = 0.1
#: a move slower than :data:`MIN_FEED_MM_S` is an error once it lasts longer than this, s
MAX_SLOW_MOVE_S = 10.0
#: longest single move accepted, s.  The slowest legitimate move, the full z travel of a tall delta
#: (~1 m) at a careful 5 mm/s, takes 200 s; 15 min leaves a margin of 4 and bounds one line's samples
#: (about 11 MB of temporary command file at 1 kHz).
MAX_MOVE_S = 900.0
#: longest single dwell accepted, s.  Heat soaks of up to an hour (``G4 S3600``) are real; longer
#: dwells belong in a macro (the compensation samples a dwell like a move: 1 h is ~43 MB and ~30 s of
#: processing).
MAX_DWELL_S = 3600.0
#: longest arc accepted, mm.  G2/G3 make at most one turn, and a full circle of 1 m radius (beyond any
#: delta's print radius) is 6.3 m; a longer arc comes from a bad centre or radius and would be split
#: into one chord per millimetre.
MAX_ARC_MM = 10000.0
#: longest line accepted, characters (real files stay under a few kB; a longer "line" is binary data
#: or a file without line breaks, and reading it whole would take unbounded memory).
MAX_LINE_CHARS = 1 << 20
#: below this requested speed a move's duration is checked against :data:`MAX_MOVE_S` (a faster move
#: cannot last that long inside a printer's workspace), mm/s
_SLOW_CHECK_MM_S = 10.0

_NUMCHARS = "0123456789.+-"
_PLANES = {"XY": (0, 1, 2, "IJ"), "XZ": (0, 2, 1, "IK"), "YZ": (1, 2, 0, "JK")}


def _dwell_klipper(p_ms, s_s):
    return (p_ms or 0.0) / 1000.0


def _dwell_marlin(p_ms, s_s):
    if s_s is not None:
        return s_s
    return (p_ms or 0.0) / 1000.0


@dataclass(frozen=True)
class Dialect:
    """How one firmware reads the modal G-code state (see the module docstring's table)."""

    name: str
    g90_sets_e_mode: bool
    g91_forces_relative_e: bool
    inches: bool
    relative_arcs: bool
    nonpositive_f_is_error: bool
    dwell_seconds: Callable


DIALECTS: dict[str, Dialect] = {
    "klipper": Dialect("klipper", g90_sets_e_mode=False, g91_forces_relative_e=True, inches=False,
                       relative_arcs=False, nonpositive_f_is_error=True, dwell_seconds=_dwell_klipper),
    "marlin": Dialect("marlin", g90_sets_e_mode=True, g91_forces_relative_e=False, inches=True,
                      relative_arcs=True, nonpositive_f_is_error=False, dwell_seconds=_dwell_marlin),
}


class _LineError(Exception):
    """Internal: a line cannot be executed (becomes GcodeError or a lenient warning)."""


def _fail(reason: str):
    raise _LineError(reason)


class GcodeParser:
    """Iterate G-code lines as :class:`GcodeLine` records.

    Parameters
    ----------
    lines : iterable of str
        Lines with or without their terminators (a text file opened with ``newline=""`` keeps them).
    path : str
        Name used in error messages.
    lenient : bool
        Count malformed lines as warnings (passed through) instead of raising.
    dialect : str
        ``"klipper"`` or ``"marlin"`` (:data:`DIALECTS`).
    arc_resolution_mm : float
        Klipper ``[gcode_arcs] resolution``: nominal chord length of split arcs.
    home_position_mm : (x, y, z)
        Where G28 leaves the nozzle (a delta homes to the top of the towers).
    start_position_mm : (x, y, z, e)
        Machine position before the first line (the machine is assumed homed).
    max_kept_warnings : int
        How many warning messages :attr:`warning_messages` keeps (all are counted).
    unknown_policy : str
        What an unknown macro or G code is (:data:`~ffcomp.gcode.commands.UNKNOWN_POLICIES`): ``"stop"``
        (a :class:`Stop`, with a warning), ``"pass"`` (passed through, with a warning) or ``"refuse"``
        (an error).
    firmware_retraction : FirmwareRetraction, optional
        The printer's Klipper ``[firmware_retraction]`` settings (:class:`ffcomp.profile.FirmwareRetraction`).
        With them (Klipper dialect), ``G10``/``G11`` are the extruder-only moves Klipper's
        ``firmware_retraction`` makes of them (``G1 E-<retract_length> F<retract_speed * 60>`` in ``G91``
        inside a saved G-code state, so the file's E coordinate does not change; the M220/M221 factors
        apply; a ``G10`` while retracted does nothing) and ``SET_RETRACTION`` changes the settings;
        without them they are stops.

    Attributes
    ----------
    lines_read : int
    warnings : int
    warning_messages : list of str
    counts : dict
        Commands seen per class: ``pass``, ``state``, ``stop`` (known stops), ``unknown`` (unknown
        commands, whatever the policy made of them), ``skipped`` (malformed lines skipped leniently);
        ``firmware_retraction``: the ``G10``/``G11`` lines (among ``pass``) timed as the extruder moves
        Klipper makes of them.
    first_motion_line, first_home_line : int or None
        Line numbers of the first move (G0-G3) and of the first G28.
    first_motion : LinearMove, ArcMove or None
        The first move (a linear move's end is where the file first sends the toolhead).
    """

    def __init__(
        self,
        lines: Iterable[str],
        *,
        path: str = "<gcode>",
        lenient: bool = False,
        dialect: str = "klipper",
        arc_resolution_mm: float = 1.0,
        home_position_mm: tuple = (0.0, 0.0, 0.0),
        start_position_mm: tuple = (0.0, 0.0, 0.0, 0.0),
        max_kept_warnings: int = 100,
        unknown_policy: str = "stop",
        firmware_retraction=None,
    ):
        if dialect not in DIALECTS:
            raise ValueError(f"unknown G-code dialect {dialect!r} (known: {', '.join(DIALECTS)})")
        if not arc_resolution_mm > 0:
            raise ValueError(f"arc_resolution_mm must be > 0, got {arc_resolution_mm}")
        if unknown_policy not in UNKNOWN_POLICIES:
            raise ValueError(f"unknown_policy must be one of {', '.join(UNKNOWN_POLICIES)}, got {unknown_policy!r}")
        self.unknown_policy = unknown_policy
        self.counts = {PASS: 0, STATE: 0, STOP: 0, UNKNOWN: 0, "skipped": 0, "firmware_retraction": 0, "sync": 0}
        self.first_motion_line: int | None = None
        self.first_home_line: int | None = None
        self.first_motion: LinearMove | ArcMove | None = None
        self._lines = lines
        self.path = str(path)
        self.lenient = lenient
        self.dialect = DIALECTS[dialect]
        self.arc_resolution_mm = float(arc_resolution_mm)
        self.home_position_mm = tuple(float(v) for v in home_position_mm)
        self.max_kept_warnings = max_kept_warnings
        self.lines_read = 0
        self.warnings = 0
        self.warning_messages: list[str] = []
        # modal state, as Klipper's gcode_move keeps it
        sp = [float(v) for v in start_position_mm]
        if len(sp) != 4:
            raise ValueError("start_position_mm must have 4 values (x, y, z, e)")
        self.last_position = sp
        self.base_position = [0.0, 0.0, 0.0, 0.0]
        self.homing_position = [0.0, 0.0, 0.0, 0.0]
        self.absolute_coord = True
        self.absolute_extrude = True
        self.speed = 25.0  # mm/s (Klipper's and Marlin's start-up feed rate, F1500)
        self.speed_factor = 1.0 / 60.0
        self.extrude_factor = 1.0
        self.unit = 1.0  # mm per G-code length unit (G20: 25.4)
        self.plane = "XY"
        self._handlers = {
            "G0": self._g0, "G1": self._g1, "G2": self._g2, "G3": self._g3, "G4": self._g4,
            "G17": self._g17, "G18": self._g18, "G19": self._g19, "G20": self._g20, "G21": self._g21,
            "G28": self._g28, "G90": self._g90, "G91": self._g91, "G92": self._g92,
            "M82": self._m82, "M83": self._m83, "M18": self._m84, "M84": self._m84, "M400": self._m400,
            "M201": self._m201, "M203": self._m203, "M204": self._m204, "M205": self._m205,
            "M220": self._m220, "M221": self._m221,
            "SET_VELOCITY_LIMIT": self._set_velocity_limit, "SET_GCODE_OFFSET": self._set_gcode_offset,
        }
        # Klipper's firmware_retraction: its settings (mm, mm/s) and whether the filament is retracted
        self.firmware_retraction = firmware_retraction if dialect == "klipper" else None
        self.is_retracted = False
        self.retraction_stops = 0  # G10/G11 lines planned as stops (no settings, or Marlin)
        if self.firmware_retraction is not None:
            fr = self.firmware_retraction
            self._retract = [fr.retract_length_mm, fr.retract_speed_mm_s, fr.unretract_extra_length_mm,
                             fr.unretract_speed_mm_s]
            self._handlers.update(G10=self._g10, G11=self._g11, SET_RETRACTION=self._set_retraction)

    # ------------------------------------------------------------------ iteration
    def __iter__(self) -> Iterator[GcodeLine]:
        return self._iter(False)

    def runs(self) -> Iterator:
        """Iterate as usual, except that consecutive plain ``G1 X Y Z [E] F`` lines come as one
        :class:`~ffcomp.gcode.move_runs.MoveRun` (arrays; the same positions and speeds as their
        records would carry)."""
        return self._iter(True)

    def _iter(self, runs: bool) -> Iterator:
        handlers = self._handlers
        lineno = 0
        match = RUN_LINE.match if runs else None
        run: list = []  # (line number, raw line, match) of the pending run
        raw = ""
        for raw in _without_bom(self._lines):
            lineno += 1
            self.lines_read = lineno
            if match is not None:
                m = match(raw)
                if m is not None and len(raw) <= MAX_LINE_CHARS:
                    run.append((lineno, raw, m))
                    if len(run) >= RUN_MAX:
                        yield from self._run_records(run)
                    continue
                if run:
                    yield from self._run_records(run)
            # fast path: plain "G1 ..." / "G0 ..." lines with no comment, checksum or compact words
            if len(raw) > MAX_LINE_CHARS:
                yield self._bad(lineno, raw[:200], "", f"line longer than {MAX_LINE_CHARS} characters: "
                                "not G-code")
                continue
            if raw[:3] in ("G1 ", "G0 ") and ";" not in raw and "(" not in raw:
                try:
                    op = self._move(raw[3:].split(), raw[1] == "0")
                except _LineError as e:
                    yield self._bad(lineno, raw, "G" + raw[1], str(e))
                    continue
                if self.first_motion_line is None:
                    self._first_motion(lineno, op)
                yield GcodeLine(lineno, raw, "G" + raw[1], op)
                continue
            text = raw.rstrip("\r\n")
            try:
                cmd, params = lex(text)
            except ValueError as e:
                yield self._bad(lineno, raw, "", str(e))
                continue
            h = handlers.get(cmd)
            if h is None:
                try:
                    op = self._other(cmd, lineno, text)
                except _LineError as e:
                    yield self._bad(lineno, raw, cmd, str(e))
                    continue
                yield GcodeLine(lineno, raw, cmd, op)
                continue
            snapshot = self._snapshot()
            try:
                op = h(params)
            except (_LineError, ValueError) as e:
                self._restore(snapshot)
                yield self._bad(lineno, raw, cmd, str(e))
                continue
            if TABLE.get(cmd) == STATE:
                self.counts[STATE] += 1
            elif self.first_motion_line is None and isinstance(op, (LinearMove, ArcMove)):
                self._first_motion(lineno, op)
            elif cmd == "G28" and self.first_home_line is None:
                self.first_home_line = lineno
            yield GcodeLine(lineno, raw, cmd, op)
        if run:
            yield from self._run_records(run)
        if raw and not raw.endswith("\n") and raw.split(";")[0].strip():
            self._warn(lineno, "the last line has no line end: the file may be truncated (a copy or an upload "
                       "cut short); its command runs as it reads", raw)

    def _run_records(self, run: list) -> Iterator:
        """The pending run (emptied) as one :class:`~ffcomp.gcode.move_runs.MoveRun`, or line by line
        where the arithmetic is not the plain case."""
        rows = run[:]
        run.clear()
        if self.absolute_coord and self.first_motion_line is not None:
            r = to_run(rows, self.last_position, self.base_position, self._e_relative(), self.extrude_factor,
                       self.unit, self.speed_factor)
            if self._slow_ok(r):
                self.last_position = [float(v) for v in r.ends[-1]]
                self.speed = float(r.speeds[-1])
                yield r
                return
        for lineno, raw, _ in rows:  # the fast path of _iter, line by line
            try:
                op = self._move(raw[3:].split(), False)
            except _LineError as e:
                yield self._bad(lineno, raw, "G1", str(e))
                continue
            if self.first_motion_line is None:
                self._first_motion(lineno, op)
            yield GcodeLine(lineno, raw, "G1", op)

    def _slow_ok(self, r) -> bool:
        """Whether every slow line of run ``r`` passes :meth:`_check_slow` (else the lines go one by one
        and the failing one raises)."""
        v = r.speeds
        slow = v < _SLOW_CHECK_MM_S
        if not slow.any():
            return True
        if float(v.min()) <= 0.0:
            return False
        prev = np.vstack([r.start, r.ends[:-1]])[slow]
        d = r.ends[slow] - prev
        dist = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)
        dist = np.where(dist > 0, dist, np.abs(d[:, 3]))
        t = dist / v[slow]
        return not bool(np.any(t > MAX_MOVE_S) or np.any((v[slow] < MIN_FEED_MM_S) & (t > MAX_SLOW_MOVE_S)))

    def _first_motion(self, lineno: int, op) -> None:
        if isinstance(op, ArcMove) or (isinstance(op, LinearMove) and op.start[:3] != op.end[:3]):
            self.first_motion_line = lineno
            self.first_motion = op

    def _other(self, cmd: str, lineno: int, text: str):
        """A command the parser does not execute: classified by :mod:`ffcomp.gcode.commands`."""
        if not cmd:
            return None
        cls = classify(cmd)
        if cls == PASS:
            self.counts[PASS] += 1
            return None
        if cls == STOP:
            self.counts[STOP] += 1
            if cmd in ("G10", "G11"):
                self._retraction_stop(lineno, text)
            return Stop(cmd, baked=cmd in BAKED_STOPS)
        # an unknown macro or G code: the policy decides
        if _has_undecodable(cmd):
            _fail("bytes that are not UTF-8 inside a command")
        if self.unknown_policy == "refuse":
            _fail(f"unknown command {cmd!r} (it may move the toolhead; --unknown-commands stop or pass "
                  "decides what to do with it)")
        self.counts[UNKNOWN] += 1
        policy = self.unknown_policy
        self._warn(lineno, f"unknown command {cmd!r} "
                   + ("treated as a stop (the toolhead comes to rest before it)" if policy == "stop"
                      else "passed through (it runs wherever the compensated motion is)"), text)
        return Stop(cmd, unknown=True) if policy == "stop" else None

    def _warn(self, lineno: int, reason: str, text: str) -> None:
        self.warnings += 1
        if len(self.warning_messages) < self.max_kept_warnings:
            self.warning_messages.append(f"{self.path}:{lineno}: {reason}: {_printable(text.strip())}")

    def _bad(self, lineno: int, raw: str, cmd: str, reason: str) -> GcodeLine:
        text = raw.rstrip("\r\n")
        if _has_undecodable(text) and "not UTF-8" not in reason:
            reason += " (the line holds bytes that are not UTF-8)"
        if not self.lenient:
            raise GcodeError(self.path, lineno, reason, _printable(text)) from None
        self.counts["skipped"] += 1
        self._warn(lineno, reason + " (skipped)", text)
        return GcodeLine(lineno, raw, cmd, None, reason)

    def _snapshot(self):
        return (list(self.last_position), list(self.base_position), list(self.homing_position),
                self.absolute_coord, self.absolute_extrude, self.speed, self.speed_factor,
                self.extrude_factor, self.unit, self.plane)

    def _restore(self, s) -> None:
        (self.last_position, self.base_position, self.homing_position, self.absolute_coord,
         self.absolute_extrude, self.speed, self.speed_factor, self.extrude_factor, self.unit,
         self.plane) = s

    # ------------------------------------------------------------------ helpers
    def _words(self, params, allowed: str, *, what: str) -> dict[str, float | None]:
        """Parse classic words; letters outside ``allowed`` are an error; empty values give None."""
        out: dict[str, float | None] = {}
        try:
            for letter, val in classic_words(params):
                if letter not in allowed:
                    _fail(f"unknown parameter '{letter}' for {what}")
                out[letter] = number(letter, val) if val else None
        except ValueError as e:
            _fail(str(e))
        for k, v in out.items():
            if v is not None and not math.isfinite(v):
                _fail(f"non-finite value for {k}")
        return out

    def _need(self, w: dict, letter: str, what: str) -> float | None:
        if letter not in w:
            return None
        v = w[letter]
        if v is None:
            _fail(f"missing value for {letter} in {what}")
        return v

    def _set_speed(self, f: float) -> None:
        if f <= 0.0:
            if self.dialect.nonpositive_f_is_error:
                _fail(f"invalid speed F{f:g}")
            return
        self.speed = f * self.unit * self.speed_factor

    def _e_relative(self) -> bool:
        """Whether E words are relative: Klipper also in G91; Marlin as M82/M83 (or G90/G91) last said."""
        if not self.absolute_extrude:
            return True
        return not self.absolute_coord and self.dialect.g91_forces_relative_e

    # ------------------------------------------------------------------ motion
    def _move(self, tokens, rapid: bool):
        """G0/G1 (hot path).  Mutates state only after the whole line parsed."""
        vx = vy = vz = ve = vf = None
        for t in tokens:
            c = t[0]
            v = t[1:]
            if not v or v.strip(_NUMCHARS):
                return self._move_slow(tokens, rapid)
            try:
                val = float(v)
            except ValueError:
                _fail(f"bad number {t!r}")
            if val - val != 0.0:
                _fail(f"non-finite value {t!r}")
            if c == "X":
                vx = val
            elif c == "Y":
                vy = val
            elif c == "E":
                ve = val
            elif c == "F":
                vf = val
            elif c == "Z":
                vz = val
            elif "a" <= c <= "z":
                return self._move_slow(tokens, rapid)
            else:
                _fail(f"unknown axis letter '{c}' in {t!r} (G0/G1 take X, Y, Z, E, F)")
        return self._apply_move(vx, vy, vz, ve, vf, rapid)

    def _move_slow(self, tokens, rapid: bool):
        try:
            words = classic_words([t.upper() for t in tokens])
        except ValueError as e:
            _fail(str(e))
        vals: dict[str, float] = {}
        for letter, val in words:
            if letter not in "XYZEF":
                _fail(f"unknown axis letter '{letter}' (G0/G1 take X, Y, Z, E, F)")
            try:
                vals[letter] = number(letter, val)
            except ValueError as e:
                _fail(str(e))
            if not math.isfinite(vals[letter]):
                _fail(f"non-finite value for {letter}")
        return self._apply_move(vals.get("X"), vals.get("Y"), vals.get("Z"), vals.get("E"),
                                vals.get("F"), rapid)

    def _apply_move(self, vx, vy, vz, ve, vf, rapid: bool):
        """Klipper's ``cmd_G1`` arithmetic (values finite, in G-code units)."""
        lp = self.last_position
        x0, y0, z0, e0 = lp
        x, y, z, e = lp
        u = self.unit
        if u != 1.0:
            vx = None if vx is None else vx * u
            vy = None if vy is None else vy * u
            vz = None if vz is None else vz * u
            ve = None if ve is None else ve * u
        bp = self.base_position
        if self.absolute_coord:
            if vx is not None:
                x = vx + bp[0]
            if vy is not None:
                y = vy + bp[1]
            if vz is not None:
                z = vz + bp[2]
        else:
            if vx is not None:
                x += vx
            if vy is not None:
                y += vy
            if vz is not None:
                z += vz
        if ve is not None:
            v = ve * self.extrude_factor
            if self._e_relative():
                e += v
            else:
                e = v + bp[3]
        old_speed = self.speed
        if vf is not None:
            self._set_speed(vf)
        if vx is None and vy is None and vz is None and ve is None:
            self.last_position = [x, y, z, e]
            return ModeChange("feedrate_mm_s", self.speed)
        if self.speed < _SLOW_CHECK_MM_S:
            d = math.sqrt((x - x0) ** 2 + (y - y0) ** 2 + (z - z0) ** 2) or abs(e - e0)
            try:
                self._check_slow(d)
            except _LineError:
                self.speed = old_speed  # a refused line changes no state
                raise
        self.last_position = [x, y, z, e]
        return LinearMove((x0, y0, z0, e0), (x, y, z, e), self.speed, rapid)

    def _check_slow(self, distance_mm: float) -> None:
        """Guards of a move of ``distance_mm`` at the current (slow) speed."""
        if distance_mm <= 0.0:
            return
        v = self.speed
        if v < MIN_FEED_MM_S and distance_mm / v > MAX_SLOW_MOVE_S:
            _fail(f"feed rate {v * 60:.4g} mm/min ({v:.3g} mm/s) is below the minimum "
                  f"{MIN_FEED_MM_S * 60:g} mm/min ({MIN_FEED_MM_S:g} mm/s) for a {distance_mm:.4g} mm move: "
                  "no printer moves this slowly (a typo, or mm/s written where G-code wants mm/min?)")
        if distance_mm / v > MAX_MOVE_S:
            _fail(f"this move would last at least {distance_mm / v:.0f} s ({distance_mm:.4g} mm at "
                  f"{v * 60:.4g} mm/min), longer than the {MAX_MOVE_S:g} s allowed for one move")

    def _g0(self, params):
        return self._move(params, True)

    def _g1(self, params):
        return self._move(params, False)

    def _g2(self, params):
        return self._arc(params, True)

    def _g3(self, params):
        return self._arc(params, False)

    def _gcode_position(self) -> list[float]:
        lp, bp = self.last_position, self.base_position
        p = [lp[i] - bp[i] for i in range(4)]
        p[3] /= self.extrude_factor
        return p

    def _chord(self, p, e_val, e_relative: bool) -> LinearMove:
        """One arc chord: a G1 to absolute G-code coordinates ``p`` (what Klipper issues)."""
        lp = self.last_position
        bp = self.base_position
        start = (lp[0], lp[1], lp[2], lp[3])
        new = [p[0] + bp[0], p[1] + bp[1], p[2] + bp[2], lp[3]]
        if e_val is not None:
            v = e_val * self.extrude_factor
            new[3] = lp[3] + v if e_relative else v + bp[3]
        self.last_position = new
        return LinearMove(start, (new[0], new[1], new[2], new[3]), self.speed, False)

    def _arc(self, params, clockwise: bool):
        w = self._words(params, "XYZEFIJKR", what="G2/G3")
        for k in w:
            self._need(w, k, "G2/G3")
        u = self.unit
        if not self.absolute_coord and not self.dialect.relative_arcs:
            _fail("G2/G3 does not support relative move mode")
        cur = self._gcode_position()
        target = list(cur[:3])
        for i, ax in enumerate("XYZ"):
            if ax in w:
                target[i] = w[ax] * u + (0.0 if self.absolute_coord else cur[i])
        a, b, h, ij = _PLANES[self.plane]
        if "R" in w and not (w.get(ij[0]) or w.get(ij[1])):
            try:
                off = offset_from_radius((cur[a], cur[b]), (target[a], target[b]), w["R"] * u, clockwise)
            except ValueError as e:
                _fail(str(e))
        else:
            off = (w.get(ij[0], 0.0) * u, w.get(ij[1], 0.0) * u)
            if not (off[0] or off[1]):
                _fail(f"G2/G3 needs a centre offset {ij[0]}/{ij[1]} or a radius R")
        length = arc_travel(cur, target, off, clockwise, (a, b, h))[2]
        if not length <= MAX_ARC_MM:
            _fail(f"arc of {length:.4g} mm is longer than the {MAX_ARC_MM:g} mm allowed (a wrong centre or "
                  "radius?)")
        points, center, radius, angle = plan_arc(cur, target, off, clockwise, (a, b, h),
                                                 self.arc_resolution_mm)
        e_absolute = not self._e_relative()
        e_per_move = e_base = 0.0
        if "E" in w:
            if e_absolute:
                e_base = cur[3]
            e_per_move = (w["E"] * u - e_base) / len(points)
        if "F" in w:
            self._set_speed(w["F"])
        if self.speed < _SLOW_CHECK_MM_S:
            self._check_slow(abs(angle) * radius + abs(target[h] - cur[h]))
        segs = []
        for p in points:
            ve = None
            if e_per_move:
                ve = e_base + e_per_move
                if e_absolute:
                    e_base += e_per_move
            segs.append(self._chord(p, ve, not e_absolute))
        bp = self.base_position
        return ArcMove(tuple(segs), clockwise, (center[0] + bp[a], center[1] + bp[b]), radius, angle,
                       self.plane)

    # ------------------------------------------------------------------ other G codes
    def _g4(self, params):
        w = self._words(params, "PS", what="G4")
        p = self._need(w, "P", "G4")
        s = self._need(w, "S", "G4")
        if (p is not None and p < 0) or (s is not None and s < 0):
            _fail("negative dwell time")
        t = float(self.dialect.dwell_seconds(p, s))
        if t > MAX_DWELL_S:
            _fail(f"dwell of {t:.0f} s is longer than the {MAX_DWELL_S:g} s allowed (put long waits in a "
                  "macro: the compensation samples a dwell like a move)")
        return Dwell(t)

    def _g17(self, params):
        self.plane = "XY"
        return ModeChange("plane", "XY")

    def _g18(self, params):
        self.plane = "XZ"
        return ModeChange("plane", "XZ")

    def _g19(self, params):
        self.plane = "YZ"
        return ModeChange("plane", "YZ")

    def _g20(self, params):
        if not self.dialect.inches:
            _fail("Machine does not support G20 (inches) command")
        self.unit = 25.4
        return ModeChange("units_mm_per_unit", 25.4)

    def _g21(self, params):
        self.unit = 1.0
        return ModeChange("units_mm_per_unit", 1.0)

    def _g28(self, params):
        # a delta homes all towers whatever axes G28 names; its parameters are not checked
        hp = self.home_position_mm
        lp = self.last_position
        self.last_position = [hp[0], hp[1], hp[2], lp[3]]
        for i in range(3):
            self.base_position[i] = self.homing_position[i]
        return Home((hp[0], hp[1], hp[2], lp[3]))

    def _g90(self, params):
        self.absolute_coord = True
        if self.dialect.g90_sets_e_mode:
            self.absolute_extrude = True
        return ModeChange("absolute_coord", True)

    def _g91(self, params):
        self.absolute_coord = False
        if self.dialect.g90_sets_e_mode:
            self.absolute_extrude = False
        return ModeChange("absolute_coord", False)

    def _g92(self, params):
        w = self._words(params, "XYZE", what="G92")
        offsets = [self._need(w, a, "G92") for a in "XYZE"]
        if all(v is None for v in offsets):
            self.base_position = list(self.last_position)
        else:
            for i, off in enumerate(offsets):
                if off is None:
                    continue
                off *= self.unit
                if i == 3:
                    off *= self.extrude_factor
                self.base_position[i] = self.last_position[i] - off
        return ModeChange("set_position", tuple(offsets))

    # ------------------------------------------------------------------ M codes
    def _m82(self, params):
        self.absolute_extrude = True
        return ModeChange("absolute_extrude", True)

    def _m83(self, params):
        self.absolute_extrude = False
        return ModeChange("absolute_extrude", False)

    def _m84(self, params):
        self.counts["sync"] += 1
        return Sync("M84")

    def _m400(self, params):
        self.counts["sync"] += 1
        return Sync("M400")

    def _m220(self, params):
        w = self._words(params, "SBRT", what="M220")
        s = self._need(w, "S", "M220")
        if s is None:
            s = 100.0
        if s <= 0:
            _fail("M220 S must be above 0")
        value = s / (60.0 * 100.0)
        self.speed = (self.speed / self.speed_factor) * value
        self.speed_factor = value
        return ModeChange("speed_factor", s)

    def _m221(self, params):
        w = self._words(params, "SDT", what="M221")
        s = self._need(w, "S", "M221")
        if s is None:
            s = 100.0
        if s <= 0:
            _fail("M221 S must be above 0")
        new = s / 100.0
        last_e = self.last_position[3]
        e_value = (last_e - self.base_position[3]) / self.extrude_factor
        self.base_position[3] = last_e - e_value * new
        self.extrude_factor = new
        return ModeChange("extrude_factor", s)

    def _positive(self, w: dict, letter: str, what: str):
        v = self._need(w, letter, what)
        if v is not None and v <= 0:
            _fail(f"{what} {letter} must be above 0")
        return v

    def _m204(self, params):
        w = self._words(params, "SPTR", what="M204")
        return LimitsChange("M204", accel_mm_s2=self._positive(w, "S", "M204"),
                            print_accel_mm_s2=self._positive(w, "P", "M204"),
                            travel_accel_mm_s2=self._positive(w, "T", "M204"),
                            retract_accel_mm_s2=self._positive(w, "R", "M204"))

    def _axes4(self, w: dict, what: str):
        vals = tuple(self._positive(w, a, what) for a in "XYZE")
        return vals if any(v is not None for v in vals) else None

    def _m201(self, params):
        w = self._words(params, "XYZET", what="M201")
        return LimitsChange("M201", max_accel_axes_mm_s2=self._axes4(w, "M201"))

    def _m203(self, params):
        w = self._words(params, "XYZET", what="M203")
        return LimitsChange("M203", max_feedrate_axes_mm_s=self._axes4(w, "M203"))

    def _m205(self, params):
        w = self._words(params, "XYZEJSTB", what="M205")
        jerk = tuple(self._need(w, a, "M205") for a in "XYZE")
        b = self._need(w, "B", "M205")
        j = self._need(w, "J", "M205")
        if j is not None and j <= 0:
            _fail("M205 J must be above 0")
        return LimitsChange("M205", junction_deviation_mm=j,
                            jerk_mm_s=jerk if any(v is not None for v in jerk) else None,
                            min_feedrate_mm_s=self._need(w, "S", "M205"),
                            min_travel_feedrate_mm_s=self._need(w, "T", "M205"),
                            min_segment_time_s=None if b is None else b * 1e-6)

    # ------------------------------------------------------------------ Klipper extended commands
    def _ext(self, params, allowed: tuple, what: str) -> dict[str, float]:
        try:
            p = extended_params(params)
        except ValueError as e:
            _fail(str(e))
        out = {}
        for k, v in p.items():
            if k not in allowed:
                _fail(f"unknown parameter '{k}' for {what}")
            try:
                x = float(v)
            except ValueError:
                _fail(f"bad number {k}={v!r}")
            if not math.isfinite(x):
                _fail(f"non-finite value for {k}")
            out[k] = x
        return out

    def _set_velocity_limit(self, params):
        p = self._ext(params, ("VELOCITY", "ACCEL", "SQUARE_CORNER_VELOCITY", "MINIMUM_CRUISE_RATIO",
                               "ACCEL_TO_DECEL"), "SET_VELOCITY_LIMIT")
        for k in ("VELOCITY", "ACCEL", "ACCEL_TO_DECEL"):
            if k in p and p[k] <= 0:
                _fail(f"SET_VELOCITY_LIMIT {k} must be above 0")
        if p.get("SQUARE_CORNER_VELOCITY", 0.0) < 0:
            _fail("SET_VELOCITY_LIMIT SQUARE_CORNER_VELOCITY must be >= 0")
        mcr = p.get("MINIMUM_CRUISE_RATIO")
        if mcr is not None and not (0.0 <= mcr < 1.0):
            _fail("SET_VELOCITY_LIMIT MINIMUM_CRUISE_RATIO must be in [0, 1)")
        return LimitsChange("SET_VELOCITY_LIMIT", velocity_mm_s=p.get("VELOCITY"), accel_mm_s2=p.get("ACCEL"),
                            accel_to_decel_mm_s2=p.get("ACCEL_TO_DECEL"),
                            square_corner_velocity_mm_s=p.get("SQUARE_CORNER_VELOCITY"),
                            minimum_cruise_ratio=mcr)

    # ------------------------------------------------------------------ firmware retraction (Klipper)
    def _g10(self, params):
        return self._fw_retract(True)

    def _g11(self, params):
        return self._fw_retract(False)

    def _fw_retract(self, retract: bool):
        """``cmd_G10`` / ``cmd_G11`` of Klipper's ``firmware_retraction``: ``SAVE_GCODE_STATE``, ``G91``,
        ``G1 E<+-length> F<int(speed * 60)>``, ``RESTORE_GCODE_STATE`` (which moves the E base by the
        same amount, so the file's E coordinate stays)."""
        self.counts[PASS] += 1
        if retract == self.is_retracted:
            return None  # Klipper does nothing
        self.is_retracted = retract
        length, speed, extra, unspeed = self._retract
        # Klipper's "G1 E%.5f F%d": the M221 factor scales E, the M220 factor the feed (G20 is not Klipper)
        de = (-round(length, 5) if retract else round(length + extra, 5)) * self.extrude_factor
        feed = int((speed if retract else unspeed) * 60.0)
        if de == 0.0:
            return None  # a zero-length move: Klipper's toolhead skips it
        self.counts["firmware_retraction"] += 1
        x, y, z, e0 = self.last_position
        e1 = e0 + de
        self.last_position = [x, y, z, e1]
        self.base_position[3] += de
        return FirmwareMove((x, y, z, e0), (x, y, z, e1), feed * self.speed_factor, self.speed_factor * 6000.0,
                            self.extrude_factor * 100.0)

    def _retraction_stop(self, lineno: int, text: str) -> None:
        """Count a G10/G11 planned as a stop; the first one is a warning that says what it costs."""
        self.retraction_stops += 1
        if self.retraction_stops > 1:
            return
        why = ("the profile has no [firmware_retraction] section" if self.dialect.name == "klipper"
               else "ffcomp times G10/G11 only for Klipper")
        self._warn(lineno, f"firmware retraction planned as a stop ({why}): at every G10/G11 the compensation "
                   "comes to rest and starts again, and the nozzle stands still for the inverse's settle and "
                   "pre-roll (0.35 s by default) besides the retraction itself; give the profile your "
                   "printer.cfg's [firmware_retraction] values to time G10/G11 as the extruder moves Klipper "
                   "makes of them", text)

    def _set_retraction(self, params):
        keys = ("RETRACT_LENGTH", "RETRACT_SPEED", "UNRETRACT_EXTRA_LENGTH", "UNRETRACT_SPEED")
        p = self._ext(params, keys, "SET_RETRACTION")
        for i, k in enumerate(keys):
            if k in p:
                lo = 1.0 if k.endswith("SPEED") else 0.0
                if p[k] < lo:
                    _fail(f"SET_RETRACTION {k} must be >= {lo:g}")
                self._retract[i] = p[k]
        self.is_retracted = False
        self.counts[PASS] += 1
        return None

    def _set_gcode_offset(self, params):
        keys = ("X", "Y", "Z", "E", "X_ADJUST", "Y_ADJUST", "Z_ADJUST", "E_ADJUST")
        try:
            raw = extended_params(params)
        except ValueError as e:
            _fail(str(e))
        if raw.get("MOVE", "0") not in ("0", ""):
            _fail("SET_GCODE_OFFSET MOVE=1 is not supported")
        raw.pop("MOVE", None)
        raw.pop("MOVE_SPEED", None)
        p = self._ext(" ".join(f"{k}={v}" for k, v in raw.items()), keys, "SET_GCODE_OFFSET")
        for i, ax in enumerate("XYZE"):
            off = p.get(ax)
            if off is None:
                adj = p.get(ax + "_ADJUST")
                if adj is None:
                    continue
                off = adj + self.homing_position[i]
            delta = off - self.homing_position[i]
            self.base_position[i] += delta
            self.homing_position[i] = off
        return ModeChange("gcode_offset", tuple(self.homing_position))


def _without_bom(lines: Iterable[str]) -> Iterator[str]:
    """``lines`` without a UTF-8 byte-order mark at the start of the first: it marks the encoding, and a
    firmware would read it as part of the first command (``\ufeffG28`` is no G28)."""
    it = iter(lines)
    first = next(it, None)
    if first is None:
        return
    yield first[1:] if first.startswith("\ufeff") else first
    yield from it


def _has_undecodable(text: str) -> bool:
    """Whether ``text`` (read with ``errors="surrogateescape"``) holds bytes that were not UTF-8."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return True
    return False


def _printable(text: str) -> str:
    """``text`` with undecodable bytes shown as ``\\xNN`` (safe to print anywhere)."""
    if not _has_undecodable(text):
        return text
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def _open_lines(path: Path) -> Iterator[str]:
    """Lines of a file, terminators kept, undecodable bytes as surrogates; a line longer than
    :data:`MAX_LINE_CHARS` comes in pieces (the parser rejects the first), so memory stays bounded."""
    limit = MAX_LINE_CHARS + 1
    with open(path, encoding="utf-8", errors="surrogateescape", newline="") as f:
        readline = f.readline
        while line := readline(limit):
            yield line
            if len(line) == limit and not line.endswith(("\n", "\r")):  # drop the rest of a long line
                while True:
                    rest = readline(limit)
                    if not rest or rest.endswith(("\n", "\r")):
                        break


def parse_gcode(source, **kw) -> GcodeParser:
    """A :class:`GcodeParser` over a file path or an iterable of lines (see its keywords).

    A ``str`` or ``PathLike`` is a file name (read lazily, line terminators kept); anything else is
    iterated as lines.
    """
    if isinstance(source, (str, os.PathLike)):
        kw.setdefault("path", str(source))
        return GcodeParser(_open_lines(Path(source)), **kw)
    return GcodeParser(source, **kw)


def parse_text(text: str, **kw) -> list[GcodeLine]:
    """Parse G-code held in a string (convenience for tests and small snippets)."""
    kw.setdefault("path", "<string>")
    return list(GcodeParser(text.splitlines(keepends=True), **kw))
