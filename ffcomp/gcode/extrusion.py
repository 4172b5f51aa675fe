"""How much filament each written segment extrudes: the source's ratios kept across the
compensated segments, and the ratio's changes kept within the extruder's junction limit.

Klipper slows the junction of two segments whose extrusion ratios ``e/d`` (mm of filament per mm
of XYZ travel) differ to ``instantaneous_corner_velocity / |diff_r|`` (1 mm/s by default).  The
compensated segments are not the source's: their extrusion starts from the reference's (the
extrusion of each segment's samples' time), which a few per cent of length difference near corners
and the command's lead or lag at a change of ratio turn into ratio steps between neighbouring
segments.  :func:`by_length` evens the ratio within a group of source moves of one ratio and
limits the steps at a group's start.  Pure numerics on per-segment arrays.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EDGE_SHARE", "EDGE_RETRACTING", "RATIO_STEP_SHARE", "PLAN_STEP_SLACK", "STEP_GAIN", "STEP_BACK_S",
           "BACK_RAMP", "flow_groups", "by_length", "limit_ratio_steps", "place_ratio_steps", "junction_loss_s",
           "extruder_capped"]

#: after a change of extrusion ratio, segments keep the extrusion of their reference time until its
#: ratio comes within this share of the group's (see :func:`by_length`)
EDGE_SHARE = 0.03

#: a group's change of ratio moves onto one junction where that costs the firmware less than this
#: share of the time the written ramp costs it (:func:`place_ratio_steps`)
STEP_GAIN = 0.5

#: how far before a group's start that junction may lie (in the previous group's last segments), s
STEP_BACK_S = 0.008

#: whether a retracting group keeps the reference-time extrusion at its start as well (its edge,
#: see :func:`by_length`).  Off since the thirty-fourth round: where the command leads or lags the
#: plan at a travel's start its reference-time ratios scatter (-0.05 .. -0.10 in a -0.074 group), and
#: those steps capped junctions at 60-110 mm/s (a random file on other_delta 0.58 ms off the clock);
#: a retraction lays no bead whose place the edge would keep.  Klipper only (``icv_mm_s`` given): on
#: Marlin it put 2 more of 40 random files beyond 0.2 ms (``bench_marlin_clock.py``).  (A switch for
#: the tests.)
EDGE_RETRACTING = False

#: the written ratio changes by at most this share of ``instantaneous_corner_velocity / v`` at a
#: junction the firmware passes at ``v`` (see :func:`limit_ratio_steps`)
RATIO_STEP_SHARE = 0.7

#: a group starting on a plan corner takes its change of ratio at once where the plan passes that
#: corner no faster than this times ``instantaneous_corner_velocity / diff_r`` (see :func:`by_length`)
PLAN_STEP_SLACK = 1.05


def extruder_capped(mv) -> bool:
    """Whether the extruder's limits apply to the planned move ``mv`` at all (Klipper's extruder
    ``check_move``: it retracts, or extrudes without XY travel: its speed and acceleration are then
    capped at the extruder's over ``|e/d|``); None (no move): False."""
    if mv is None:
        return False
    s, e = mv.start_mm, mv.end_mm
    de = e[3] - s[3]
    return bool(de != 0 and (de < 0 or (e[0] - s[0] == 0 and e[1] - s[1] == 0)))


def flow_groups(moves: list, rel_tol: float = 0.01) -> np.ndarray:
    """Group ids of consecutive motion runs whose source moves extrude at the same ratio (mm of
    filament per mm of XYZ travel, within ``rel_tol``; travel moves: 0): Klipper sees no extruder
    junction between such source moves, so their written segments share one ratio too."""
    r = np.array([((m.end_mm[3] - m.start_mm[3]) / max(float(np.linalg.norm(np.subtract(m.end_mm[:3], m.start_mm[:3]))),
                                                       1e-12)) if m is not None else np.nan for m in moves])
    same = np.abs(np.diff(r)) <= rel_tol * np.maximum(np.abs(r[1:]), np.abs(r[:-1]))
    return np.concatenate([[0], np.cumsum(~same)])


def by_length(de: np.ndarray, dist_mm: np.ndarray, group: np.ndarray, hold: np.ndarray,
              speed_mm_s: np.ndarray | None = None, icv_mm_s: float | None = None,
              capped: np.ndarray | None = None, e_limits: tuple[float, float] | None = None,
              corner_v_mm_s: np.ndarray | None = None,
              prev: tuple[float, float, float] | None = None,
              plan_v_mm_s: np.ndarray | None = None) -> np.ndarray:
    """Each group's extrusion shared among its segments in proportion to their written length.

    Klipper limits the junction of two segments whose extrusion ratios ``e/d`` differ to
    ``instantaneous_corner_velocity / |diff_r|`` (1 mm/s by default).  The reference gives each
    segment the extrusion of its samples' time, but the compensated segments' lengths differ from
    the reference path's over the same time by a few per cent at corners, so at high flow (0.1 mm of
    filament per mm) the ratios of neighbouring segments differ by ~0.005 and the firmware slows
    the junctions to ~200 mm/s, running late (or, after the feed solve, early).  Within a group
    (consecutive runs whose source moves share one ratio, :func:`flow_groups`) the source has no
    such junction, so the group's extrusion is spread by length: its total is unchanged, its
    junctions see ``diff_r = 0``.
    Holds (segments under a micrometre), the segments at a group's start whose own ratio has not
    yet come within ``EDGE_SHARE`` of the group's (the first spans the corner from the previous
    ratio; keeping them, the ratio changes over several junctions instead of at once; not in a
    retracting group, :data:`EDGE_RETRACTING`), and groups without length keep their own values.

    Parameters
    ----------
    de : (n,) extrusion of each segment over its samples' reference time, mm
    dist_mm : (n,) written length of each segment, mm
    group : (n,) non-decreasing group id of each segment (:func:`flow_groups` of its run)
    hold : (n,) segments written as holds
    speed_mm_s, icv_mm_s : each segment's intended mean speed and the firmware's
        ``instantaneous_corner_velocity``: if given, the ratio steps at a group's start are then kept
        within the junction limit (:func:`limit_ratio_steps`)
    capped, e_limits : see :func:`limit_ratio_steps`
    corner_v_mm_s : (n,) optional
        The speed (mm/s) the firmware's corner rule allows at each segment's start (``inf`` where
        it sets no limit: a straight line, a hold).  A group whose first junction is so slow already
        that its change of ratio costs nothing there (a reversal: the firmware stops) has no edge:
        its first segments take the group's ratio at once.  Kept at their reference-time
        extrusion instead, the segments leaving a reversal step their ratio at every junction while
        they speed up (a z move down, then up while retracting: 0.45 ms early on the way in, as the
        feed solve anticipated the lateness of the way out).
    prev : (ratio, length mm, speed mm/s), optional
        The segment the firmware runs at speed just before these (a previous chunk's last): see
        :func:`limit_ratio_steps`.
    plan_v_mm_s : (n,) optional
        The plan's own speed (mm/s) at each segment's start where that start is the plan's corner
        (NaN elsewhere).  A group that starts on a corner the plan itself passes no faster than its
        change of ratio allows (within :data:`PLAN_STEP_SLACK`: a travel into an extruding lift, the
        plan slowed to ``icv / diff_r``) takes its ratio there at once, as the plan does: ramped
        instead, the first step let the firmware through the corner faster than the plan, the next
        one braked it after the corner, where the plan speeds up, and its ratio above the group's
        lowered the extruder's acceleration cap (a random file on the default profile 0.55 ms off
        the clock).
    """
    de = np.asarray(de, float)
    if not len(de):
        return de
    g = np.asarray(group)
    n = len(g)
    hold = np.asarray(hold, bool)
    start = np.concatenate(([False], g[1:] != g[:-1]))
    _, gi = np.unique(g, return_inverse=True)
    # after a change of ratio (not at the chunk's start: the group may continue the last chunk's)
    # the segments keep their reference-time extrusion until its ratio comes within EDGE_SHARE
    ok_d = ~hold & (dist_mm > 1e-9)
    rho_g = np.bincount(gi, weights=np.where(ok_d, de, 0.0)) / np.maximum(
        np.bincount(gi, weights=np.where(ok_d, dist_mm, 0.0)), 1e-12)
    rho = np.where(ok_d, de / np.where(ok_d, dist_mm, 1.0), rho_g[gi])
    near = np.abs(rho - rho_g[gi]) <= EDGE_SHARE * np.abs(rho_g[gi])
    # the edge: from a group's first segment up to its first segment near the group's ratio
    step_ok = np.zeros(n, bool)  # a group's start where its change of ratio costs the firmware nothing
    if corner_v_mm_s is not None and icv_mm_s is not None and start.any():
        s_ = np.nonzero(start)[0]
        step = np.abs(rho_g[gi[s_]] - rho_g[gi[s_ - 1]])
        cv = np.asarray(corner_v_mm_s, float)[s_]
        step_ok[s_] = np.isfinite(cv) & (np.where(np.isfinite(cv), cv, 0.0) * step
                                         <= RATIO_STEP_SHARE * float(icv_mm_s))
        if plan_v_mm_s is not None:
            pv = np.asarray(plan_v_mm_s, float)[s_]
            step_ok[s_] |= np.isfinite(pv) & (np.where(np.isfinite(pv), pv, 0.0) * step
                                              <= PLAN_STEP_SLACK * float(icv_mm_s))
    near |= step_ok  # (the edge of such a group ends before it starts)
    reached = np.maximum.accumulate(np.where(near, np.arange(n), -1))
    first = np.maximum.accumulate(np.where(start, np.arange(n), -1))
    edge = (first >= 0) & (reached < first)
    if not EDGE_RETRACTING and icv_mm_s is not None:
        # a retraction lays no bead to place: its group's ratio is even from its start (Klipper's
        # junction rule; on Marlin, whose junctions weigh the extruder otherwise, the edge stays)
        edge &= ~(rho_g[gi] < 0)
    free = ~hold & ~edge
    tot_e = np.bincount(gi, weights=np.where(free, de, 0.0))
    tot_d = np.bincount(gi, weights=np.where(free, dist_mm, 0.0))
    ok = (tot_d > 1e-6)[gi] & free
    out = de.copy()
    out[ok] = tot_e[gi[ok]] * dist_mm[ok] / tot_d[gi[ok]]
    if speed_mm_s is not None and icv_mm_s is not None:
        out = limit_ratio_steps(out, dist_mm, np.asarray(speed_mm_s, float), g, hold, edge, float(icv_mm_s),
                                capped=capped, e_limits=e_limits, step_ok=step_ok, prev=prev)
    return out


def limit_ratio_steps(e: np.ndarray, dist_mm: np.ndarray, speed_mm_s: np.ndarray, group: np.ndarray,
                      hold: np.ndarray, edge: np.ndarray, icv_mm_s: float,
                      share: float = RATIO_STEP_SHARE, capped: np.ndarray | None = None,
                      max_shift: float = 0.1, e_limits: tuple[float, float] | None = None,
                      step_ok: np.ndarray | None = None,
                      prev: tuple[float, float, float] | None = None) -> np.ndarray:
    """Extrusions whose ratio changes from segment to segment no faster than the firmware's
    junction limit lets the segments keep their speed.

    Klipper passes the junction of two segments whose ratios differ by ``diff_r`` at no more than
    ``icv / |diff_r|``.  At a change of ratio (a travel into a print move) the written segments'
    ratios step from the old ratio to the new over the first few segments (their reference-time
    extrusion, :func:`by_length`), and where the command moves fast there, a step of 0.02 at
    150 mm/s caps the junction at 50 mm/s: the file ran 1-3 ms late.  Wherever a junction inside or
    at the start of a group would be capped below ``max(v_prev, v_next) / share``, the group's
    ratios from its start on are ramped instead: each step within ``share * icv / max(v_prev,
    v_next)``, towards the reference-time ratio on the group's first segments (``edge``) and the
    group's even ratio after them, which takes up the extrusion the ramp held back (a few passes), so
    the group's total is unchanged.  The firmware stops at a hold: the ramp starts afresh after it.
    A group that ends before its ramp does is scaled to its total instead.  A group whose even ratio
    would move by more than ``max_shift`` (relative) to take up the ramp's extrusion keeps
    :func:`by_length`'s values; so does a group holding segments the extruder's own limits cap
    (``capped``: extruding without XY travel, or retracting: Klipper caps those at
    ``max_extrude_only_velocity / |r|`` and ``max_extrude_only_accel / |r|``, so a higher ratio may
    run slower), unless ``e_limits`` = (``max_extrude_only_velocity``, ``max_extrude_only_accel``)
    shows those caps stay above twice each capped segment's speed and acceleration (estimated from
    the speed changes to its neighbours) at the new ratios.  Where a group's start keeps a step
    beyond the limit after that (a dry group after a retracting z move has no extrusion to take up
    a ramp: the even-ratio check above refuses it), the same ramp runs backwards over the end of
    the group before (:data:`BACK_RAMP`): its last segments step towards the new ratio, its even
    part takes up the difference, its start (edge, or the ramp at its own start) stays.  A
    retracting lift into a dry one, which the command passes at 17 mm/s where ``icv / |diff_r|``
    is 5.7, ran 2.2 ms off the clock with one step there.

    Parameters
    ----------
    e : (n,) extrusion of each segment (:func:`by_length`'s), mm
    dist_mm, speed_mm_s : (n,) each segment's written length (mm) and intended mean speed (mm/s)
    group, hold, edge : (n,) group ids (non-decreasing), holds, and a group's first segments that
        keep their reference-time extrusion
    icv_mm_s : the firmware's ``instantaneous_corner_velocity``, mm/s
    share : see :data:`RATIO_STEP_SHARE`
    capped : (n,) bool, optional
    max_shift : largest relative change of a group's even ratio
    e_limits : (mm/s, mm/s^2), optional
    step_ok : (n,) bool, optional
        Segments whose start junction may take any change of ratio (see :func:`by_length`): no
        limit there, and a ramp starts afresh after it.
    prev : (ratio, length mm, speed mm/s), optional
        The segment written before ``e[0]`` that the firmware joins to it at speed (the last of
        the writer's previous chunk, where the cut falls inside a group): the first group's ratio
        ramps from that segment's instead of stepping to its own even ratio at once.  The chunks'
        two parts of a group each take their own even ratio, which differ where the command's
        lead changes along the group: a retracting z move cut 50 samples before its rest stepped
        from 0.188 to 0.229 there, a junction capped at 24 mm/s in a 50 mm/s ramp, 5 ms late.
    """
    if prev is not None and len(e) and not hold[0]:
        def ahead(a, x):
            return None if a is None else np.r_[x, a]
        r0, d0, v0 = prev
        return limit_ratio_steps(np.r_[r0 * d0, e], np.r_[d0, dist_mm], np.r_[v0, speed_mm_s],
                                 np.r_[group[0] - 1, group], np.r_[False, hold], np.r_[False, edge],
                                 icv_mm_s, share, capped=ahead(capped, False), max_shift=max_shift,
                                 e_limits=e_limits, step_ok=ahead(step_ok, False))[1:]
    n = len(e)
    if n < 2 or icv_mm_s <= 0:
        return e
    hold = np.asarray(hold, bool)
    edge = np.asarray(edge, bool)
    out = _ramp_group_starts(e, dist_mm, speed_mm_s, group, hold, edge, icv_mm_s, share, capped, max_shift,
                             e_limits, step_ok)
    if not BACK_RAMP:
        return out
    # a change of ratio the ramp at the new group's start could not take (a travel after a
    # retracting z move: a dry group has no extrusion to take up the ramp's) is ramped at the end
    # of the group before instead: the same ramp on the reversed segments (for a group whose own
    # steps are within the limit)
    ok, r, _, lim = _junction_limits(out, dist_mm, speed_mm_s, hold, icv_mm_s, share, step_ok)
    starts = np.nonzero(group[1:] != group[:-1])[0] + 1
    left = starts[ok[starts] & ok[starts - 1] & (np.abs(r[starts] - r[starts - 1]) > lim[starts - 1] * 1.0001)]
    if not left.size:
        return out
    prev_start = np.maximum.accumulate(np.where(np.r_[True, group[1:] != group[:-1]], np.arange(n), 0))
    only = np.zeros(n, bool)  # (reversed) the last segment of each group to ramp at its end
    keep = edge.copy()  # and the segments the ramp there leaves as they are
    spans = []

    def inside_ok(x, g0, g1, slack):
        rx = np.where(ok[g0:g1], x[g0:g1] / np.where(ok[g0:g1], dist_mm[g0:g1], 1.0), 0.0)
        inner = ok[g0:g1 - 1] & ok[g0 + 1:g1]
        return not np.any(inner & (np.abs(np.diff(rx)) > lim[g0:g1 - 1] * slack))

    for g1 in left.tolist():
        g0 = int(prev_start[g1 - 1])
        if not inside_ok(out, g0, g1, 1.0001):
            continue  # (a group with steps beyond the limit inside: not one the ramps could settle)
        only[g1 - 1] = True
        spans.append((g0, g1))
        # the group's start up to where its ratio reaches the one it ends on (its edge, or the
        # ramp at its start) stays; the even part after it takes up the ramp at its end
        even = ok[g0:g1] & (np.abs(r[g0:g1] - r[g1 - 1]) <= 1e-9 * max(abs(r[g1 - 1]), 1e-12))
        keep[g0:g0 + (int(np.argmax(even)) if even.any() else g1 - g0)] = True
    if not only.any():
        return out
    rev = slice(None, None, -1)
    back = _ramp_group_starts(out[rev], dist_mm[rev], speed_mm_s[rev], -group[rev], hold[rev], keep[rev],
                              icv_mm_s, share, None if capped is None else np.asarray(capped)[rev], max_shift,
                              e_limits, None if step_ok is None else np.r_[False, np.asarray(step_ok, bool)[::-1][:-1]],
                              only=only[rev])
    back = np.ascontiguousarray(back[rev])
    for g0, g1 in spans:  # where the ramp at the end met the kept start with a step, the group stays
        if not inside_ok(back, g0, g1, 1.1):
            back[g0:g1] = out[g0:g1]
    return back


#: :func:`limit_ratio_steps` ramps a change of ratio at the end of the group before where the new
#: group cannot take the ramp (a switch for the tests)
BACK_RAMP = True


def _junction_limits(e, dist_mm, speed_mm_s, hold, icv_mm_s, share, step_ok):
    """The moving segments (not holds, with length), their ratios and speeds (0 elsewhere), and each
    junction's limit on the change of ratio, ``share * icv / max(v_prev, v_next)`` (``inf`` where
    ``step_ok`` marks the later segment): junction ``j`` joins segments ``j`` and ``j + 1``."""
    ok = ~hold & (dist_mm > 1e-9)
    r = np.where(ok, e / np.where(ok, dist_mm, 1.0), 0.0)
    v = np.where(ok, speed_mm_s, 0.0)
    lim = share * icv_mm_s / np.maximum(np.maximum(v[1:], v[:-1]), 1e-9)
    if step_ok is not None:
        lim = np.where(np.asarray(step_ok, bool)[1:], np.inf, lim)
    return ok, r, v, lim


def _ramp_group_starts(e, dist_mm, speed_mm_s, group, hold, edge, icv_mm_s, share, capped, max_shift, e_limits,
                       step_ok, only: np.ndarray | None = None) -> np.ndarray:
    """:func:`limit_ratio_steps`' ramps at the groups' starts (``only``: just at the starts marked
    there); the input array where nothing changed."""
    n = len(e)
    ok, r, v, lim = _junction_limits(e, dist_mm, speed_mm_s, hold, icv_mm_s, share, step_ok)
    bad = ok[1:] & ok[:-1] & (np.abs(np.diff(r)) > lim * 1.0001)
    if not bad.any():
        return e
    out = e.copy()
    starts = np.nonzero(np.r_[True, group[1:] != group[:-1]])[0]
    for g0, g1 in zip(starts.tolist(), np.r_[starts[1:], n].tolist()):
        if only is not None and not only[g0]:
            continue
        cap_g = capped is not None and bool(capped[g0:g1].any())
        if not bad[max(g0 - 1, 0):g1 - 1].any() or (cap_g and e_limits is None):
            continue
        seg = np.arange(g0, g1)
        mov = ok[g0:g1]
        total = float(out[g0:g1][mov].sum())
        free = mov & ~edge[g0:g1]
        rho = float(r[g0:g1][free][0]) if free.any() else None  # the group's even ratio (by_length)
        rho0 = rho
        new = out[g0:g1].copy()
        settled = False  # the hand-over from the ramp to the group's even ratio within the limit
        for _ in range(4):
            new = out[g0:g1].copy()
            # (the group before as written: the ramp may have changed it)
            rp = out[g0 - 1] / dist_mm[g0 - 1] if g0 > 0 and ok[g0 - 1] else None
            reached = None
            for q, idx in enumerate(seg.tolist()):
                if not ok[idx]:
                    if hold[idx]:
                        rp = None
                    continue
                want = rho if (free[q] and rho is not None) else r[idx]
                if rp is not None and idx > 0 and ok[idx - 1]:
                    c = lim[idx - 1]
                    want = min(max(want, rp - c), rp + c)
                new[q] = want * dist_mm[idx]
                rp = want
                if free[q] and want == rho:
                    reached = q
                    break
            if reached is None:
                break
            after = np.zeros(len(seg), bool)
            after[reached + 1:] = free[reached + 1:]
            d_after = float(dist_mm[g0:g1][after].sum())
            if d_after <= 1e-9:
                reached = None
                break
            rest = total - float(new[:reached + 1][mov[:reached + 1]].sum())
            rest -= float(new[reached + 1:][mov[reached + 1:] & ~after[reached + 1:]].sum())
            rho_new = rest / d_after
            new[after] = rho_new * dist_mm[g0:g1][after]
            if abs(rho_new - rho) <= 0.1 * lim[g0 + reached]:  # (the step there stays within the limit)
                settled = True
                break
            rho = rho_new
        if reached is None:  # the ramp outlasts the group: keep its shape, scale it to the total
            s_ = float(new[mov].sum())
            if abs(s_) <= 1e-12 or abs(total / s_ - 1.0) > max_shift:
                continue
            new[mov] *= total / s_
        elif not settled or (rho0 is not None and abs(rho - rho0) > max_shift * abs(rho0)):
            continue  # (the passes did not settle: a step at the hand-over would break the limit)
        if cap_g:  # the extruder's caps at the new ratios must stay clear of the segments' motion
            c_ = capped[g0:g1] & mov
            rn = np.abs(new[c_]) / dist_mm[g0:g1][c_]
            vmax, amax = e_limits
            # each segment's acceleration, from the speed change to its neighbours over their times
            vg = v[g0:g1]
            tg = dist_mm[g0:g1] / np.maximum(vg, 1e-9)
            dv = np.abs(np.diff(vg)) / np.maximum(0.5 * (tg[1:] + tg[:-1]), 1e-9)
            acc = np.maximum(np.r_[0.0, dv], np.r_[dv, 0.0])
            if np.any(rn * 2.0 * vg[c_] > vmax) or np.any(rn * 2.0 * acc[c_] > amax):
                continue
        out[g0:g1] = new
    return out


def junction_loss_s(v_mm_s, cap_mm_s, acc_mm_s2):
    """Time (s) the firmware loses where it must pass a junction at ``cap`` instead of ``v``: it brakes
    to ``cap`` and accelerates back at ``acc``, ``(v - cap)^2 / (acc v)`` (nothing where ``cap >= v``)."""
    dv = np.maximum(np.asarray(v_mm_s, float) - cap_mm_s, 0.0)
    return dv * dv / np.maximum(np.asarray(acc_mm_s2, float) * np.maximum(v_mm_s, 1e-9), 1e-12)


def place_ratio_steps(e: np.ndarray, dist_mm: np.ndarray, speed_mm_s: np.ndarray, acc_mm_s2: np.ndarray,
                      group: np.ndarray, hold: np.ndarray, icv_mm_s: float, capped: np.ndarray | None = None,
                      back_s: float = STEP_BACK_S, gain: float = STEP_GAIN, max_shift: float = 0.1) -> np.ndarray:
    """Each change of extrusion ratio moved onto the one junction where the firmware loses least.

    Klipper passes a junction whose ratios differ by ``diff_r`` at no more than ``icv / |diff_r|``.
    Where a travel runs into a print move, the source's ratio jumps at the corner, where the plan
    slows to that limit; the compensated command passes its corner faster and leads the reference
    by a few milliseconds, so the reference-time extrusion of its first segments ramps the ratio up
    over several junctions at growing speed (:func:`by_length`'s edge, or
    :func:`limit_ratio_steps`' ramp), and each of them caps the firmware: the file ran up to 0.8 ms
    early and then late, 57 um off the command, on a random file on the default profile.  A step
    costs the firmware about ``(v - cap)^2 / (a v)`` (:func:`junction_loss_s`) at the junction's
    speed ``v`` (the slower segment's) and acceleration ``a``, so one step where the command runs
    slowest (near its corner) costs far less than a ramp where it speeds up.

    For every group start that is not at a hold (the firmware stops there: a step costs nothing), the
    zone from up to ``back_s`` before the start (the previous group's last moving segments) to where
    the group's ratio settles is given the previous ratio up to one junction and the group's after
    it, the junction chosen to lose least; the group's extrusion after the zone is scaled so that
    the total from the zone's start to the group's end is unchanged (into a travel: the previous
    ratio up to the junction is scaled instead, the travel extrudes nothing).  This replaces the
    written values only where it loses less than ``gain`` times what they lose, moves no ratio by
    more than ``max_shift`` (relative), and leaves zones with holds or segments the extruder's own
    limits cap (``capped``) alone.  The extruded placement moves by at most the zone: the bead
    starts where the command turns, a few milliseconds before the reference does.

    Parameters
    ----------
    e : (n,) extrusion of each segment as it would be written (:func:`by_length`'s), mm
    dist_mm, speed_mm_s, acc_mm_s2 : (n,) each segment's written length (mm), intended mean speed
        (mm/s) and the firmware's acceleration on it (mm/s^2, :func:`~ffcomp.gcode.chain_plan.segment_limits`)
    group, hold : (n,) group ids (non-decreasing, :func:`flow_groups`) and holds
    icv_mm_s : the firmware's ``instantaneous_corner_velocity``, mm/s
    capped : (n,) bool, optional; back_s : s; gain, max_shift : see above

    Returns
    -------
    ndarray, (n,): the extrusions, mm (the input array where nothing changed)
    """
    e = np.asarray(e, float)
    n = len(e)
    if n < 3 or icv_mm_s <= 0:
        return e
    hold = np.asarray(hold, bool)
    ok = ~hold & (dist_mm > 1e-9)
    v = np.where(ok, speed_mm_s, 0.0)
    dt = np.where(ok, dist_mm / np.maximum(v, 1e-9), 0.0)
    jv = np.minimum(v[:-1], v[1:])  # junction k: segments k | k + 1 (0 next to a hold: a stop)
    ja = np.minimum(acc_mm_s2[:-1], acc_mm_s2[1:])

    def f(k, dr):  # loss at junctions k for ratio steps dr
        return junction_loss_s(jv[k], icv_mm_s / np.maximum(np.abs(dr), 1e-12), ja[k])

    out = e
    starts = np.nonzero(group[1:] != group[:-1])[0] + 1
    # what every junction loses as written: transitions that lose nothing are skipped at once
    r = np.where(ok, e / np.where(ok, dist_mm, 1.0), 0.0)
    lost = np.r_[0.0, np.cumsum(f(np.arange(n - 1), np.diff(r)))]
    changed_upto = -1  # (the losses above are stale below this segment)
    for g0, g1 in zip(starts.tolist(), np.r_[starts[1:], n].tolist()):
        if not (ok[g0 - 1] and ok[g0]):
            continue
        z0, t = g0, 0.0  # segment z0 - 1 stays as written: moving, of the previous group
        while z0 >= 2 and ok[z0 - 2] and group[z0 - 2] == group[g0 - 1] and t + dt[z0 - 1] <= back_s:
            t += dt[z0 - 1]
            z0 -= 1
        L = z0 - 1
        if changed_upto <= L and lost[min(g1, n - 1)] - lost[L] <= 0.0:
            continue
        r = np.where(ok, out / np.where(ok, dist_mm, 1.0), 0.0)
        last = g0 + int(np.nonzero(ok[g0:g1])[0][-1])
        rb = r[last]
        tol = 1e-3 * abs(rb) + 1e-9
        off = np.nonzero(ok[g0:g1] & (np.abs(r[g0:g1] - rb) > tol))[0]
        z1 = g0 + int(off[-1]) + 1 if off.size else g0
        if not ok[g0:z1].all() or (capped is not None and capped[z0:g1].any()):
            continue
        ra = r[L]
        if ra == 0.0 and rb == 0.0:
            continue
        # candidates m = L .. z1 - 1: segments z0..m at the previous ratio, m + 1.. at the group's
        m = np.arange(L, z1)
        d_a = np.r_[0.0, np.cumsum(dist_mm[z0:z1])]  # D_a(m) = d_a[m - L]
        into_travel = abs(rb) <= 0.01 * abs(ra)  # (what a travel carries is rounding and spill)
        if not into_travel:
            okb = ok[z0:g1]
            T = float(out[z0:g1][okb].sum())
            D = float(dist_mm[z0:g1][okb].sum())
            Db = D - d_a
            with np.errstate(divide="ignore", invalid="ignore"):
                rb_m = np.where(Db > 1e-9, (T - ra * d_a) / Db, np.nan)
            ra_m = np.full(len(m), ra)
            loss = f(m, rb_m - ra)
            if g1 < n:
                loss = loss + f(np.full(len(m), g1 - 1), r[g1] - rb_m)
            okg = ok[g0:g1]
            r_avg = float(out[g0:g1][okg].sum() / dist_mm[g0:g1][okg].sum())  # the group's own ratio
            good = np.isfinite(rb_m) & (np.abs(rb_m / r_avg - 1.0) <= max_shift)
            hi = min(g1, n - 1)
        else:
            T = float(out[z0:z1].sum())
            with np.errstate(divide="ignore", invalid="ignore"):
                ra_m = np.where(d_a > 1e-9, T / d_a, np.nan)
            rb_m = np.zeros(len(m))
            loss = f(np.full(len(m), L), ra_m - ra) + f(m, ra_m)
            good = np.isfinite(ra_m) & (np.abs(ra_m / ra - 1.0) <= max_shift)
            hi = z1
        if not good.any():
            continue
        cur = float(np.sum(f(np.arange(L, hi), np.diff(r[L:hi + 1]))))
        # (near-ties go to the junction nearest the group's start: the source's own corner)
        q = int(np.argmin(np.where(good, loss * (1.0 + 0.02 * np.abs(m - (g0 - 1))), np.inf)))
        if not loss[q] < gain * cur:
            continue
        mq = int(m[q])
        new = out.copy()
        new[z0:mq + 1] = ra_m[q] * dist_mm[z0:mq + 1]
        if not into_travel:
            sel = np.arange(mq + 1, g1)
            sel = sel[ok[sel]]
            new[sel] = rb_m[q] * dist_mm[sel]
        else:
            new[mq + 1:z1] = 0.0
        out = new
        changed_upto = g1
    return out
