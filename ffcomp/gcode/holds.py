"""Segments the writer turns into holds (``G4``): the firmware stands still there instead.

* :func:`settle_holds`: segments under a micrometre (the firmware would crawl), and the cascade of
  start points they move;
* :func:`unrunnable_rests`: short moves from rest to rest that the firmware cannot run in their
  time (the settling after a pinned z move), within the point tolerance;
* :func:`merged_rest_holds`: the settled holds where a run leaves or comes to rest on the plan's
  time, merged into the segment next to them;
* :func:`merged_wet_holds`: holds that extrude, merged into the moving segment after them;
* :func:`merged_start_holds`: the last holds before a move that cannot leave rest in its time,
  merged into that move.

Pure numeric kernels on the writer's points (no I/O), called by :class:`~ffcomp.gcode.writer.GcodeWriter`.
"""

from __future__ import annotations

import numpy as np

from .chain_plan import ChainLimits, segment_limits

__all__ = ["settle_holds", "unrunnable_rests", "merged_rest_holds", "merged_wet_holds", "merged_ramp_holds",
           "merged_start_holds"]


def unrunnable_rests(lim: ChainLimits, P0: np.ndarray, P1: np.ndarray, dist: np.ndarray, D: np.ndarray,
                      hold: np.ndarray, dry: np.ndarray, tol_mm: float) -> np.ndarray:
    """Segments better written as holds: short moves from rest to rest that the firmware cannot run
    in their time.

    Where a pinned z move ends (the plan stops, the path reverses) the free command after it settles
    by a micrometre or two before it stands still again.  Klipper stops at both ends of such a
    segment (a reversal before it, a ``G4`` after it) and needs ``2 sqrt(d / a)`` for its length
    ``d``: more than the millisecond it is given, so the output ran up to 1.2 ms late there until
    the ``G4`` gave the time back.  A segment within the point tolerance ``tol_mm`` of its start,
    with no extrusion (``dry``), that starts from rest (a hold before it, or a reversal of the
    path: Klipper's junction there is a full stop) and ends at a hold, and that needs more than its
    time ``D`` (s) from rest to rest at its acceleration limit, stands still instead: the nozzle
    stays within ``tol_mm``.
    """
    n = len(dist)
    out = np.zeros(n, bool)
    if n < 2:
        return out
    moving = ~hold
    # the cheap tests first (this runs on every chunk); the limits only for what is left
    k = np.nonzero(moving & dry & (dist <= tol_mm) & np.r_[hold[1:], False])[0]
    k = k[k > 0]
    if not k.size:
        return out
    acc = segment_limits(lim, P0[k], P1[k], np.zeros(k.size))[1]
    k = k[dist[k] > 0.25 * acc * D[k] * D[k]]
    if not k.size:
        return out
    prev_rest = hold[k - 1]
    turn = ~prev_rest & moving[k - 1]
    if turn.any():  # the junction before: a full stop when the path reverses
        a, b = P1[k - 1] - P0[k - 1], P1[k] - P0[k]
        cos = np.einsum("ij,ij->i", a, b) / np.maximum(dist[k - 1] * dist[k], 1e-300)
        prev_rest |= turn & (cos < -0.999)
    out[k[prev_rest]] = True
    _unrunnable_chains(lim, P0, P1, dist, D, hold, dry, tol_mm, out)
    return out


#: the longest chain of short segments between two rests :func:`_unrunnable_chains` looks at
MAX_CHAIN = 8


def _unrunnable_chains(lim: ChainLimits, P0, P1, dist, D, hold, dry, tol_mm: float, out: np.ndarray) -> None:
    """Chains of 2 to :data:`MAX_CHAIN` short dry segments from a hold to a hold, every point within
    ``tol_mm`` of the chain's start, that the firmware cannot run in their time: a stream's settle
    (the command wanders a few micrometres out and back before it stands still) written as a jump
    out and a crawl back, each a stop-to-stop move, ran 1.2 ms late on a pure z settle at
    ``max_z_accel`` (a vase's last lift).  The firmware needs at least ``2 sqrt(d / a)`` to go ``d``
    from rest to rest: out to the farthest point and back to the end.  Such chains stand still
    instead (``out`` set in place)."""
    n = len(dist)
    moving = ~hold & dry & (dist <= tol_mm)
    starts = np.nonzero(moving[1:-1] & hold[:-2] & ~hold[2:])[0] + 1  # leaves a hold, goes on moving
    for a in starts.tolist():
        b = a
        while b + 1 < n and b - a + 1 < MAX_CHAIN and moving[b + 1]:
            b += 1
        if b == a or b + 1 >= n or not hold[b + 1]:
            continue
        pts = P1[a:b + 1]
        off = np.sqrt(np.sum((pts - P0[a]) ** 2, axis=1))
        far = int(np.argmax(off))
        if off[far] > tol_mm:
            continue
        acc = float(np.min(segment_limits(lim, P0[a:b + 1], P1[a:b + 1], np.zeros(b - a + 1))[1]))
        back = float(np.sqrt(np.sum((pts[-1] - pts[far]) ** 2)))
        need = 2.0 * (np.sqrt(off[far] / acc) + np.sqrt(back / acc))
        if need > float(np.sum(D[a:b + 1])):
            out[a:b + 1] = True


def settle_holds(Pr: np.ndarray, i: np.ndarray, j: np.ndarray, first_seg: np.ndarray, offs: np.ndarray,
                  last: np.ndarray, force: np.ndarray | None = None):
    """Segments under a micrometre are written as holds (the firmware would crawl): the nozzle stays
    where the last written segment left it, so the end point of a hold is its start point, and the
    next segment (or the next run, which starts where the previous one ended) starts from there;
    a few vectorised passes settle the cascade.  ``force``: segments written as holds whatever
    their length (:func:`unrunnable_rests`).  Returns ``Pr`` (points as written), the segment
    vectors, lengths and hold flags."""
    Pr = Pr.copy()
    n = len(i)
    for _ in range(6):
        d = Pr[j] - Pr[i]
        dist = np.sqrt(np.einsum("ij,ij->i", d, d))
        hold = dist < 1e-3
        if force is not None:
            hold |= force
        if not hold.any():
            break
        # the first hold of each group of consecutive holds (within a run) is its root
        grp_start = hold & (first_seg | ~np.concatenate(([False], hold[:-1])))
        root = np.maximum.accumulate(np.where(grp_start, np.arange(n), -1))
        moved = hold & np.any(Pr[j] != Pr[i[np.maximum(root, 0)]], axis=1)
        if len(offs) > 1:  # a run starts where the previous one ended
            lead_bad = np.any(Pr[offs[1:]] != Pr[last[:-1]], axis=1)
        else:
            lead_bad = np.zeros(0, bool)
        if not moved.any() and not lead_bad.any():
            break
        Pr[j[hold]] = Pr[i[root[hold]]]
        if len(offs) > 1:
            Pr[offs[1:]] = Pr[last[:-1]]
    d = Pr[j] - Pr[i]
    dist = np.sqrt(np.einsum("ij,ij->i", d, d))
    return Pr, d, dist, (dist < 1e-3) if force is None else (dist < 1e-3) | force


#: :func:`merged_rest_holds` merges a run's first segment into the next only where it spans at most
#: this many samples (None: any).  The settling's rest after a file's last move, pinned to the plan's
#: rest point for 80 ms by the pin repair and then moving 17 um and back (the repair's last
#: correction of the ringing), was merged into one 87 ms chord that crept through the rest: 18 um
#: off the command (a random file on the default profile)
REST_MERGE_MAX_SAMPLES: float | None = 4.0


def merged_rest_holds(i: np.ndarray, j: np.ndarray, srun: np.ndarray, first_seg: np.ndarray, hold: np.ndarray,
                      leaves: np.ndarray, rests: np.ndarray,
                      near: np.ndarray | None = None,
                      span: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Segments ``i -> j`` (point indices) with the holds the settling made at a run's ends merged
    into their neighbour, or None where there are none.

    * A run's first segment that leaves rest on the plan's time (``leaves``) and that became a hold
      (the nozzle rests up to a micrometre off the run's lead point): its end is not a point, the
      next segment leaves rest from the lead at the lead's time.  As a hold, the firmware stood
      still for it and then had a whole sample less for the next distance: 0.99 ms late for the
      3.6 s descent after a homing on other_delta, whose plan ramps at ``max_z_accel``.  (Not
      a group of holds: where the command stands still there, ``G4`` is exact; merged, the
      segment would creep, and the one after it leave a crawl: 0.61 -> 0.68 ms on
      relative_extrusion.)
    * A run's last segment that ends on the plan's rest point (``rests``,
      :func:`~ffcomp.gcode.plan_clock.rest_end`) and became a hold: the firmware stopped at the
      last sample, where the plan still moves; that sample is not a point, the segment before ends
      at the rest point at its time.

    ``srun``, ``first_seg``, ``hold``, ``leaves``, ``rests``: per segment.  ``near`` (per segment,
    default ``hold``): first segments short enough to merge, holds or not.  A first sample a
    micrometre or two off the lead is the same case: the command settles a stop short of the plan's
    rest point, where the run ends; written, the firmware would leave rest for that micrometre in
    the part of a sample the plan gives it (0.7 ms late after a z-hop on other_delta).
    ``span`` (per segment, samples): a first segment longer than :data:`REST_MERGE_MAX_SAMPLES` is
    not merged: there the command stands on the lead for a while (a ``G4`` is exact) and then
    moves on, and the merged segment would creep from the lead to that move's first point.
    """
    nxt_same = np.r_[srun[1:] == srun[:-1], False]
    prv_same = np.r_[False, srun[1:] == srun[:-1]]
    near = hold if near is None else near | hold
    first = first_seg & near & leaves & nxt_same & ~np.r_[hold[1:], False]
    if span is not None and REST_MERGE_MAX_SAMPLES is not None:
        first &= span <= REST_MERGE_MAX_SAMPLES
    end = hold & ~nxt_same & rests & prv_same & ~np.r_[False, hold[:-1]] & ~first
    end[1:] &= ~first[:-1]
    if not (first.any() or end.any()):
        return None
    m_, e_ = np.nonzero(first)[0], np.nonzero(end)[0]
    j = j.copy()
    j[m_] = j[m_ + 1]
    j[e_ - 1] = j[e_]
    keep = np.ones(len(i), bool)
    keep[m_ + 1] = False
    keep[e_] = False
    return i[keep], j[keep]


def merged_wet_holds(i: np.ndarray, j: np.ndarray, srun: np.ndarray, hold: np.ndarray,
                     wet: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Segments ``i -> j`` with each group of consecutive holds that extrudes (``wet``: any of the
    group) merged into the moving segment after it in the same run, or None where there is none.

    A hold that extrudes is written as an extruder-only line, and Klipper stops before and after
    one (its look-ahead joins no kinematic move to it): the next segment starts from rest, where
    the plan is moving.  Where a move extrudes slowly (an extruding z move at a high ratio: its
    first samples move the nozzle less than a micrometre) the firmware then could not reach the
    plan's speed again under the extruder's own limits, and the output fell 8-11 ms behind.  The
    group's points are dropped instead (the nozzle moves less than a micrometre there): the segment
    after them spans their time and extrudes their filament too; at a run's end, the segment before
    them.  ``srun``, ``hold``, ``wet``: per segment.
    """
    n = len(i)
    if n == 0 or not (hold & wet).any():
        return None
    same_prev = np.r_[False, srun[1:] == srun[:-1]]
    goes_on = hold & np.r_[False, hold[:-1]] & same_prev  # a hold that continues the group before it
    starts = np.nonzero(hold & ~goes_on)[0]
    ends = np.nonzero(hold & ~np.r_[goes_on[1:], False])[0]  # (the same groups, in order)
    cw = np.r_[0, np.cumsum(wet & hold)]
    is_wet = cw[ends + 1] > cw[starts]
    j = j.copy()
    keep = np.ones(n, bool)
    for g0, g1 in zip(starts[is_wet].tolist(), ends[is_wet].tolist()):
        nx = g1 + 1
        if nx < n and srun[nx] == srun[g0]:
            j[g0] = j[nx]
            keep[g0 + 1:nx + 1] = False
        elif g0 > 0 and srun[g0 - 1] == srun[g0] and keep[g0 - 1]:  # at the run's end: the one before
            j[g0 - 1] = j[g1]
            keep[g0:g1 + 1] = False
    if keep.all():
        return None
    return i[keep], j[keep]


def merged_ramp_holds(i: np.ndarray, j: np.ndarray, srun: np.ndarray, hold: np.ndarray,
                      ramp: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Segments ``i -> j`` with the holds at the ends of a slow ramp merged into the moving segment
    next to them, or None where there are none.

    A quiet z move (``PlannedMove.quiet``: ramps of one resonance period) leaves rest and comes to
    rest slowly: its first and last samples move the nozzle less than a micrometre, which
    :func:`settle_holds` writes as holds.  The firmware then stands still for them and has to cover
    their motion in the one sample of the first moving segment (at ``max_z_accel``: 0.46 ms late
    on a cube's z-hops on other_delta), or stops a micrometre short of the move's end and carries it
    past the next retraction.  Here the group of holds at a run's start goes into the first moving
    segment (which leaves rest at the run's start and spans their time), and the group at a run's
    end into the last moving one (which ends on the move's end point at its time).

    ``srun``, ``hold``, ``ramp``: per segment (``ramp``: the segment's run is a quiet move).
    """
    n = len(i)
    if n == 0 or not (hold & ramp).any():
        return None
    keep = np.ones(n, bool)
    j = j.copy()
    i = i.copy()
    starts = np.r_[0, np.nonzero(srun[1:] != srun[:-1])[0] + 1]
    ends = np.r_[starts[1:], n]
    for a, b in zip(starts.tolist(), ends.tolist()):
        if not ramp[a] or hold[a:b].all():
            continue
        mv = np.nonzero(~hold[a:b])[0]
        f, g = a + int(mv[0]), a + int(mv[-1])  # the first and the last moving segment
        if f > a:  # holds from the run's start: the first moving segment leaves from the start
            i[f] = i[a]
            keep[a:f] = False
        if g < b - 1:  # holds to the run's end: the last moving segment ends there
            j[g] = j[b - 1]
            keep[g + 1:b] = False
    if keep.all():
        return None
    return i[keep], j[keep]


#: :func:`merged_start_holds` is on (a switch for the tests)
START_HOLD_MERGE = True

#: :func:`merged_start_holds` merges at most this many holds into a move that starts from rest
START_HOLD_MAX_MERGES = 3

#: :func:`merged_start_holds` merges only where the move needs this many times its time from rest.
#: (A move a few per cent short, the pre-roll after a homing, ran later merged: the longer segment's
#: low feed capped the junction into the fast one after it, +0.030 -> +0.103 ms on arcs.gcode)
START_HOLD_SHORT = 1.2


def merged_start_holds(lim: ChainLimits, i: np.ndarray, j: np.ndarray, P: np.ndarray, srun: np.ndarray,
                       hold: np.ndarray, dry: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Segments ``i -> j`` (point indices into ``P``, mm, as printed) with the hold before a move
    that starts from rest merged into that move where the firmware cannot start it in its time, or
    None where there is none.

    A command that leaves rest slowly (a stream's pre-roll after a stop) moves less than a
    micrometre per sample at first: those samples are holds (``G4``), and the first segment that
    moves starts from rest with the distance the command covered while they stood.  It needs
    ``sqrt(2 d / a)`` at least at its acceleration limit ``a`` (Klipper's delta cap
    ``max_z_accel * d/|dz|`` on a z move): 3 um in 1 ms at 3,000 mm/s^2 took 1.41 ms, 0.43 ms late
    after a ``G10`` on other_delta.  Where it needs more than :data:`START_HOLD_SHORT` times its
    time, the last hold (dry, in the same run) is not a point: the move spans its time as well (the
    nozzle stood within a micrometre of its start), up to :data:`START_HOLD_MAX_MERGES` holds back
    while the move still cannot start in its time.
    ``srun``, ``hold``, ``dry`` (no extrusion), ``D`` (durations, s): per segment.
    """
    if not START_HOLD_MERGE:
        return None
    n = len(i)
    if n < 2:
        return None
    q = np.nonzero(~hold[1:] & hold[:-1] & dry[1:] & dry[:-1] & (srun[1:] == srun[:-1]))[0] + 1
    if not q.size:
        return None
    d = np.linalg.norm(P[j[q]] - P[i[q]], axis=1)
    acc = segment_limits(lim, P[i[q]], P[j[q]], np.zeros(q.size))[1]
    q = q[d > 0.5 * acc * (START_HOLD_SHORT * D[q]) ** 2]
    if not q.size:
        return None
    keep = np.ones(n, bool)
    i = i.copy()
    for m, d_m, a_m in zip(q.tolist(), d.tolist(), acc.tolist()):  # (few: one per start from rest)
        span, first = D[m], m
        for k in range(m - 1, max(m - 1 - START_HOLD_MAX_MERGES, -1), -1):
            if not (hold[k] and dry[k] and srun[k] == srun[m] and keep[k]):
                break
            keep[k] = False
            span += D[k]
            first = k
            if 2.0 * d_m <= a_m * span * span:
                break
        i[m] = i[first]
    return i[keep], j[keep]
