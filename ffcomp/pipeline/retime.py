"""Feed rates re-timed on the firmware's own plan, for planners without a vectorised chain model.

Klipper's writer solves its feeds against an exact, vectorised copy of Klipper's lookahead
(:mod:`ffcomp.gcode.chain_plan`, :mod:`ffcomp.gcode.feed_solve`).  Marlin's planner (junction
deviation with the extruder in the junction vector, per-axis acceleration limits, extruder-only
blocks entered at a junction speed) has no such model in the writer, whose feeds assume simple
trapezoids: the written file ran 35 ms off the clock over the 36 s of ``stress_square.gcode`` and
0.6 s over ``cube_prusa.gcode``.  :func:`retime_file` closes that loop on the written file: it
re-plans the file with the firmware-faithful planner (the self-check's own measurement), and

* scales each segment's F by its re-planned over its intended duration (a segment that runs long
  gets a higher feed), and
* gives each gap between two runs (the extruder-only moves of a retraction, where the nozzle stands)
  the time it lacks or has too much: the extruder-only moves' feeds are solved, on the trapezoid
  ``T(F) = d/F + F/a`` and then by a secant on the previous pass, for the change of duration the
  lateness jump across the gap asks, within :data:`EXTRUDE_FEED_RANGE` of the slicer's feed;
* what a gap cannot give (the extruder at its limits) and what a segment does not give (one that
  does not follow its feed: it accelerates at a limit) is run half ahead of it and taken back half
  after it, over a time constant of 20 ms, so the largest lateness is half such a jump;
* a stop (a heater wait, M600) starts a new clock: no gap across one is timed and nothing is
  carried over it,

a few passes, keeping the best file seen (the largest lateness on the absolute clock).
"""

from __future__ import annotations

import math
import os
import re
import shutil

import numpy as np

from ..gcode.moves import EXTRUDE, FIRMWARE
from ..io_atomic import make_temp, release_temp
from .self_check import measure

__all__ = ["retime_file", "RetimeResult"]

_F = re.compile(r"(?<=\s)F(-?[0-9.]+)")
_E = re.compile(r"(?<=\s)E(-?[0-9.]+)")
#: a lateness jump across a gap beyond this (s) is a stop (a heater wait, M600: a new clock), not
#: a retraction's timing
_GAP_MAX_S = 0.05
#: the range of an extruder-only move's feed, as a factor of the written one (the slicer's
#: retraction speed): what a gap asks beyond it is taken back by the segments around it
EXTRUDE_FEED_RANGE = (0.7, 1.5)
#: a segment's lateness below this (s) asks no factor of its own: it is carried on (see _residues)
RESIDUE_S = 1e-7


class RetimeResult:
    """What :func:`retime_file` did: ``worst_ms`` (largest |lateness| on the absolute clock measured
    before each pass and after the last, ms), ``passes`` run, ``kept`` (index into ``worst_ms`` of
    the file kept)."""

    def __init__(self, worst_ms: list[float], passes: int, kept: int):
        self.worst_ms, self.passes, self.kept = worst_ms, passes, kept

    @property
    def before_ms(self) -> float:
        return self.worst_ms[0] if self.worst_ms else 0.0

    @property
    def after_ms(self) -> float:
        return self.worst_ms[self.kept] if self.worst_ms else 0.0


def _top_feed(d: float, a: float, v0: float = 0.0, v1: float = 0.0) -> float:
    """The highest speed (mm/s) a move of ``d`` mm entered at ``v0`` and left at ``v1`` reaches at
    acceleration ``a`` (the triangle's peak): a higher feed does not shorten it."""
    return math.sqrt(a * d + 0.5 * (v0 * v0 + v1 * v1))


def _trapezoid_time(f: float, d: float, a: float, v0: float = 0.0, v1: float = 0.0) -> float:
    """Duration (s) of a move of ``d`` mm at feed ``f`` (mm/s) and acceleration ``a`` (mm/s^2),
    entered at ``v0`` and left at ``v1`` (a triangle where ``f`` is beyond its reach)."""
    f = max(min(f, _top_feed(d, a, v0, v1)), max(v0, v1, 1e-9))
    v0, v1 = min(v0, f), min(v1, f)
    return (f - v0) / a + (f - v1) / a + (d - (2.0 * f * f - v0 * v0 - v1 * v1) / (2.0 * a)) / f


def _extrude_only_feed(f_mm_s: float, d_mm: float, a_mm_s2: float, dT_s: float, vmax_mm_s: float,
                       v0: float = 0.0, v1: float = 0.0) -> tuple[float, float]:
    """The feed (mm/s) that changes an extruder-only move's duration by ``dT_s`` on its trapezoid
    (:func:`_trapezoid_time`, entered at ``v0`` and left at ``v1``, each at most the feed: Marlin
    joins an extruder-only block to its neighbours at a junction speed, which its own feed caps),
    bounded by ``vmax_mm_s`` and by the triangle's reach; and the change of duration it gives (s).
    The duration falls as the feed rises: bisection on the feed's logarithm."""
    def T(f):
        return _trapezoid_time(f, d_mm, a_mm_s2, min(v0, f), min(v1, f))

    t0 = T(f_mm_s)
    want = t0 + dT_s
    lo, hi = 1e-3, max(min(_top_feed(d_mm, a_mm_s2, v0, v1), vmax_mm_s), 1e-3)
    if want >= T(lo):
        f = lo
    elif want <= T(hi):
        f = hi
    else:
        for _ in range(60):
            mid = math.sqrt(lo * hi)
            if T(mid) > want:
                lo = mid
            else:
                hi = mid
        f = math.sqrt(lo * hi)
    return float(f), T(f) - t0


def _secant_feed(f: float, t: float, prev: tuple | None, dT: float, f_top: float) -> float | None:
    """The feed (mm/s) for a change ``dT`` of an extruder-only move's duration ``t`` at feed ``f``,
    from the slope measured against the previous pass ``prev = (f, t)``; None without a usable one."""
    if prev is None or abs(f - prev[0]) < 1e-6 * f:
        return None
    slope = (t - prev[1]) / (f - prev[0])
    if not slope < -1e-12:  # (a faster feed must shorten it; else the model decides)
        return None
    return float(min(max(f + dT / slope, 0.3 * f), f_top))


def _taken_back(left: np.ndarray, want: np.ndarray, tau_s: float, breaks: np.ndarray | None = None,
                skip: np.ndarray | None = None) -> np.ndarray:
    """How much of the lateness ``left`` before each segment (s; sparse) each segment takes back
    (s): the lateness seen at a segment decays by ``exp(-duration / tau_s)`` across it; none is
    carried into a segment where ``breaks`` is set (a new clock after a stop); a segment in ``skip``
    (one that does not follow its feed) takes none and passes it all on."""
    back = np.zeros(len(left))
    nz = np.nonzero(left)[0]
    carry, k, ptr, n = 0.0, 0, 0, len(left)
    while k < n:
        if abs(carry) < 1e-8:  # nothing carried: jump to the next gap that leaves some
            while ptr < len(nz) and nz[ptr] < k:
                ptr += 1
            if ptr >= len(nz):
                break
            carry, k = 0.0, int(nz[ptr])
        if breaks is not None and breaks[k]:
            carry = 0.0
        seen = carry + left[k]
        if skip is not None and skip[k]:
            carry = seen
            k += 1
            continue
        r = math.exp(-want[k] / tau_s)
        back[k] = (1.0 - r) * seen
        carry = r * seen
        k += 1
    return back


def _answered(line: np.ndarray, dur: np.ndarray, seg_hist: dict | None) -> np.ndarray:
    """The share of its last factor's change each segment delivered: ``(d0 - dur) / (d0 - d0 / f)``
    with ``seg_hist[line] = (f, d0)`` (the factor and the duration before it, previous pass); NaN
    without one, or where the factor asked for no more than :data:`RESIDUE_S`."""
    out = np.full(len(line), np.nan)
    if not seg_hist:
        return out
    for k, n in enumerate(line.tolist()):
        h = seg_hist.get(n)
        if h is not None:
            asked = h[1] - h[1] / h[0]  # what the factor should have changed (either way)
            if abs(asked) > RESIDUE_S:
                out[k] = (h[1] - dur[k]) / asked
    return out


def _residues(dur: np.ndarray, want: np.ndarray, lim_mask: np.ndarray, answered: np.ndarray,
              breaks: np.ndarray) -> np.ndarray:
    """What each segment takes back (s) of the lateness the segments before it leave that their own
    factors do not remove: below the re-timing's resolution (:data:`RESIDUE_S`) no factor is asked
    for, and a segment that answered its last factor only in part (``answered``, :func:`_answered`)
    leaves the rest.  Summed over a file those residues drift the clock
    (``cube_cura.gcode`` on other_delta with Marlin: a microsecond or two at each layer's corners,
    +0.35 ms after 11 minutes).  They are carried on, summed, to the next segment that follows its
    factor (not ``lim_mask``) once they exceed the resolution (so its factor changes at all); nothing
    is carried across ``breaks`` (a stop: a new clock)."""
    late_s = dur - want
    share = np.where(np.abs(late_s) <= RESIDUE_S, 1.0,
                     np.where(np.isnan(answered), 0.0, 1.0 - np.clip(np.nan_to_num(answered), 0.0, 1.0)))
    hand = np.where(lim_mask, 0.0, share * late_s)
    back = np.zeros(len(late_s))
    carry = 0.0
    for k in range(1, len(late_s)):
        carry = 0.0 if breaks[k] else carry + hand[k - 1]
        if not lim_mask[k] and abs(carry) > RESIDUE_S:
            back[k], carry = carry, 0.0
    return back


def _corrections(rows: list, other: list, lines_f: dict, e_accel: float, e_vmax: float, catch_up_s: float,
                 hist: dict | None = None, seg_hist: dict | None = None, limited: set | None = None,
                 first_f: dict | None = None):
    """Per output line: the factor for a segment's F, and the new F (mm/s) of extruder-only moves.

    ``lines_f``: the extruder-only moves' current ``(F mm/s, |E| mm)`` by output line.  The part of a
    gap's lateness its extruder-only moves cannot take back (at the extruder's limits) is taken
    back by the segments after it, over a time constant ``catch_up_s``.  ``hist``: each extruder-only
    move's ``(F mm/s, duration s)`` of the previous pass (the secant's other point: the trapezoid
    model misjudges a move the firmware enters at a junction speed); updated in place.
    ``first_f``: each extruder-only move's feed as written (mm/s; updated in place).
    ``seg_hist``: each segment's ``(factor applied, duration before)`` of the previous pass, and
    ``limited``: the segments found not to follow their feed (a segment the firmware cannot run
    faster: it accelerates from rest at its limit); their excess joins the gaps' (both updated in
    place).
    """
    line = np.concatenate([r[0] for r in rows]).astype(np.int64)
    late = np.concatenate([r[2] for r in rows])
    dur = np.concatenate([r[3] for r in rows])
    want = np.concatenate([r[4] for r in rows])
    stream = np.concatenate([r[5] for r in rows])
    # the lateness each gap adds: the jump of lateness across it less what the segment itself adds
    # (a gap with a stop in it starts a new clock: not a gap to time)
    jump = late - (dur - want) - np.concatenate([[0.0], late[:-1]])
    jump[1:][stream[1:] != stream[:-1]] = 0.0
    gap: dict[int, float] = {}
    left = np.zeros(len(line))  # lateness a gap leaves for the segments after it, s (within a stream)
    lim_mask = np.zeros(len(line), bool)
    last_ahead = 0.0
    answered = _answered(line, dur, seg_hist)
    if seg_hist is not None and limited is not None:
        with np.errstate(invalid="ignore"):
            limited.update(line[answered < 0.3].tolist())
        if limited:
            lim_mask = np.fromiter((n in limited for n in line.tolist()), bool, len(line))
            excess = np.where(lim_mask, dur - want, 0.0)
            left[1:] += excess[:-1]
            if lim_mask[-1] and len(line) > 1:  # the last segment: its excess is run ahead of it, in full
                last_ahead = float(excess[-1])
    if other:
        ol = np.array([o[0] for o in other], dtype=np.int64)
        kinds = [o[1] for o in other]
        odur = np.array([o[3] for o in other])
        for k in np.nonzero((np.abs(jump) > 2e-6) & (np.abs(jump) < _GAP_MAX_S))[0].tolist():
            if k == 0:
                continue
            lo, hi = np.searchsorted(ol, line[k - 1], "right"), np.searchsorted(ol, line[k], "left")
            idx = [i for i in range(lo, hi) if kinds[i] in (EXTRUDE, FIRMWARE) and int(ol[i]) in lines_f]
            tot = float(sum(odur[i] for i in idx))
            if not idx or tot <= 0:
                continue
            done = 0.0
            for i in idx:  # shared in proportion to the moves' durations: early (jump < 0) -> longer
                n = int(ol[i])
                f, d = lines_f[n]
                dT = -float(jump[k]) * odur[i] / tot
                v0, v1, acc = float(other[i][4]), float(other[i][5]), float(other[i][6]) or e_accel
                fn, _ = _extrude_only_feed(f, d, acc, dT, e_vmax, v0, v1)
                sec = _secant_feed(f, float(odur[i]), None if hist is None else hist.get(n), dT,
                                   min(_top_feed(d, acc, v0, v1), e_vmax))
                if sec is not None:
                    fn = sec
                # the slicer's retraction speed changes by at most EXTRUDE_FEED_RANGE
                f0 = f if first_f is None else first_f.setdefault(n, f)
                fn = min(max(fn, f0 * EXTRUDE_FEED_RANGE[0]), f0 * EXTRUDE_FEED_RANGE[1])
                gap[n] = fn
                if hist is not None:
                    hist[n] = (f, float(odur[i]))
                done += (_trapezoid_time(fn, d, acc, min(v0, fn), min(v1, fn))
                         - _trapezoid_time(f, d, acc, min(v0, f), min(v1, f)))
            left[k] = float(jump[k]) + done
    bnd = np.concatenate([[False], stream[1:] != stream[:-1]])  # a stop between: a new clock
    rbnd = np.concatenate([[False], bnd[::-1][:-1]])
    left[bnd] = 0.0  # (nothing carried across a stop)
    # half of what a gap cannot take back is run ahead of time before it (the segments before it
    # end early, down to half of it at the gap) and half is taken back after it: the largest
    # lateness is half the jump, not all of it
    ahead = np.zeros(len(left))
    ahead[:-1] = 0.5 * left[1:]
    if last_ahead:
        ahead[-2] += last_ahead
    target = (want - _taken_back(0.5 * left, want, catch_up_s, bnd, lim_mask)
              - _taken_back(ahead[::-1], want[::-1], catch_up_s, rbnd, lim_mask[::-1])[::-1]
              - _residues(dur, want, lim_mask, answered, bnd))
    ok = (want > 1e-6) & (dur > 0) & (np.abs(dur - target) > RESIDUE_S)
    scale = np.clip(np.where(ok, dur / np.where(ok, np.maximum(target, 0.5 * want), 1.0), 1.0), 0.7, 1.5)
    ok &= ~lim_mask
    seg = {int(n): float(s) for n, s in zip(line[ok], scale[ok])}
    if seg_hist is not None:
        seg_hist.clear()
        seg_hist.update({int(n): (float(s), float(d)) for n, s, d in zip(line[ok], scale[ok], dur[ok])})
    return seg, gap


def _extrude_only_lines(path: str, wanted: set) -> dict:
    """``{line: (F mm/s, |E| mm)}`` of the extruder-only moves at the output lines ``wanted``."""
    out = {}
    with open(path, encoding="utf-8", errors="surrogateescape", newline="") as fi:
        for n, ln in enumerate(fi, 1):
            if n in wanted:
                m, e = _F.search(ln), _E.search(ln)
                if m and e and float(e.group(1)) != 0.0:
                    out[n] = (float(m.group(1)) / 60.0, abs(float(e.group(1))))
    return out


def _rewrite(path: str, tmp: str, seg: dict, gap: dict) -> int:
    """Write ``path`` with the corrections (segment factors, extruder-only feeds in mm/s) to ``tmp``;
    returns how many lines changed."""
    changed = 0
    with open(path, encoding="utf-8", errors="surrogateescape", newline="") as fi, \
            open(tmp, "w", encoding="utf-8", errors="surrogateescape", newline="") as fo:
        for n, ln in enumerate(fi, 1):
            sc = seg.get(n)
            fe = gap.get(n)
            if sc is not None or fe is not None:
                m = _F.search(ln)
                if m:
                    f = float(m.group(1)) * sc if sc is not None else 60.0 * fe
                    ln = ln[:m.start(1)] + f"{f:.3f}" + ln[m.end(1):]
                    changed += 1
            fo.write(ln)
    return changed


def retime_file(path: str, qfile: str, profile, geom, start_mm, segfile: str, head_len: int, *,
                passes: int = 6, goal_ms: float = 0.05, catch_up_s: float = 0.02) -> RetimeResult:
    """Re-time the feeds of the written file ``path`` in place on the firmware's own plan (see the
    module's docstring); ``passes`` at most, stopping once the largest lateness is within
    ``goal_ms``.  The file kept is the best one measured, so it is never worse than the input."""
    lim = profile.limits
    e_accel, e_vmax = lim.max_extrude_only_accel_mm_s2, lim.max_extrude_only_velocity_mm_s
    directory = os.path.dirname(os.path.abspath(path))
    best_path = None
    worst: list[float] = []
    best_i = 0
    tmp = None
    hist: dict = {}
    seg_hist: dict = {}
    limited: set = set()
    first_f: dict = {}
    try:
        for p in range(passes + 1):
            rows: list = []
            other: list = []
            measure(path, qfile, profile, geom, start_mm, segfile, head_len, trace=rows, trace_other=other,
                    timing_only=True)
            w = float(max((np.max(np.abs(r[2])) for r in rows if len(r[2])), default=0.0)) * 1e3
            worst.append(w)
            if w <= worst[best_i] or p == 0:
                best_i = p
                if p < passes and w > goal_ms:  # (the last or a good one need no copy)
                    if best_path is None:
                        fd, best_path = make_temp(directory, "retime", ".gcode")
                        os.close(fd)
                    shutil.copyfile(path, best_path)
            if w <= goal_ms or p == passes or not rows:
                break
            if p >= 2 and min(worst[-2:]) > 0.95 * min(worst[:-2]):  # two passes without a 5 % gain
                break
            eo = _extrude_only_lines(path, {int(o[0]) for o in other if o[1] in (EXTRUDE, FIRMWARE)})
            seg, gap = _corrections(rows, other, eo, e_accel, e_vmax, catch_up_s, hist, seg_hist, limited, first_f)
            if not seg and not gap:
                break
            if tmp is None:
                fd, tmp = make_temp(directory, "retime", ".gcode")
                os.close(fd)
            _rewrite(path, tmp, seg, gap)
            shutil.copyfile(tmp, path)
        if best_i != len(worst) - 1 and best_path is not None:
            shutil.copyfile(best_path, path)
    finally:
        release_temp(tmp)
        release_temp(best_path)
    return RetimeResult(worst, len(worst) - 1, best_i)
