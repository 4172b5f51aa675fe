"""Where the plan's stops and corners fall between two samples: the times and points the writer
(:mod:`ffcomp.gcode.writer`) puts there so the firmware runs the written chain on the plan's clock.

The samples sit on a fixed grid; the plan comes to rest (before an extruder-only move, a dwell, a
reversal), leaves rest and turns its corners between two of them, and the firmware ramps from
and to exactly those points.  Where the compensated command follows the plan there (pinned, or
where the firmware's limits bind), these kernels give a run's end point and time
(:func:`rest_end`), the time it leaves rest (:func:`rest_start`) and the plan's own speeds along
segments that follow it (:func:`plan_speeds`).  Times are in samples of the writer's count
(``k0 + index``; ``k_plan`` maps samples to the plan's grid), ``dt`` in s, positions in mm.
"""

from __future__ import annotations

import math

import numpy as np

from .chain_plan import junction_v2, segment_limits
from .moves import MOVE, PlannedMove

__all__ = ["rest_end", "rest_start", "corner_lead", "corner_lead_free", "corner_tail", "corner_segment_mm",
           "free_corner", "sampled_corners_ok", "plan_speeds",
           "REST_POINT_NEAR_MM",
           "CORNER_LEAD_MAX_MM"]

#: a run's last sample this close to the plan's rest point (mm, as written) takes its place, rather
#: than a segment of that length being appended: a micrometre's segment into a corner caps the
#: firmware's junction there (Klipper's centripetal rule, ``0.5 d a tan(theta / 2)``), and the
#: pinned ramp before it ran up to 0.7 ms late braking for it (relative_extrusion on other_delta).
#: The writer drops the next run's first point as close to that rest point for the same reason.
REST_POINT_NEAR_MM = 2e-3


def rest_end(dt: float, k0: int, b: int, X: np.ndarray, mv: PlannedMove | None, k_plan: np.ndarray | None,
             on_plan: np.ndarray | None, next_move: PlannedMove | None):
    """Where and when a motion run (samples ``.. k0 + b - 1``) must end if its planned move comes
    to rest (or, on the plan, to a corner) between two samples: ``(point mm, time / dt, extruder mm,
    appended)``, else None.

    The samples stop short of the rest point (by up to one sample of the deceleration); written
    as they are, the firmware would brake to rest early and short, late by up to a sample (a
    loss before every extruder-only move, dwell and full stop; with ``max_z_accel`` binding,
    most of a layer change's drift).  The run ends on the plan's rest point at the plan's time
    instead: a point appended after the last sample where that sample follows the plan, or,
    where the last sample is within :data:`REST_POINT_NEAR_MM` of the rest point (the pin repair
    puts a free command's last sample there; a pinned ramp's last sample can fall a micrometre or
    two short of it), in its place (``appended`` 1 or 0).  None where the run does
    not end its move, or the command is elsewhere (a free command turns round before or after
    the plan's stop).  Where the command follows the plan up to its last sample, a move that
    ends at a corner passed at speed ends on the plan's corner at its time too (a pinned z-hop
    before the travel: the firmware takes the corner as the plan does, instead of braking for a
    corner moved up to a sample's travel away).
    """
    if mv is None or k_plan is None or on_plan is None or k_plan[b - 1] < 0:
        return None
    if mv.end_v_mm_s > 1e-9 and not on_plan[b - 1]:
        return None
    k_last = k0 + b - 1
    k_end = mv.t_end_s / dt + (k_last - int(k_plan[b - 1]))  # on the writer's count
    end = np.array(mv.end_mm[:3], float)
    far = np.linalg.norm(np.round(end, 4) - np.round(X[b - 1], 4)) >= REST_POINT_NEAR_MM
    if (k_last - 1 + 1e-6 < k_end <= k_last - 1e-6 and not far and on_plan[b - 1] and b >= 2
            and mv.end_v_mm_s <= 1e-9):
        # the plan came to rest before the last sample, which stands on the rest point: that
        # point takes the plan's rest time (the writer then drops the sample before it where it
        # lies within a micrometre: a hold there would make the firmware stop a sample early)
        return end, k_end, float(mv.end_mm[3]), 0
    if not (k_last < k_end - 1e-6 and k_end <= k_last + 1 + 1e-9):
        return None
    # an appended point is the plan's: the samples either side must be on the plan too (a
    # free command after it would have to jump from the plan's point to its own)
    if far and not on_plan[b - 1]:
        return None
    if far and b < len(on_plan) and not on_plan[b]:
        return None
    if far and b == len(on_plan):  # the next sample comes with the next chunk: a hold stands there
        if next_move is None or next_move.kind == MOVE:
            return None
    return end, k_end, float(mv.end_mm[3]), int(far)


#: the farthest :func:`corner_lead` moves a run's first point from its corner, mm (and the longest
#: segment :func:`corner_segment_mm` asks for).  0.05 since the thirty-fourth round, 0.02 before: a
#: free lift on from a pinned layer change's lift, a 44 deg turn the plan takes at 11.4 mm/s, needs
#: 0.035 mm at ``max_z_accel`` = 3,000; at 0.02 the firmware took it at 8.6 mm/s, 0.64 ms off the clock
CORNER_LEAD_MAX_MM = 0.05
#: the most samples :func:`corner_lead` looks at past a corner
CORNER_LEAD_MAX_SAMPLES = 16
#: the least distance between the moved first point and the run's second sample, mm (closer, the
#: two would print as one point: a hold, where the firmware stops)
CORNER_LEAD_GAP_MM = 2e-3


def corner_segment_mm(u_in, u_out, v_mm_s: float, accel_mm_s2: float,
                      max_mm: float | None = None, straight_cos: float = -0.999) -> float | None:
    """The length (mm) a segment next to a junction needs for Klipper's centripetal rule,
    ``v^2 <= d a tan(theta/2) / 2``, to allow ``v_mm_s`` there: ``2 v^2 / (a tan(theta/2))`` for the
    inner angle ``theta`` between the directions ``u_in`` and ``u_out``, at most ``max_mm``
    (default :data:`CORNER_LEAD_MAX_MM`); None on a (nearly) straight line (Klipper's
    ``junction_cos_theta`` below ``straight_cos``: by default turns under 2.6 deg; Klipper's own is
    -0.999999, 0.08 deg) or under a micrometre."""
    max_mm = CORNER_LEAD_MAX_MM if max_mm is None else max_mm
    jc = -float(np.dot(u_in[:3], u_out[:3]))  # Klipper's junction_cos_theta
    if jc < straight_cos:
        return None
    tan_half = np.sqrt(0.5 * (1.0 - jc)) / np.sqrt(max(0.5 * (1.0 + jc), 1e-12))
    reach = min(2.0 * v_mm_s * v_mm_s / (accel_mm_s2 * tan_half), max_mm)
    return reach if reach >= 1e-3 else None


def corner_lead(dt: float, k0: int, a: int, b: int, X: np.ndarray, mv: PlannedMove | None,
                k_plan: np.ndarray | None, on_plan: np.ndarray | None, lead_pt: np.ndarray | None,
                prev: PlannedMove | None):
    """How a motion run (samples ``k0 + a .. k0 + b - 1``) that leaves a corner of the plan at
    speed begins: ``(n, point mm, time / dt on the writer's count)``, its first ``n`` samples
    dropped and, unless ``point`` is None, the next one moved to ``point`` at that time; or None
    to keep its samples.

    Klipper caps the speed at a junction by the centripetal rule of the segment after it,
    ``v^2 <= d tan(theta/2) a / 2`` (``d`` its length, ``a`` its acceleration, ``theta`` the
    inner angle between the segments; none on a straight line).  A run that
    follows the plan out of a corner the plan passes at ``v_j`` (a z-hop's move down after its
    travel, at ``max_z_accel``) starts with a sample's chord of a micrometre or two: the firmware
    would slow to ``sqrt(d a tan(theta/2) / 2)`` at the corner and run a fraction of a
    millisecond late down the whole move.  Its first point is the plan's point
    ``2 v_j^2 / (a tan(theta/2))`` along the move (at most :data:`CORNER_LEAD_MAX_MM`; ``theta``
    between ``prev``, the plan's move before, and ``mv``) at the plan's time there; the samples
    before it go.  Where a sample lies just beyond that point (within
    :data:`CORNER_LEAD_GAP_MM`: the two would print as one point, a hold where the firmware
    stops), that sample is the first point instead.  Only where the run's samples up to there
    are on the plan (pinned), the run starts on the move's start and the point falls in the move's
    ramp or cruise (a slow lift, 5 -> 10 mm/s, cruises within the reach: its first chord was left at
    3.6 um, and the firmware took the corner 0.4 ms off the clock; cube_cura on other_delta).
    """
    if (on_plan is None or b - a < 4 or not on_plan[a] or mv is None or prev is None or prev.kind != MOVE
            or k_plan is None or lead_pt is None or k_plan[a] < 0 or mv.start_v_mm_s <= 1e-9
            or mv.accel_mm_s2 <= 0.0):
        return None
    start = np.array(mv.start_mm[:3], float)
    if np.linalg.norm(np.round(start, 4) - lead_pt) >= 1e-3:
        return None
    v, acc = mv.start_v_mm_s, mv.accel_mm_s2
    reach = corner_segment_mm(prev.unit, mv.unit, v, acc)
    if reach is None:
        return None
    if np.linalg.norm(X[a] - start) >= reach:
        return None
    d = np.linalg.norm(X[a:min(b, a + CORNER_LEAD_MAX_SAMPLES)] - start, axis=1)
    beyond = np.nonzero(d >= reach)[0]
    if not beyond.size:
        return None
    m = int(beyond[0])  # the first sample at or beyond the point
    if m == 0 or m > b - a - 3 or not on_plan[a:a + m + 1].all():
        return None
    if d[m] < reach + CORNER_LEAD_GAP_MM:
        return m, None, None
    tau = (np.sqrt(v * v + 2.0 * acc * reach) - v) / acc
    if tau > mv.accel_t_s:  # past the ramp: in the cruise (a slow lift reaches it within the reach)
        vc = mv.cruise_v_mm_s
        s_acc = v * mv.accel_t_s + 0.5 * acc * mv.accel_t_s**2
        tau = mv.accel_t_s + (reach - s_acc) / max(vc, 1e-9)
        if tau > mv.accel_t_s + mv.cruise_t_s:
            return None
    k = (mv.t_start_s + tau) / dt + (k0 + a - int(k_plan[a]))
    if not (k0 + a - 1 < k < k0 + a + m - 1e-6):
        return None
    return m - 1, start + np.array(mv.unit[:3], float) * reach, k


def corner_lead_free(a: int, b: int, X: np.ndarray, mv: PlannedMove | None, on_plan: np.ndarray | None,
                     lead_pt: np.ndarray | None, prev: PlannedMove | None, fw_accel_mm_s2: float, tol_mm: float):
    """How a free motion run (samples ``a .. b - 1``, off the plan within the corner's reach) that
    leaves the plan's corner begins, the run before having ended on that corner (pinned up to it:
    :func:`rest_end`): ``(n, None, None)``, its first ``n`` samples dropped, or None to keep them.

    The mirror of :func:`corner_lead` for a command that leaves the plan at the corner (a
    retracting travel into a lift the correction moves): written as sampled, its first chord is a
    micrometre or two, and Klipper's centripetal rule of that chord caps the corner below the
    plan's ``v_j`` (a random file on the default profile: 3.5 mm/s for the plan's 9, then the lift
    ran 0.28 ms late).  The samples within ``2 v_j^2 / (a tan(theta/2))`` of the corner (at most
    :data:`CORNER_LEAD_MAX_MM`; ``a`` the firmware's acceleration along the move,
    ``fw_accel_mm_s2``) go, where they lie within ``tol_mm`` of the chord that replaces them and at
    least three samples remain.
    """
    if (on_plan is None or mv is None or prev is None or prev.kind != MOVE or mv.kind != MOVE
            or lead_pt is None or mv.start_v_mm_s <= 1e-9 or fw_accel_mm_s2 <= 0.0 or b - a < 4):
        return None
    start = np.array(mv.start_mm[:3], float)
    if np.linalg.norm(np.round(start, 4) - lead_pt) >= 1e-3:
        return None
    reach = corner_segment_mm(prev.unit, mv.unit, mv.start_v_mm_s, fw_accel_mm_s2)
    if reach is None:  # a straight plan: the command's own small turn at its first samples
        m = _straight_lead(a, b, X, mv.start_v_mm_s, start, fw_accel_mm_s2)
    else:
        d = np.linalg.norm(X[a:min(b, a + CORNER_LEAD_MAX_SAMPLES)] - start, axis=1)
        beyond = np.nonzero(d >= reach)[0]
        if not beyond.size or on_plan[a:a + int(beyond[0]) + 1].all():  # (on the plan: corner_lead's)
            return None
        m = int(beyond[0])
    if m == 0 or m > b - a - 3 or _off_chord(X[a:a + m], start, X[a + m]) > tol_mm:
        return None
    return m, None, None


def _straight_lead(a: int, b: int, X: np.ndarray, v_mm_s: float, start: np.ndarray, fw_accel_mm_s2: float) -> int:
    """How many of a run's first samples :func:`corner_lead_free` drops where the plan runs straight
    on through the corner (two collinear moves): the first chord, from the corner point to the run's
    first sample, may be a few micrometres, and where the command turns there by a fraction of a
    degree (a correction leaving a pinned z move), Klipper's centripetal rule of that chord caps
    the junction (3.2 um and a 0.7 deg turn: 27 mm/s in a lift at 55 mm/s, which the pinned ramp
    before it braked for, 4.6 ms late on other_delta).  The samples whose chord from the corner is
    shorter than :func:`corner_segment_mm` of the turn there at the plan's speed ``v_mm_s`` (with
    Klipper's own straight-line threshold) go; 0 where two points coincide."""
    m = 0
    while m < min(b - a - 3, CORNER_LEAD_MAX_SAMPLES):
        d_in, d_out = X[a + m] - start, X[a + m + 1] - X[a + m]
        l_in, l_out = float(np.linalg.norm(d_in)), float(np.linalg.norm(d_out))
        if l_in < 1e-6 or l_out < 1e-6:
            return 0
        reach = corner_segment_mm(d_in / l_in, d_out / l_out, v_mm_s, fw_accel_mm_s2, straight_cos=-0.999999)
        if reach is None or l_in >= reach:
            break
        m += 1
    return m


def corner_tail(dt: float, k0: int, a: int, b: int, X: np.ndarray, mv: PlannedMove | None,
                on_plan: np.ndarray | None, next_move: PlannedMove | None, end, fw_accel_mm_s2: float):
    """How a motion run that ends on the plan's corner (see :func:`rest_end`) comes into it:
    ``(n, point mm, time / dt on the writer's count)``, its last ``n`` samples before the corner
    point dropped and, unless ``point`` is None, the first of them moved to ``point`` at that time
    (where no sample lies within the segment's length, the last one moves out to it);
    or None to keep its samples.

    Klipper caps a junction by the centripetal rule of the segment before it as well as the one
    after, ``v^2 <= d a tan(theta/2) / 2`` with that segment's length ``d`` and acceleration
    ``a``.  A pinned z move (a z-hop, a layer change) that runs into an XY travel at the plan's
    ``v_j`` ended with a sample's chord of a micrometre or two: the firmware slowed to under a
    third of ``v_j`` there and the ramp before it ran up to 0.36 ms late (the sample files' z-hops
    on other_delta, where ``max_z_accel * d/|dz|`` is the z move's acceleration).  A longer
    segment lets the firmware take the corner faster than the plan (the output's square corner
    velocity is the header's), and the ramp runs early.  So the segment into the corner is
    ``2 v_j^2 / (a tan(theta/2))`` long (at most :data:`CORNER_LEAD_MAX_MM`; ``a`` the firmware's
    acceleration along the move, ``fw_accel_mm_s2``): it starts at the plan's point there at the
    plan's time, or at the sample just before that point (within :data:`CORNER_LEAD_GAP_MM`: the two
    would print as one point).  Only where the samples dropped and the one before them lie on the
    plan (a straight line: the firmware's one segment decelerates as the plan does), within
    :data:`CORNER_LEAD_MAX_SAMPLES` of the corner, and the point falls in the plan's deceleration or
    the cruise before it.
    """
    if (end is None or mv is None or next_move is None or next_move.kind != MOVE or on_plan is None
            or mv.end_v_mm_s <= 1e-9 or fw_accel_mm_s2 <= 0.0 or mv.accel_mm_s2 <= 0.0):
        return None
    v = mv.end_v_mm_s
    reach = corner_segment_mm(mv.unit, next_move.unit, v, fw_accel_mm_s2)
    if reach is None:
        return None
    pt, k_end, appended = np.asarray(end[0], float), float(end[1]), int(end[3])
    last = b - 1 if appended else b - 2  # the last sample before the corner point
    lo = max(a + 1, last - CORNER_LEAD_MAX_SAMPLES + 1)
    n = 0
    for s in range(last, lo - 1, -1):
        if np.linalg.norm(X[s] - pt) >= reach:
            break
        n += 1
    if n == 0:  # the last sample lies beyond the point: it moves there (the junction no faster)
        if last < a or np.linalg.norm(X[last] - pt) < reach + CORNER_LEAD_GAP_MM:
            return None
        n = 1
    first = last - n + 1
    if first - 1 < a or not on_plan[first - 1:last + 1].all():
        return None
    if np.linalg.norm(X[first - 1] - pt) < reach + CORNER_LEAD_GAP_MM:
        return n, None, None
    acc = mv.accel_mm_s2
    tau = (np.sqrt(v * v + 2.0 * acc * reach) - v) / acc  # the plan's time from the point to the corner
    if tau > mv.decel_t_s:  # the point lies in the cruise before the braking
        decel_d = 0.5 * (mv.cruise_v_mm_s + v) * mv.decel_t_s
        tau = mv.decel_t_s + (reach - decel_d) / max(mv.cruise_v_mm_s, 1e-9)
        if tau > mv.decel_t_s + mv.cruise_t_s:
            return None
    k = k_end - tau / dt
    if not (k0 + first - 1 + 1e-6 < k < k_end - 1e-6):
        return None
    return n, pt - np.array(mv.unit[:3], float) * reach, k


def rest_start(dt: float, k0: int, a: int, mv: PlannedMove | None, k_plan: np.ndarray | None,
               on_plan: np.ndarray | None, lead_pt: np.ndarray, lead_k: float) -> float:
    """When (time / dt, the writer's count) a motion run starting at sample ``k0 + a`` leaves its
    lead point: the plan's start where its move starts from rest between two samples at the
    point the writer left the nozzle, its first sample on the plan (else ``lead_k``, the previous
    point's time).  From the previous sample instead, the firmware would be asked to cover the
    first sample's distance from rest in a whole sample, not in the part of it the plan moves
    (early, then late).
    """
    if (mv is None or k_plan is None or on_plan is None or not on_plan[a] or mv.start_v_mm_s > 1e-9
            or k_plan[a] < 0 or lead_pt is None
            or np.linalg.norm(np.round(mv.start_mm[:3], 4) - lead_pt) >= 1e-3):
        return lead_k
    k_go = mv.t_start_s / dt + (k0 + a - int(k_plan[a]))
    if not (k0 + a - 1 - 1e-9 <= k_go < k0 + a + 1e-6):
        return lead_k
    return max(lead_k, k_go)


def plan_speeds(dt: float, k0: int, mvs: list, a_s, offs, src, K, i, j, srun, went, on_plan, k_plan):
    """The plan's peak speed (mm/s) along each segment ``i -> j`` (points of the motion runs whose
    moves are ``mvs``) whose ends both follow the plan (pinned, or where limits bind), NaN
    elsewhere: the feed that makes the firmware's own ramps run the plan (see
    :func:`ffcomp.gcode.feed_solve.solve_feeds`), and the plan's acceleration along each segment.
    A run's lead point follows the plan where the run leaves rest on the plan's time (``went``)."""
    op = on_plan[src] & (k_plan[src] >= 0)
    op[offs] = np.asarray(went, bool)
    on = op[i] & op[j]
    out = np.full(len(i), np.nan)
    if not on.any():
        return out, np.zeros(len(i))
    a_s = np.asarray(a_s)
    kofs = np.where(k_plan[a_s] >= 0, (k0 + a_s) - k_plan[a_s], 0)  # writer count - plan count
    prm = np.array([(m.t_start_s, m.start_v_mm_s, m.cruise_v_mm_s, m.accel_mm_s2, m.accel_t_s, m.cruise_t_s,
                     m.duration_s) if m is not None else (0, 0, 0, 0, 0, 0, 0) for m in mvs], float)
    ok = np.array([m is not None for m in mvs])[srun] & on
    t0, v0, vc, acc, ta, tc, dur = prm[srun].T
    ti = np.clip((K[i] - kofs[srun]) * dt - t0, 0.0, dur)
    tj = np.clip((K[j] - kofs[srun]) * dt - t0, 0.0, dur)

    def v(t):
        return np.maximum(np.where(t < ta, v0 + acc * t, np.where(t < ta + tc, vc, vc - acc * (t - ta - tc))), 0.0)

    peak = np.where(tj <= ta, v(tj), np.where(ti >= ta + tc, v(ti), vc))
    out[ok] = np.maximum(peak[ok], 1e-3)
    return out, acc


#: the farthest :func:`free_corner` drops a corner's neighbours from it, mm
FREE_CORNER_MAX_MM = 0.05
#: :func:`free_corner` acts where the sampled chords' junctions cap the speed below this share of
#: the command's
FREE_CORNER_SHARE = 0.9
#: ... and where the written corner's tightest junction (against the command's speed) beats the
#: sampled chain's by at least this factor
FREE_CORNER_GAIN = 1.1
#: a plan's turn under 0.5 deg (the cosine between its moves above this) is no corner for
#: :func:`free_corner` (Klipper's rule lets 1 ms chords through it at 180 mm/s on other_delta)
FREE_CORNER_STRAIGHT_COS = math.cos(math.radians(0.5))


def _plan_point(mv: PlannedMove, t_s: float) -> np.ndarray:
    """The plan's nozzle point (mm) on move ``mv`` at print time ``t_s`` (clamped to the move)."""
    return np.array(mv.start_mm[:3], float) + np.array(mv.unit[:3], float) * mv.distance_at(t_s)


def _off_chord(pts: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> float:
    """The largest distance (mm) of ``pts`` (n, 3) from the segment ``p0 -> p1``."""
    d = p1 - p0
    L2 = float(d @ d)
    if L2 <= 1e-18:
        return float(np.max(np.linalg.norm(pts - p0, axis=1)))
    s = np.clip((pts - p0) @ d / L2, 0.0, 1.0)
    return float(np.max(np.linalg.norm(pts - (p0 + s[:, None] * d), axis=1)))


def free_corner(dt: float, k0: int, a: int, b: int, b_next: int, X: np.ndarray, mv: PlannedMove | None,
                next_move: PlannedMove | None, k_plan: np.ndarray | None, lim, tol_mm: float):
    """A corner the plan passes at speed between samples ``k0 + b - 1`` and ``k0 + b`` where the
    command does not follow the plan (so :func:`rest_end`, :func:`corner_tail` and
    :func:`corner_lead` leave it): ``((point mm, time / dt, extruder mm, 1), n_tail, m_lead)`` or
    None.

    Written as sampled, the segment that straddles the corner and its neighbours are a sample's
    chord each, and Klipper's centripetal rule ``v^2 <= d a tan(theta/2) / 2`` of those short
    segments (``d`` a segment's length, ``a`` its acceleration: ``max_z_accel * d/|dz|`` on a
    steep one) caps the junction below the command's speed there (the plan's ``v_j`` plus the
    correction's velocity): on other_delta a travel into a lift turned at 9 mm/s instead of 13,
    the lift ran 0.3 ms late and the feed solve ran the travel 0.8 ms early to share it (random
    files).  The run instead ends on the command's corner: the plan's corner point moved by the
    correction (the command minus the plan) interpolated between the two samples, at the plan's
    time; the run's last ``n_tail`` samples and the next run's first ``m_lead`` samples within
    :func:`corner_segment_mm` of it (for the command's speed, the turn between the segments that
    replace them and the firmware's acceleration along each, ``lim``: a
    :class:`~ffcomp.gcode.chain_plan.ChainLimits`; at most :data:`FREE_CORNER_MAX_MM`) are
    dropped.  Only where the sampled chords cap the junctions below :data:`FREE_CORNER_SHARE` of
    the command's speed there, the dropped samples lie within ``tol_mm`` of the chords that replace
    them (the command is nearly straight either side of the plan's corner), the tightest of the
    written junctions (the corner and the two before and after it) gains on the sampled chain's
    by :data:`FREE_CORNER_GAIN`, and ``b_next`` (the end of the next run, which
    starts at ``b``) leaves at least three samples after them.
    """
    if (mv is None or next_move is None or next_move.kind != MOVE or mv.kind != MOVE or k_plan is None
            or b < 2 or b + 1 >= len(X) or b - a < 2 or b_next - b < 4 or mv.end_v_mm_s <= 1e-9):
        return None
    ua, ub = mv.unit, next_move.unit
    if ua[0] * ub[0] + ua[1] * ub[1] + ua[2] * ub[2] > FREE_CORNER_STRAIGHT_COS:
        return None  # the plan does not turn there: the command has no kink
    if k_plan[b - 1] < 0 or k_plan[b] != k_plan[b - 1] + 1 or abs(next_move.t_start_s - mv.t_end_s) > 1e-9:
        return None
    t1, t2 = k_plan[b - 1] * dt, k_plan[b] * dt
    if not (t1 < mv.t_end_s - 1e-9 and mv.t_end_s <= t2 + 1e-12 and t2 < next_move.t_end_s):
        return None
    # as sampled: Klipper's limits at the two junctions either side of the straddling chord, against
    # the command's speed there (the writer asks this of a whole chunk's run ends at once first)
    if sampled_corners_ok(lim, X, np.array([b]), dt)[0]:
        return None
    ln = np.linalg.norm(np.diff(X[b - 2:b + 2], axis=0), axis=1)
    v = min(ln[0], ln[2]) / dt  # the speed the corner must let through (the slower side's)
    w = (mv.t_end_s - t1) / dt
    c1 = X[b - 1] - _plan_point(mv, t1)
    c2 = X[b] - _plan_point(next_move, t2)
    pc = np.array(mv.end_mm[:3], float) + c1 + (c2 - c1) * w
    lo = max(a, b - 1 - CORNER_LEAD_MAX_SAMPLES)
    hi = min(b_next - 4, b + CORNER_LEAD_MAX_SAMPLES)
    p_in, p_out = X[b - 2], X[b + 1]  # the far ends of the segments either side (first guess)
    n = m = 0
    for _ in range(3):
        d_in, d_out = pc - p_in, p_out - pc
        l_in, l_out = float(np.linalg.norm(d_in)), float(np.linalg.norm(d_out))
        if l_in < 1e-6 or l_out < 1e-6:
            return None
        acc = segment_limits(lim, np.array([p_in, pc]), np.array([pc, p_out]), np.zeros(2))[1]
        u_in, u_out = d_in / l_in, d_out / l_out
        reach_in = corner_segment_mm(u_in, u_out, v, float(acc[0]), FREE_CORNER_MAX_MM)
        reach_out = corner_segment_mm(u_in, u_out, v, float(acc[1]), FREE_CORNER_MAX_MM)
        if reach_in is None or reach_out is None:
            return None
        n2 = 0
        while b - 1 - n2 > lo and np.linalg.norm(X[b - 1 - n2] - pc) < reach_in:
            n2 += 1
        m2 = 0
        while b + m2 < hi and np.linalg.norm(X[b + m2] - pc) < reach_out:
            m2 += 1
        if (n2, m2) == (n, m) and _ > 0:
            break
        n, m = n2, m2
        p_in, p_out = X[b - 1 - n], X[b + m]
    if n == 0 and m == 0:
        return None
    if np.linalg.norm(X[b - 1 - n] - pc) < reach_in or np.linalg.norm(X[b + m] - pc) < reach_out:
        return None  # ran into the run's edge or the samples looked at
    if n and _off_chord(X[b - n:b], X[b - 1 - n], pc) > tol_mm:
        return None
    if m and _off_chord(X[b:b + m], pc, X[b + m]) > tol_mm:
        return None
    # the junctions either side move too (the chords next to them change length): the corner is
    # written so only where the tightest of them, against the command's speed, gains on the sampled
    # chain's (a corner whose new in-chord was shorter than the sample it replaced capped the
    # junction before it, a z turn in cube_prusa on other_delta: +0.26 ms)
    if b - 2 - n < 0 or b + m + 2 > len(X):
        return None  # (no chord beyond the samples it would drop on one side: nothing to compare)
    S = X[b - 2 - n:b + m + 2]
    jv_s = _junction_speeds(lim, S)
    jv_n = _junction_speeds(lim, np.array([S[0], S[1], pc, S[-2], S[-1]]))
    if jv_s is None or jv_n is None:
        return None
    ln = np.linalg.norm(np.diff(S, axis=0), axis=1)
    need = 0.5 * (ln[:-1] + ln[1:]) / dt
    if np.min(jv_n / np.array([need[0], v, need[-1]])) < FREE_CORNER_GAIN * np.min(jv_s / need):
        return None
    k_end = mv.t_end_s / dt + (k0 + b - 1 - int(k_plan[b - 1]))
    return (pc, k_end, float(mv.end_mm[3]), 1), n, m


def sampled_corners_ok(lim, X: np.ndarray, bs: np.ndarray, dt: float) -> np.ndarray:
    """Whether Klipper's corner rules (:func:`~ffcomp.gcode.chain_plan.junction_v2`, no extrusion;
    each chord's acceleration as :func:`~ffcomp.gcode.chain_plan.segment_limits` gives it: the
    delta cap, the slow zones) let the sampled chords either side of the corners between samples
    ``bs - 1`` and ``bs`` of ``X`` (each ``2 <= b < len(X) - 1``) through their two junctions at
    :data:`FREE_CORNER_SHARE` of the command's speed there (the mean of the chords either side, per
    ``dt``), as an array; True where two samples coincide (nothing to do).  The writer asks it of
    every free run's end of a chunk in one pass: a call per corner cost 2.7 s of 17 on the plate's
    first 40,000 lines."""
    P = X[bs[:, None] + np.arange(-2, 2)]  # (k, 4, 3)
    A, B = P[:, :-1].reshape(-1, 3), P[:, 1:].reshape(-1, 3)
    d = B - A
    ln = np.sqrt(np.einsum("ij,ij->i", d, d))
    degenerate = (ln < 1e-6).reshape(-1, 3).any(axis=1)
    acc = segment_limits(lim, A, B, np.zeros(len(d)))[1]
    with np.errstate(invalid="ignore", divide="ignore"):
        jv2 = junction_v2(lim, d / ln[:, None], np.zeros(len(d)), acc, 2.0 * ln * acc)
    L = ln.reshape(-1, 3)
    need = FREE_CORNER_SHARE * 0.5 * (L[:, :-1] + L[:, 1:]) / dt
    return degenerate | np.all(np.stack([jv2[0::3], jv2[1::3]], axis=1) >= need * need, axis=1)


def _junction_speeds(lim, P: np.ndarray) -> np.ndarray | None:
    """Klipper's junction speed limits (mm/s; corner rules, no extrusion) at the inner points of the
    chain ``P`` (n, 3), or None where two points coincide."""
    d = np.diff(P, axis=0)
    ln = np.linalg.norm(d, axis=1)
    if np.any(ln < 1e-6):
        return None
    acc = segment_limits(lim, P[:-1], P[1:], np.zeros(len(d)))[1]
    return np.sqrt(junction_v2(lim, d / ln[:, None], np.zeros(len(d)), acc, 2.0 * ln * acc))
