"""Compensated G-code writer.

Input: the source file's lines (re-parsed, so every line keeps its number and meaning) and, in
time order, compensated samples with the reference's extruder position and the planned move each
sample belongs to.  Output: the source with every XYZ motion line replaced by G1 segments through
the compensated nozzle positions, and every other line kept in place.

* Points are placed adaptively: a segment ends where linear interpolation *in time* (the firmware
  moves a segment at constant speed) would stray from the compensated samples by more than
  ``tol_mm``; feed rates are length / duration, so timing follows the compensated command.
* Extrusion follows the reference timing: each segment extrudes ``e_ref(t_end) - e_ref(t_start)``
  (relative extrusion, rounding carried over), so material is laid when the original lays it.
* Lines whose meaning the compensation has baked in are commented out with ``; ffcomp:``:
  coordinate and extrusion modes (the output is G90 + M83 throughout), G92 and gcode offsets (the
  output is in machine coordinates), speed and flow factors, and motion-limit commands (the header
  sets the limits the compensated file needs).
* Extruder-only moves become ``G1 E.. F..`` with the planned speed; dwells, homing, temperatures,
  fans, comments and object labels pass through verbatim.
"""

from __future__ import annotations

from array import array
from dataclasses import dataclass, field
from typing import IO, Iterator

import numpy as np

from .moves import DWELL, EXTRUDE, MOVE, PlannedMove
from .records import ArcMove, GcodeLine, LimitsChange, LinearMove, ModeChange

__all__ = ["WriterStats", "GcodeWriter", "adaptive_breakpoints", "BAKED_MODES"]

#: ModeChange names whose effect is baked into the output (the line is commented out)
BAKED_MODES = {"absolute_coord", "absolute_extrude", "set_position", "gcode_offset", "speed_factor",
               "extrude_factor", "units_mm_per_unit", "plane", "feedrate_mm_s"}


def adaptive_breakpoints(P: np.ndarray, tol: float) -> np.ndarray:
    """Indices (including 0 and len-1) such that time-linear interpolation between consecutive
    breakpoints stays within ``tol`` of every point of ``P`` (shape (n, d)); Douglas-Peucker in time."""
    n = len(P)
    if n <= 2:
        return np.arange(n)
    keep = np.zeros(n, bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        f = (np.arange(i + 1, j) - i) / (j - i)
        lerp = P[i] + f[:, None] * (P[j] - P[i])
        d = np.max(np.abs(P[i + 1:j] - lerp), axis=1)
        k = int(np.argmax(d))
        if d[k] > tol:
            mid = i + 1 + k
            keep[mid] = True
            stack.append((i, mid))
            stack.append((mid, j))
    return np.nonzero(keep)[0]


@dataclass
class WriterStats:
    """What the writer did (for the closing summary)."""

    segments: int = 0
    motion_lines_replaced: int = 0
    lines_passed: int = 0
    lines_commented: int = 0
    extrude_moves: int = 0
    holds: int = 0
    peak_speed_mm_s: float = 0.0
    peak_accel_mm_s2: float = 0.0
    extruded_mm: float = 0.0
    notes: list = field(default_factory=list)


class GcodeWriter:
    """Streams the compensated body of a G-code file.

    Parameters
    ----------
    lines : iterator of GcodeLine
        The source, parsed (every line, in order).
    out : text file
        Where the body goes.
    dt_s : float
        Sample time of the compensated samples.
    tol_mm : float
        Point placement tolerance.
    moves : dict
        ``move index -> PlannedMove`` (filled by the planner as it goes; entries are dropped here).
    """

    def __init__(self, lines: Iterator[GcodeLine], out: IO[str], dt_s: float, tol_mm: float,
                 moves: dict[int, PlannedMove], accel_mm_s2: float = float("inf"),
                 max_z_accel_mm_s2: float = float("inf"), max_z_velocity_mm_s: float = float("inf")):
        self.lines, self.out, self.dt, self.tol = lines, out, dt_s, tol_mm
        self.accel, self.max_z_accel, self.max_z_v = accel_mm_s2, max_z_accel_mm_s2, max_z_velocity_mm_s
        self.f_last = 0.0  # feed rate (mm/s) of the last segment written: the next junction speed
        self.moves = moves
        self.stats = WriterStats()
        self.next_line: GcodeLine | None = None
        self.emitted_upto = 0  # source lines with lineno <= this are written
        self.last_pt: np.ndarray | None = None  # last emitted nozzle point (mm)
        self.last_k = None  # sample index of it
        self.e_emitted = 0.0  # extrusion written so far (relative sum), mm
        self.e_ref_cum = 0.0  # reference extrusion accounted for so far, mm
        self.e_last_ref = None  # reference extruder position at the last emitted point
        self.replaced: set[int] = set()  # source line numbers written as motion
        self.done_moves: set[int] = set()  # planned move indices written
        self.prev_v = None
        self.after_hold = False
        self.nlines = 0  # body lines written
        #: (body line number, first sample, last sample, catch-up flag) of every XYZ segment (self-check)
        self.segments = array("q")
        self._write = out.write

    def _w(self, text: str) -> None:
        self._write(text)
        self.nlines += 1

    # ------------------------------------------------------------------ source lines
    def _line_iter_next(self) -> GcodeLine | None:
        if self.next_line is None:
            self.next_line = next(self.lines, None)
        return self.next_line

    def flush_lines(self, upto: int) -> None:
        """Write the source lines numbered < ``upto`` that are not motion lines."""
        w = self._w
        while True:
            ln = self._line_iter_next()
            if ln is None or ln.lineno >= upto:
                return
            self.next_line = None
            op = ln.op
            raw = ln.raw if ln.raw.endswith("\n") else ln.raw + "\n"
            if isinstance(op, (LinearMove, ArcMove)):
                if ln.lineno not in self.replaced:  # produced no planned motion (zero length)
                    w("; ffcomp (no motion): " + raw)
                continue
            if isinstance(op, LimitsChange) or (isinstance(op, ModeChange) and op.name in BAKED_MODES):
                w("; ffcomp (baked in): " + raw)
                self.stats.lines_commented += 1
                continue
            if op is not None and type(op).__name__ == "Dwell":
                continue  # written with its planned move, in time order
            w(raw)
            self.stats.lines_passed += 1

    # ------------------------------------------------------------------ samples
    def feed(self, k0: int, xyz_mm: np.ndarray, e_mm: np.ndarray, move_index: np.ndarray,
             lineno: np.ndarray) -> None:
        """Compensated nozzle positions of samples ``k0 ..`` with their reference extrusion and move."""
        n = len(xyz_mm)
        if n == 0:
            return
        if self.last_pt is None:
            self.last_pt, self.last_k, self.e_last_ref = xyz_mm[0].copy(), k0, float(e_mm[0])
        # split into runs of one planned move
        cut = np.nonzero(np.diff(move_index))[0] + 1
        bounds = np.concatenate([[0], cut, [n]])
        for a, b in zip(bounds[:-1], bounds[1:]):
            mi = int(move_index[a])
            mv = self.moves.get(mi)
            kind = mv.kind if mv is not None else MOVE
            ln = int(lineno[a])
            self.flush_lines(ln)
            if kind == MOVE:
                self._motion(k0 + a, xyz_mm[a:b], e_mm[a:b])
            elif kind == EXTRUDE:
                if mv.index not in self.done_moves:
                    self._extrude(mv)
                self._hold(k0 + b - 1, e_mm[b - 1])
            elif kind == DWELL:
                if mv.index not in self.done_moves:
                    self._dwell(mv, ln)
                self._hold(k0 + b - 1, e_mm[b - 1])
            if mv is not None:
                self.done_moves.add(mv.index)
            self.replaced.add(ln)
            self.stats.motion_lines_replaced = len(self.replaced)
            for old in [k for k in self.moves if k < mi - 2]:
                del self.moves[old]
            if len(self.done_moves) > 64:
                self.done_moves = {k for k in self.done_moves if k >= mi - 2}

    def _hold(self, k_end: int, e_ref_end: float) -> None:
        self.f_last = 0.0  # the firmware stops for extruder-only moves and dwells
        self.last_k = k_end
        self.e_last_ref = e_ref_end
        self.after_hold = True

    def _extrude(self, mv: PlannedMove) -> None:
        de = mv.end_mm[3] - mv.start_mm[3]
        speed = max(mv.cruise_v_mm_s, 1e-3)
        self.e_ref_cum += de
        de_w = round(self.e_ref_cum - self.e_emitted, 5)
        self._w(f"G1 E{de_w:.5f} F{speed * 60:.1f}\n")
        self.e_emitted += de_w
        self.stats.extrude_moves += 1

    def _dwell(self, mv: PlannedMove, lineno: int) -> None:
        self._w(f"G4 P{mv.cruise_t_s * 1000:.0f}\n")

    def _motion(self, k_start: int, P: np.ndarray, E: np.ndarray) -> None:
        # path from the last emitted point through this run's samples
        pts = np.vstack([self.last_pt[None], P])
        es = np.concatenate([[self.e_last_ref], E])
        ks = np.concatenate([[self.last_k], np.arange(k_start, k_start + len(P))])
        # samples are consecutive except possibly the jump from last_k (after a hold)
        catch_up = self.after_hold and len(pts) > 2
        if catch_up:
            # the command moved on while the planned nozzle stood still (retraction, dwell): catch up
            # in one sample's time instead of stretching the next segment
            idx = np.concatenate([[0], 1 + adaptive_breakpoints(pts[1:], self.tol)])
        else:
            idx = adaptive_breakpoints(pts, self.tol)
        self.after_hold = False
        i, j = idx[:-1], idx[1:]
        dt = (ks[j] - ks[i]) * self.dt
        ok = dt > 0
        i, j, dt = i[ok], j[ok], dt[ok]
        if len(i):
            # the firmware sees the printed (rounded) coordinates: durations must come from those
            pts = np.round(pts, 4)
            d = pts[j] - pts[i]
            dist = np.sqrt(np.einsum("ij,ij->i", d, d))
            # extrusion: the emitted total is the reference total rounded to 0.01 um, so the
            # rounding never accumulates (each line gets the difference of consecutive rounded totals)
            cum = self.e_ref_cum + np.cumsum(es[j] - es[i])
            tot = np.round(cum, 5)
            de = np.diff(np.concatenate([[self.e_emitted], tot]))
            self.e_ref_cum = float(cum[-1])
            self.e_emitted = float(tot[-1])
            hold = dist < 1e-3  # under a micrometre: the firmware would crawl; hold instead
            v = self._firmware_feeds(d, dist, dt, hold)
            lines = []
            seg_rows = []
            n0 = self.nlines
            for r in range(len(i)):
                if hold[r]:
                    if abs(de[r]) > 1e-9:
                        lines.append(f"G1 E{de[r]:.5f} F{max(abs(de[r]) / dt[r], 1e-3) * 60:.1f}\n")
                    else:
                        lines.append(f"G4 P{dt[r] * 1000:.0f}\n")
                    continue
                x, y, z = pts[j[r]]
                if abs(de[r]) > 1e-9:
                    lines.append(f"G1 X{x:.4f} Y{y:.4f} Z{z:.4f} E{de[r]:.5f} F{v[r] * 60:.3f}\n")
                else:
                    lines.append(f"G1 X{x:.4f} Y{y:.4f} Z{z:.4f} F{v[r] * 60:.3f}\n")
                seg_rows.append((n0 + len(lines), int(ks[i[r]]), int(ks[j[r]]), int(catch_up and i[r] == 0)))
            self._write("".join(lines))
            self.nlines += len(lines)
            for row in seg_rows:
                self.segments.extend(row)
            self.stats.holds += int(hold.sum())
            self.stats.segments += int((~hold).sum())
            self.stats.extruded_mm += float(np.sum(np.maximum(de[~hold], 0.0)))
            if (~hold).any():
                vv = d[~hold] / dt[~hold][:, None]
                self.stats.peak_speed_mm_s = max(self.stats.peak_speed_mm_s, float(v[~hold].max()))
                if self.prev_v is not None:
                    vv = np.vstack([self.prev_v[None], vv])
                if len(vv) > 1:
                    acc = np.linalg.norm(np.diff(vv, axis=0), axis=1) / np.maximum(dt[~hold][-len(vv) + 1:], self.dt)
                    self.stats.peak_accel_mm_s2 = max(self.stats.peak_accel_mm_s2, float(acc.max()))
                self.prev_v = vv[-1]
        self.last_pt = pts[-1].copy()
        self.last_k = int(ks[-1])
        self.e_last_ref = float(es[-1])

    def _firmware_feeds(self, d, dist, dt, hold) -> np.ndarray:
        """Feed rates that make the firmware's trapezoids last the intended durations.

        A segment cruises at its F, but the firmware enters it at the junction speed
        ``min(F_prev, F)`` and leaves at ``min(F, F_next)``, ramping at its acceleration limit
        (the header's ACCEL, or Klipper's delta limit ``max_z_accel * d / |dz|`` on segments with z
        travel).  Solving ``d = F T - (F - v_in)^2 / 2a - (F - v_out)^2 / 2a`` for F, a few sweeps
        over the run, removes the time those ramps would add (a slow drift otherwise).
        """
        v = dist / dt
        dz = np.abs(d[:, 2])
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(dz > 0, dist / np.maximum(dz, 1e-12), np.inf)
        a = np.minimum(self.accel, self.max_z_accel * ratio)
        if not np.all(np.isfinite(a)) or len(v) == 0:
            return v
        F = v.copy()
        for _ in range(4):
            prev = np.concatenate([[self.f_last], F[:-1]])
            prev = np.where(np.concatenate([[False], hold[:-1]]), 0.0, prev)
            nxt = np.concatenate([F[1:], [F[-1]]])
            vin = np.minimum(prev, F)
            vout = np.minimum(nxt, F)
            b = vin + vout + a * dt
            disc = b * b - 2.0 * (vin * vin + vout * vout + 2.0 * a * dist)
            Fn = np.where(disc > 0, 0.5 * (b - np.sqrt(np.maximum(disc, 0.0))), v)
            F = np.where(hold, v, np.maximum(Fn, v))
        self.f_last = float(F[~hold][-1]) if (~hold).any() else 0.0
        return F

    def finish(self) -> None:
        self.flush_lines(1 << 62)
