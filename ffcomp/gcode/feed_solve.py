"""Feed rates that make Klipper run a chain of G1 segments on the intended absolute clock.

The writer gives every segment an intended duration (the time between its two compensated samples).
Klipper, though, enters and leaves each segment at junction speeds and ramps at its acceleration
limits (the delta's ``max_z_accel * d/|dz|`` among them), so ``F = length / duration`` runs late,
and the lateness adds up over a file.  :func:`solve_feeds` instead closes the loop on the absolute
clock: it plans the written chain as Klipper will (:func:`ffcomp.gcode.chain_plan.plan_chain`),
compares every segment's end with its intended time and corrects the feed rates, a few sweeps over
the chunk.  A segment asked to start late (because one before it could not be run in its time, e.g.
a catch-up from rest) is asked to be shorter by that much, so lateness never accumulates: it is
recovered as soon as the limits allow.  The chain's last segments stay open (their exit speed
depends on the next chunk): they are re-planned, feeds fixed, together with the next chunk.

Where those rounds leave the chain off the clock at speed, a joint solve follows (:func:`_refine`:
Gauss-Newton on all the feeds at once; where only a stretch of a long chain is off, on the feeds
around it).  Its cost weighs each segment end's lateness by the speed
there (:func:`clock_weights`): lateness times speed is the distance from the intended command at
the same instant, so a millisecond spent where the command nearly stands still (the apex of a z
reversal at ``max_z_accel``, which the firmware must take slower than the command does) is left
there rather than spread over the fast segments around it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix, issparse
from scipy.sparse.linalg import LinearOperator, lsqr

from .chain_plan import ChainLimits, junction_v2, plan_chain, segment_limits

__all__ = ["TimingState", "solve_feeds", "dwell_as_written", "extrude_only_feed", "extrude_only_time"]

#: written segments kept open for the next chunk's plan
TAIL = 48
#: sweeps of the feed correction
SWEEPS = 8
#: rounds of handing lateness on to the segments after one that could not take its share
RECOVERY_ROUNDS = 3
#: rounds of waiting out time gained ahead of the clock
AHEAD_ROUNDS = 3
#: rounds of spreading the lateness of a stretch over its first segments
BEHIND_ROUNDS = 3
#: segments that share the wait when a stretch starts ahead of the clock
AHEAD_SPREAD = 24
#: a fixed run's first segment that ends at least this far ahead of the clock (s) has the free
#: segment before it wait (:func:`_wait_before_fixed`)
FIXED_AHEAD_MIN_S = 2e-5
#: rounds of it (each on what the last left)
FIXED_AHEAD_ROUNDS = 2
#: the share of that lead the segment before the run takes
FIXED_AHEAD_SHARE = 0.5
#: rounds of starting a stretch that stays late early instead, and the lateness that calls for it (s)
ANTICIPATE_ROUNDS = 2
ANTICIPATE_MIN_S = 1e-4
#: the share of the stretch's peak lateness it starts early by
ANTICIPATE_SHARE = 0.5
#: a segment is never asked to run in less than this share of its intended time (nor the
#: feed raised beyond 1 / this of the plain length / duration)
MIN_SHARE = 0.4
#: a segment next to a full stop runs as fast as it can when that is at least this share of its
#: intended time (the limits hold it near its time anyway: a ramp at the acceleration limit)
STOP_FAST_SHARE = 0.85
#: Gauss-Newton refinement of the rounds' feeds (:func:`_refine`): at most ``REFINE_ITERS``
#: iterations, where the rounds leave more than ``REFINE_MIN_MM`` of RMS lateness times speed
#: (:func:`clock_weights`, floored at ``REFINE_V0`` mm/s); the Jacobian of the durations counts
#: ``REFINE_BAND`` segments on either side of a feed (its reach through the junction speeds);
#: chains of at most ``REFINE_DENSE`` free segments are solved densely, longer ones by LSQR
REFINE_ITERS = 4
REFINE_MIN_MM = 2e-3
#: where the chain's RMS stays below ``REFINE_MIN_MM`` but a segment end is more than
#: ``REFINE_PEAK_MM`` off (lateness times speed, mm), the refinement frees only the feeds within
#: ``REFINE_LOCAL`` segments of such ends (one stretch off the clock in a long chain: a corner into
#: a lift at ``max_z_accel``, which the RMS of the chain dilutes; 1e-3 mm halved the RMS lateness
#: again for 4 % of the run's time on the plate, the largest no lower), each stretch planned as a
#: sub-chain ``REFINE_MARGIN`` segments longer either side (:func:`_refine_stretches`; 12 left a
#: lift's ramp on ringing_tower_prusa 0.4 ms late, the speeds at a nearer edge fixed too soon)
REFINE_PEAK_MM = 2e-3
#: the refinement's objective also charges every segment end more than ``HINGE_S`` off the clock
#: for the excess, weighted as ``HINGE_MM_S`` (mm/s; :func:`refine_objective`): a stretch the
#: limits cannot run in its time (a lift's top turning into its travel on a printer with a low
#: ``max_z_accel``) then splits its lateness between the ends either side instead of putting
#: most of it where the nozzle is slow (-0.24 / +0.08 ms at a ringing tower's lift top on
#: other_delta); a chain whose ends stay within ``HINGE_S`` is solved as before
HINGE_S = 1.2e-4
HINGE_MM_S = 2000.0
#: the hinge on open chains too (a chunk's last chain, whose tail the next chunk solves again).
#: Off: there it took a Klipper user's tower on other_delta from -0.219 / +0.232 to -0.287 /
#: -0.329 ms (how the next chunk's solve of that tail joins it was not traced), and closed chains
#: alone take the random files as far (other_delta 5 -> 3 of 40 above 0.2 ms)
HINGE_OPEN_CHAINS = False
#: a whole chain's hinged refinement (:func:`_hinged`) may raise its largest lateness times speed
#: (about the distance from the intended command, mm) by this factor at most (or to
#: ``2 REFINE_PEAK_MM``)
HINGE_COST_GROWTH = 1.25
REFINE_LOCAL = 24
REFINE_MARGIN = 48
#: (25 mm/s since the twenty-first round, 10 before: where the command nearly stands still, a
#: millisecond off the clock cost so little that the solve left up to 0.6 ms there, beyond the
#: 0.2 ms the clock must keep; at 25 the random files' median drift on other_delta fell 0.078 ->
#: 0.046 ms and every sample file's moved towards 0, their distance from the command the same)
REFINE_V0 = 25.0
REFINE_BAND = 12
REFINE_DENSE = 600
#: chains of at most this many segments get the refinement's Jacobian by one batched plan of every
#: free feed perturbed (:func:`_duration_jacobian`); longer ones banded (:func:`_banded_jacobian`)
DENSE_JACOBIAN = 160
#: the gentle take-back of a stretch left off the clock (:func:`_take_back`): each free segment
#: takes back at most this share of its intended time, a few rounds, where more than
#: ``TAKEBACK_MIN_S`` is left
TAKEBACK_SHARE = 0.1
TAKEBACK_ROUNDS = 3
TAKEBACK_MIN_S = 2e-5


@dataclass
class TimingState:
    """What the solve carries from one chunk to the next, and its running statistics."""

    late_s: float = 0.0  #: lateness at the end of what is written (s; open tail: provisional)
    #: the open tail: start, end (n, 3), extrusion, feed (mm/s), intended duration (s)
    tail: tuple | None = None
    tail_late_s: float = 0.0  #: lateness at the tail's start
    tail_v2: float = 0.0  #: entry speed squared of the tail's first segment


def dwell_as_written(t_s: float) -> float:
    """A dwell (s) as the writer prints it: ``G4 P`` in ms with three decimals, so to the microsecond.

    The timing state must carry the written value: a microsecond rounded off at every retraction
    added up to +0.16 ms of drift over the 3.35 h plate (the writer believed itself on time).
    """
    return round(t_s * 1e6) / 1e6


def extrude_only_feed(de: np.ndarray, t: np.ndarray, accel: float, vmax: float) -> np.ndarray:
    """Feed (mm/s) that makes an extruder-only move of ``|de|`` from rest to rest last ``t``.

    From rest to rest at acceleration ``accel``: ``t = |de| / v + v / accel`` for ``v^2 <= accel |de|``;
    the smaller root is the one with a cruise.  Where ``t`` is too short, the triangle's peak speed.
    """
    L = np.abs(de)
    disc = (t * accel) ** 2 - 4.0 * accel * L
    v = np.where(disc >= 0, 0.5 * (t * accel - np.sqrt(np.maximum(disc, 0.0))), np.sqrt(accel * L))
    return np.clip(v, 1e-3, vmax)


def extrude_only_time(de: np.ndarray, v: np.ndarray, accel: float) -> np.ndarray:
    """Duration (s) of extruder-only moves of ``|de|`` at feed ``v`` from rest to rest."""
    L = np.abs(de)
    v = np.minimum(v, np.sqrt(accel * L))
    return L / v + v / accel


def _lateness(t: np.ndarray, D: np.ndarray, late0: float) -> tuple[np.ndarray, np.ndarray]:
    """Lateness (s) on the absolute clock at each segment's end and at its start, for planned
    durations ``t``, intended ``D`` and ``late0`` on entry."""
    at_end = late0 + np.cumsum(t - D)
    return at_end, np.concatenate([[late0], at_end[:-1]])


def _solve_chain(lim: ChainLimits, P0, P1, de, D, free, late0, start_v2, end_open, F0):
    """Feeds of one chain (segments not free keep ``F0``); returns feeds, the lateness at each
    segment end and the entry speeds.

    1. Every free segment's feed is corrected towards its own intended duration (a few sweeps:
       the junctions couple neighbours only weakly); time gained ahead on entry is waited out by
       the first segment.
    2. Segments that cannot be run in their time (the limits bind) leave lateness, which the
       segments after them take back as fast as they can run (at most ``1 / MIN_SHARE`` times
       their plain speed): the queue recursion ``L_i = max(0, L_{i-1} + lo_i - D_i)`` over the
       fastest durations ``lo``, solved in closed form; a few sweeps aim every segment at its
       share; a segment that fell short hands the rest on in the next round.  A round is kept
       only if it lowers the summed squared lateness.
    3. Stretches that ended up ahead of the clock (a recovery overshot) are waited out.
    4. After the joint refinement (:func:`_refine`), what is still off the clock after the worst
       spot is taken back gently (:func:`_take_back`).

    Throughout, the two segments on either side of a full stop inside the chain (a reversal: the
    junction speed is zero) run as fast as they can where the limits hold them near their time
    anyway (:data:`STOP_FAST_SHARE`).  Aimed at their own intended time instead, the segment into
    the stop cruises slower than it could and caps the junction before it, and the one out of it
    leaves the next at a speed the acceleration limit never makes up: a z reversal at
    ``max_z_accel`` ran 0.23 ms late that way.
    """
    d = P1 - P0
    dist = np.sqrt(np.einsum("ij,ij->i", d, d))
    vmax, acc = segment_limits(lim, P0, P1, de)
    unit = d / dist[:, None]
    jv = np.concatenate([[np.inf], junction_v2(lim, unit, de / dist, acc, 2.0 * dist * acc)])
    Fmax = dist / (MIN_SHARE * D)

    def plan(F):
        cv2 = np.minimum(F, vmax) ** 2
        return plan_chain(dist, cv2, acc, jv, start_v2, cv2[..., -1] if end_open else 0.0)  # (F: (..., n))

    def sweeps(F, want, n, floor=None):
        for _ in range(n):
            t = plan(F)[0]
            F = np.where(free, np.clip(F * (t / want), 1e-3, Fmax), F)
            if floor is not None:  # recovering: never slower than on the plain clock
                F = np.maximum(F, floor)
        return F

    # ahead of the clock on entry (an extruder-only move written faster than planned): the first
    # free segment waits it out
    fast_ = _stop_rule(plan, free, jv, Fmax, vmax, F0, D)
    wantA = D.copy()
    if late0 < 0 and free.any():
        k = int(np.argmax(free))
        wantA[k] -= late0
    F = FA = sweeps(F0.copy(), fast_(wantA), SWEEPS // 2)
    # the fastest each segment can run (all free segments at their fastest: the junction rules
    # and the limits still bind), then the queue recursion for the lateness left after each one
    # when every late segment runs as fast as it can: L_i = max(0, L_{i-1} + lo_i - D_i)
    lo = plan(np.where(free, np.minimum(Fmax, vmax), F))[0]

    def cost(t_):  # of the planned durations t_: the squared lateness at every segment end
        return float(np.sum((late0 + np.cumsum(t_ - D)) ** 2))

    best_plan = plan(F)
    best, best_cost = F, cost(best_plan[0])
    for _ in range(RECOVERY_ROUNDS):
        S = late0 + np.cumsum(lo - D)
        L = S - np.minimum(0.0, np.minimum.accumulate(S))
        L_prev = np.concatenate([[late0], L[:-1]])
        want = fast_(np.maximum(D + L - L_prev, lo))
        if not np.any(np.abs(want - D) > 1e-9):
            break
        FB = sweeps(best, want, SWEEPS // 2, floor=FA)
        pB = plan(FB)
        t = pB[0]
        c = cost(t)
        # keep the recovery only where it helps (the junctions couple the segments, so the
        # fastest durations are estimates); a segment that fell short of its share was slower
        # than estimated: the next round hands the rest on
        if c < best_cost:
            best, best_cost, best_plan = FB, c, pB
        short = free & (t > want * (1 + 1e-3) + 1e-7)
        if not short.any():
            break
        lo = np.where(short, np.maximum(lo, t), lo)
    # ahead of the clock somewhere (a recovery overshot): the first segment of each stretch that
    # starts ahead waits it out, a few rounds
    for _ in range(AHEAD_ROUNDS):
        t_best = best_plan[0]
        late_end, ls = _lateness(t_best, D, late0)
        ahead = free & (ls < -1e-5)
        first = ahead & ~np.concatenate(([False], ahead[:-1]))
        if not first.any():
            break
        # two ways: the first segment waits it all, or the first AHEAD_SPREAD segments share it
        # (a short segment cannot take much longer than planned without braking harder than the
        # limits allow: sample-by-sample segments where max_z_accel binds)
        idx = np.arange(len(D))
        start_of = np.maximum.accumulate(np.where(first, idx, 0))
        spread = ahead & (idx - start_of < AHEAD_SPREAD)
        d_sum = np.bincount(start_of[spread], weights=D[spread], minlength=len(D))[start_of]
        extra = np.where(spread, -ls[start_of] * D / np.maximum(d_sum, 1e-12), 0.0)
        kept = False
        for want in (np.where(first, D - ls, t_best), t_best + extra):
            FC = sweeps(best, fast_(want), SWEEPS // 2)
            pC = plan(FC)
            c = cost(pC[0])
            if c < best_cost:
                best, best_cost, best_plan, kept = FC, c, pC, True
                break
        if not kept:
            break
    # behind the clock for a stretch the recovery above left alone (the queue asks the first
    # segments for their fastest, which short segments cannot reach without accelerating harder
    # than the limits allow, and the round is dropped): the first AHEAD_SPREAD segments of the
    # stretch each take back a share, the latest stretches first, one at a time
    for _ in range(BEHIND_ROUNDS):
        t_best = best_plan[0]
        late_end, ls = _lateness(t_best, D, late0)
        behind = free & (ls > 1e-5)
        first = np.nonzero(behind & ~np.concatenate(([False], behind[:-1])))[0]
        if not first.size:
            break
        k = int(first[np.argmax(ls[first])])
        end = k + 1
        while end < len(D) and end - k < AHEAD_SPREAD and behind[end]:
            end += 1
        want = t_best.copy()
        want[k:end] -= ls[k] * D[k:end] / np.sum(D[k:end])
        FC = sweeps(best, fast_(np.maximum(want, MIN_SHARE * D)), SWEEPS // 2)
        pC = plan(FC)
        c = cost(pC[0])
        if c >= best_cost:
            break
        best, best_cost, best_plan = FC, c, pC
    # a stretch the limits keep late however fast it is asked to run (a steep corner at
    # max_z_accel) starts early instead, by up to half its peak: the segments before it run ahead
    # of the clock, and the largest lateness either way halves; kept only where it falls
    for _ in range(ANTICIPATE_ROUNDS):
        t_best = best_plan[0]
        late_end = late0 + np.cumsum(t_best - D)
        p = int(np.argmax(late_end))
        peak = float(late_end[p])
        if peak < ANTICIPATE_MIN_S:
            break
        s = p
        while s > 0 and late_end[s - 1] > 0.1 * peak:
            s -= 1
        a = max(0, s - AHEAD_SPREAD)
        w = np.where(free[a:s], D[a:s], 0.0)
        if not w.any():
            break
        want = t_best.copy()
        want[a:s] -= ANTICIPATE_SHARE * peak * w / w.sum()
        FC = sweeps(best, fast_(np.maximum(want, MIN_SHARE * D)), SWEEPS // 2)
        pC = plan(FC)
        if np.max(np.abs(late0 + np.cumsum(pC[0] - D))) >= np.max(np.abs(late_end)) - 1e-6:
            break
        best, best_cost, best_plan = FC, cost(pC[0]), pC
    if REFINE_ITERS and free.any():
        w = clock_weights(dist, D)
        hi = np.minimum(Fmax, vmax)
        off = np.abs(w * (late0 + np.cumsum(best_plan[0] - D)))
        if float(np.sqrt(np.mean(off**2))) > REFINE_MIN_MM:
            best, best_plan = _refine(plan, best, best_plan, free, D, late0, hi, w)
            if HINGE_OPEN_CHAINS or not end_open:
                best, best_plan = _hinged(plan, best, best_plan, free, D, late0, hi, w)
        elif np.any(off > REFINE_PEAK_MM):
            best, best_plan = _refine_stretches(plan, dist, vmax, acc, jv, best, best_plan, free, off, D, late0,
                                                hi, w)
    if free.any():
        w = clock_weights(dist, D)
        best, best_plan = _take_back(plan, sweeps, fast_, best, best_plan, free, D, late0, w)
        best, best_plan = _wait_before_fixed(plan, sweeps, fast_, best, best_plan, free, D, late0, w)
    t, vin, _ = best_plan
    return best, late0 + np.cumsum(t - D), vin


def _wait_before_fixed(plan, sweeps, fast_, best, best_plan, free, D, late0, w):
    """A run of segments at fixed feeds (the plan's own speeds where a limit binds: a lift at
    ``max_z_accel``) that ends its first segment ahead of the clock gets part of that wait from the
    free segment just before it.

    The run follows the plan from the plan's corner, but the writer's point there sits on the
    sample before the corner's time: the first fixed segment covers only the rest of its sample
    and ends early, and its fixed feed cannot wait.  The whole run then stays ahead until a free
    segment after it waits it out (a layer change's lift after a printed line, Slic3r's ringing
    tower on the default profile: 0.23 ms early over a 10 ms lift, at 32 mm/s).  The free segment
    before the corner takes :data:`FIXED_AHEAD_SHARE` of the lead and the free segment after the
    run gives back as much of the wait it took: the corner (slow) comes a little late, the run a
    little early.  It runs last, on what the joint refinement and the take-back left (they put
    most such corners right themselves; run before them, the rule sent a quarter of the tower's
    chains to worse optima), and is kept only where the lateness weighted by speed (``w``,
    :func:`clock_weights`: about the distance it costs) falls.
    """
    if free.all():  # (no fixed run; the caller runs it only where some segment is free)
        return best, best_plan

    def wcost(t_):
        return float(np.sum((w * (late0 + np.cumsum(t_ - D))) ** 2))

    best_w = wcost(best_plan[0])
    free_idx = np.nonzero(free)[0]
    for _ in range(FIXED_AHEAD_ROUNDS):
        t_best = best_plan[0]
        late_end, ls = _lateness(t_best, D, late0)
        # the first segment of each fixed run after a free one, its lateness added on the way
        s = np.nonzero(~free[1:] & free[:-1])[0] + 1
        jump = late_end[s] - ls[s]
        sel = (jump < -FIXED_AHEAD_MIN_S) & (late_end[s] < -FIXED_AHEAD_MIN_S)
        k = s[sel]
        if not k.size:
            break
        amount = FIXED_AHEAD_SHARE * np.minimum(-jump[sel], -late_end[k])
        want = t_best.copy()
        want[k - 1] += amount
        # the first free segment after the run had waited the run's lead out: no longer
        after = np.searchsorted(free_idx, k)
        ok = after < len(free_idx)
        j = free_idx[after[ok]]
        want[j] = np.maximum(want[j] - amount[ok], MIN_SHARE * D[j])
        FC = sweeps(best, fast_(want), SWEEPS // 2)
        pC = plan(FC)
        cw = wcost(pC[0])
        if cw >= best_w:
            break
        best, best_plan, best_w = FC, pC, cw
    return best, best_plan


def _gentle_wants(t, D, free, late0):
    """Durations that take back the lateness (or wait out the time ahead) carried into each free
    segment by at most :data:`TAKEBACK_SHARE` of its intended time: the queue recursion of
    :func:`_solve_chain`'s recovery, at a rate almost any segment can run (not its fastest)."""
    want = t.copy()
    cap = TAKEBACK_SHARE * D
    lat = late0
    for i, (ti, di, fr, ci) in enumerate(zip(t.tolist(), D.tolist(), free.tolist(), cap.tolist())):
        if fr and lat != 0.0:
            want[i] = ti - (min(lat, ci) if lat > 0 else max(lat, -ci))
        lat += want[i] - di
    return want


def _take_back(plan, sweeps, fast_, F, p, free, D, late0, w):
    """Where the rounds and the refinement leave a stretch off the clock behind a spot the limits
    bind (a z wobble at ``max_z_accel`` after a layer change), though the segments after it are free
    to run a little faster: it is taken back at :data:`TAKEBACK_SHARE` of their time
    (:func:`_gentle_wants`), a few rounds (each hands on what a segment could not take).  Kept where
    the lateness times speed falls and the largest lateness does not grow.  (A layer change of a
    gyroid tower on other_delta left 0.63 ms for 1.4 s of printing: 25 um at 40 mm/s; the
    refinement's joint solve stopped at that plateau.)"""
    r = late0 + np.cumsum(p[0] - D)
    if float(np.max(np.abs(r))) <= TAKEBACK_MIN_S:
        return F, p
    cost, worst = float(np.sum((w * r) ** 2)), float(np.max(np.abs(r)))
    # only after the worst spot (where the limits bind, a faster or slower segment only moves it)
    pk = int(np.argmax(np.abs(r) >= 0.98 * worst))  # (the first end at the plateau's level)
    after = free.copy()
    after[:pk + 1] = False
    for _ in range(TAKEBACK_ROUNDS):
        rr = late0 + np.cumsum(p[0] - D)
        want = p[0].copy()
        want[pk + 1:] = _gentle_wants(p[0][pk + 1:], D[pk + 1:], after[pk + 1:], float(rr[pk]))
        want = fast_(np.maximum(want, MIN_SHARE * D))
        Fn = sweeps(F, want, SWEEPS // 2)
        pn = plan(Fn)
        # a segment that could not take its share (a limit binds it) is left out of the next round,
        # which hands its share on to the segments after it
        after &= ~(np.abs(pn[0] - want) > 1e-6 + 1e-3 * want)
        rn = late0 + np.cumsum(pn[0] - D)
        cn = float(np.sum((w * rn) ** 2))
        if cn >= cost or float(np.max(np.abs(rn))) > worst + 1e-6:
            break
        F, p, cost = Fn, pn, cn
        if float(np.max(np.abs(rn[pk + 1:]), initial=0.0)) <= TAKEBACK_MIN_S:
            break
    return F, p


def refine_objective(w: np.ndarray, r: np.ndarray, hinge: bool = True) -> float:
    """What the refinement minimises: the squared lateness times speed (``w``: :func:`clock_weights`,
    mm/s; ``r``: lateness, s) at every segment end, plus (``hinge``) the squared excess over
    :data:`HINGE_S` weighted as :data:`HINGE_MM_S`."""
    c = float(np.sum((w * r) ** 2))
    if hinge:
        ex = np.maximum(np.abs(r) - HINGE_S, 0.0)
        c += HINGE_MM_S**2 * float(np.sum(ex**2))
    return c


def _hinged(plan, F, p, free, D, late0, hi, w):
    """Where a chain's refined feeds ``F`` (plan ``p``) leave a segment end more than :data:`HINGE_S`
    off the clock, :func:`_refine` again with the hinge; kept where the largest lateness falls and
    the largest lateness times speed grows by at most :data:`HINGE_COST_GROWTH` (a z travel at
    100 mm/s on other_delta: refined with the hinge alone its clock error went 3.4 -> 14 um)."""
    r = late0 + np.cumsum(p[0] - D)
    peak = float(np.max(np.abs(r)))
    if peak <= HINGE_S:
        return F, p
    Fh, ph = _refine(plan, F, p, free, D, late0, hi, w, hinge=True)
    rh = late0 + np.cumsum(ph[0] - D)
    off, offh = float(np.max(np.abs(w * r))), float(np.max(np.abs(w * rh)))
    if float(np.max(np.abs(rh))) < peak and offh <= max(HINGE_COST_GROWTH * off, 2 * REFINE_PEAK_MM):
        return Fh, ph
    return F, p


def _refine_stretches(plan, dist, vmax, acc, jv, F, p, free, off, D, late0, hi, w):
    """:func:`_refine` of the free feeds within :data:`REFINE_LOCAL` segments of the segment ends
    more than :data:`REFINE_PEAK_MM` off (``off``: lateness times speed, mm), each such stretch on
    its own sub-chain (:data:`REFINE_MARGIN` more segments either side, entered and left at the
    speeds of the chain's plan ``p``): a refinement's dozens of plans then cost the stretch's
    length, not the chain's.  The chain is planned again with the new feeds, kept where its
    weighted lateness fell and its largest lateness did not grow.
    """
    n = len(D)
    hot = np.convolve(off > REFINE_PEAK_MM, np.ones(2 * REFINE_LOCAL + 1))[REFINE_LOCAL:REFINE_LOCAL + n] > 0
    hot &= free
    if not hot.any():
        return F, p
    t, vin, vout = p
    late_end = late0 + np.cumsum(t - D)
    edges = np.flatnonzero(np.diff(np.r_[0, hot.astype(np.int8), 0]))
    Fn = F.copy()
    for a, b in zip(edges[::2].tolist(), edges[1::2].tolist()):
        s0, s1 = max(a - REFINE_MARGIN, 0), min(b + REFINE_MARGIN, n)
        v0, v1 = float(vin[s0]) ** 2, float(vout[s1 - 1]) ** 2

        def sub(Fs, s0=s0, s1=s1, v0=v0, v1=v1):
            return plan_chain(dist[s0:s1], np.minimum(Fs, vmax[s0:s1]) ** 2, acc[s0:s1], jv[s0:s1], v0, v1)

        l0 = late0 if s0 == 0 else float(late_end[s0 - 1])
        Fs, _ = _refine(sub, Fn[s0:s1], sub(Fn[s0:s1]), hot[s0:s1], D[s0:s1], l0, hi[s0:s1], w[s0:s1])
        Fn[s0:s1] = Fs
    pn = plan(Fn)
    late_n = late0 + np.cumsum(pn[0] - D)
    if np.sum((w * late_n) ** 2) < np.sum(off**2) and np.max(np.abs(late_n)) <= np.max(np.abs(late_end)):
        return Fn, pn
    return F, p


def _refine(plan, F, p, free, D, late0, hi, w, hinge: bool = False):
    """Gauss-Newton (Levenberg-Marquardt) on the free feeds' logarithms for the least summed squared
    lateness times speed (``w``, :func:`clock_weights`) at every segment end, from the rounds' feeds
    ``F`` (plan ``p``); returns the best feeds and their plan.  The rounds aim each segment at a
    duration one at a time and keep a round only where the whole chain gains, which can leave long
    stretches a fraction of a millisecond ahead or behind after a corner the limits slow (a z
    reversal at ``max_z_accel``); the joint solve takes them back.  Feeds stay within
    ``[1e-3, hi]`` (mm/s).  ``hinge``: the objective charges lateness beyond :data:`HINGE_S` too
    (:func:`refine_objective`; see :func:`_hinged`)."""
    fi = np.nonzero(free)[0]
    F = np.where(free, np.minimum(F, hi), F)  # a feed above the segment's cap changes nothing
    r = late0 + np.cumsum(p[0] - D)
    cost = refine_objective(w, r, hinge)
    lam = 1e-3 * float(np.mean(D)) ** 2 * float(np.mean(w**2))
    for _ in range(REFINE_ITERS):
        # the hinge where it acts, folded into one weighted row per segment end: w^2 (r + x)^2 +
        # H^2 (r - L sign r + x)^2 = we^2 (x + r*)^2 + const
        far = (np.abs(r) > HINGE_S) & hinge
        we = np.sqrt(w**2 + np.where(far, HINGE_MM_S**2, 0.0))
        rs = np.where(far, (w**2 * r + HINGE_MM_S**2 * (r - HINGE_S * np.sign(r))) / we**2, r)
        solve = _damped_solver(_duration_jacobian(plan, F, p[0], free), we, -we * rs)
        for _ in range(8):
            Fn = F.copy()
            Fn[fi] = np.clip(F[fi] * np.exp(np.clip(solve(lam), -1.0, 1.0)), 1e-3, hi[fi])
            pn = plan(Fn)
            rn = late0 + np.cumsum(pn[0] - D)
            cn = refine_objective(w, rn, hinge)
            if cn < cost:
                break
            lam *= 10.0
        else:
            break
        improved = cn < 0.98 * cost
        F, p, r, cost = Fn, pn, rn, cn
        lam *= 0.3
        if not improved:
            break
    return F, p


def _duration_jacobian(plan, F, t, free):
    """d(duration)/d(log feed) (n, free segments): :func:`_banded_jacobian`, or on a short chain (up
    to :data:`DENSE_JACOBIAN` segments) every free feed perturbed on its own in one batched plan."""
    if len(t) > DENSE_JACOBIAN:
        return _banded_jacobian(plan, F, t, free)
    fi = np.nonzero(free)[0]
    h = 1e-6
    Fp = np.repeat(F[None], fi.size, axis=0)
    Fp[np.arange(fi.size), fi] *= np.exp(h)
    return ((plan(Fp)[0] - t) / h).T  # (n, free)


def _banded_jacobian(plan, F, t, free):
    """d(duration)/d(log feed) (n, free segments), sparse: finite differences on interleaved groups
    of feeds, each duration counted for the perturbed feed within :data:`REFINE_BAND` segments."""
    n = len(t)
    fi = np.nonzero(free)[0]
    col = np.full(n, -1)
    col[fi] = np.arange(fi.size)
    step, h, rows = 2 * REFINE_BAND + 1, 1e-6, np.arange(n)
    groups = [c for c in range(min(step, n)) if np.any(fi % step == c)]
    Fp = np.repeat(F[None], len(groups), axis=0)  # every group's perturbed feeds: one batched plan
    for g, c in enumerate(groups):
        js = fi[fi % step == c]
        Fp[g, js] *= np.exp(h)
    dts = (plan(Fp)[0] - t) / h
    ri, ci, vals = [], [], []
    for g, c in enumerate(groups):
        dt = dts[g]
        j = c + np.round((rows - c) / step).astype(int) * step  # the nearest perturbed segment
        ok = (np.abs(rows - j) <= REFINE_BAND) & (j >= 0) & (j < n)
        ok[ok] &= free[j[ok]]
        ok &= dt != 0
        ri.append(rows[ok])
        ci.append(col[j[ok]])
        vals.append(dt[ok])
    return csr_matrix((np.concatenate(vals), (np.concatenate(ri), np.concatenate(ci))), shape=(n, fi.size))


def _damped_solver(Jt, w, b):
    """``solve(lam)``: the step ``x`` minimising ``|w * cumsum(Jt x) - b|^2 + lam |x|^2`` (the
    lateness is the running sum of the durations).  Small chains: one eigendecomposition serves
    every damping tried; long ones (more than :data:`REFINE_DENSE` free segments): LSQR."""
    if Jt.shape[1] <= REFINE_DENSE:
        A = w[:, None] * np.cumsum(Jt.toarray() if issparse(Jt) else Jt, axis=0)
        ev, V = np.linalg.eigh(A.T @ A)
        g = V.T @ (A.T @ b)
        ev = np.maximum(ev, 0.0)
        return lambda lam: V @ (g / (ev + lam))
    if not issparse(Jt):  # (a dense Jacobian of a short chain with many free feeds)
        Jt = csr_matrix(Jt)
    JtT = Jt.T.tocsr()
    A = LinearOperator(Jt.shape, matvec=lambda x: w * np.cumsum(Jt @ x),
                       rmatvec=lambda y: JtT @ np.cumsum((w * y)[::-1])[::-1])
    return lambda lam: lsqr(A, b, damp=np.sqrt(lam), atol=1e-8, btol=1e-8, iter_lim=300)[0]


def clock_weights(dist: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Speed at every segment end (mm/s): the root mean square of the two segments' plain speeds
    ``dist / D``, floored in quadrature at :data:`REFINE_V0`.  Lateness there times it is about the
    position error it costs (mm): a millisecond late at a near stop costs next to nothing, at
    100 mm/s a tenth of a millimetre."""
    v2 = (dist / D) ** 2
    return np.sqrt(0.5 * (v2 + np.r_[v2[1:], v2[-1]]) + REFINE_V0**2)


def _stop_rule(plan, free, jv, Fmax, vmax, F0, D):
    """The target durations' rule at full stops inside a chain (see :func:`_solve_chain`): returns
    ``fast_(want)``, which lowers ``want`` to the fastest durations on the free segments on either
    side of a zero junction that the limits hold within :data:`STOP_FAST_SHARE` of their time."""
    k = np.nonzero(jv[1:] <= 0.0)[0] + 1  # segments that start from a stop inside the chain
    if not k.size:
        return lambda want: want
    fast = np.zeros(len(D), bool)
    fast[k] = fast[k - 1] = True
    fast &= free
    if not fast.any():
        return lambda want: want
    lo = plan(np.where(free, np.minimum(Fmax, vmax), F0))[0]  # everything free at its fastest
    fast &= lo >= STOP_FAST_SHARE * D
    if not fast.any():
        return lambda want: want
    return lambda want: np.where(fast, np.minimum(want, lo), want)


def solve_feeds(lim: ChainLimits, st: TimingState, P0: np.ndarray, P1: np.ndarray, D: np.ndarray,
                de: np.ndarray, hold: np.ndarray, stop_first: np.ndarray, open_end: bool,
                pre_late: np.ndarray | None = None, wait_out: np.ndarray | None = None,
                fixed_v: np.ndarray | None = None) -> np.ndarray:
    """Feed rates (mm/s) of a chunk's segments, in written order.

    Parameters
    ----------
    lim : the firmware's limits
    st : carried state (updated)
    P0, P1 : (n, 3) segment start and end as printed, mm
    D : (n,) intended durations, s
    de : (n,) extrusion of each segment, mm
    hold : (n,) segments written as ``G4`` or extruder-only lines (the firmware stops there); their
        value is the extruder feed (mm/s), or for a ``G4`` its duration (s)
    stop_first : (n,) the firmware stands still before this segment (an extruder-only move or a
        dwell was written just before it)
    open_end : bool
        The chunk ends in motion (the next chunk continues the chain).
    pre_late : (n,), optional
        Lateness (s) that lines written just before a segment (extruder-only moves, dwells) add.
    wait_out : (n,), optional
        Filled with the time (s) to stand still (a ``G4``) before a chain that starts from rest
        (``stop_first``) ahead of the clock: standing still is exact, whereas a first segment
        slowed to a crawl leaves the next ones behind a plan that leaves rest at full acceleration.
        Without it, the first segment waits.
    fixed_v : (n,), optional
        Feed rates (mm/s) the solve keeps (NaN: solved): segments that follow the plan itself, whose
        feed is the plan's peak speed along them, so the firmware's own ramps reproduce the plan
        (a feed matched to a duration instead trades a few microseconds for speed that segments
        at the acceleration limit never win back).
    """
    n = len(D)
    F = np.zeros(n)
    if pre_late is None:
        pre_late = np.zeros(n)
    moving = ~hold
    # chains: runs of moving segments; a hold or a stop starts a new one
    brk = hold | stop_first
    idx = np.arange(n)
    starts = idx[moving & (np.concatenate(([True], brk[1:] | hold[:-1])) | stop_first)]
    # a chain ends before the next hold or stop
    ends_at = np.nonzero(brk)[0]
    e_of = ends_at[np.minimum(np.searchsorted(ends_at, starts, side="right"), len(ends_at) - 1)] \
        if len(ends_at) else np.full(len(starts), n)
    e_of = np.where(e_of > starts, e_of, n)
    chains = list(zip(starts.tolist(), e_of.tolist()))
    first_chain_continues = bool(chains) and chains[0][0] == 0 and not stop_first[0]
    # lateness due before a segment inside a chain (a run that leaves rest on the plan's time a
    # fraction of a sample after the point before it, which the firmware runs on through: a wait
    # the firmware cannot make there) is that segment's to take: its intended duration grows by it
    # (without this the chain ran that much early from there on: 0.38 ms after a G10's creep into a
    # lift at max_z_accel 3000, kept through the travel after it)
    inner = moving & (pre_late != 0.0)
    inner[[a for a, _ in chains][1 if first_chain_continues else 0:]] = False
    if inner.any():
        D = np.array(D, float)
        D[inner] = np.maximum(D[inner] - pre_late[inner], MIN_SHARE * D[inner])
        pre_late = np.where(inner, 0.0, pre_late)
    if st.tail is not None and not first_chain_continues:
        _close_tail(lim, st)
    k_hold = 0
    hold_idx = np.nonzero(hold)[0]
    for c, (a, b) in enumerate(chains):
        # the holds before this chain
        for h in hold_idx[np.searchsorted(hold_idx, k_hold):np.searchsorted(hold_idx, a)].tolist():
            st.late_s += pre_late[h]
            F[h] = _hold(lim, st, de[h], D[h])
        k_hold = b
        st.late_s += pre_late[a]
        # from rest: after an extruder-only move or dwell, or after segments written as holds
        # (``G4``: a stretch where the command stands still, e.g. the rest before a stream)
        if wait_out is not None and (stop_first[a] or (a > 0 and hold[a - 1])) and st.late_s < -1e-6:
            # keep the time the first segment needs beyond its share, leaving rest at the
            # acceleration limit (a command that moves off harder than the firmware can)
            vmax1, acc1 = segment_limits(lim, P0[a:a + 1], P1[a:a + 1], de[a:a + 1])
            d1 = float(np.linalg.norm(P1[a] - P0[a]))
            v1 = min(float(vmax1[0]), float(np.sqrt(2.0 * acc1[0] * d1)))
            t1 = d1 / max(v1, 1e-9) + 0.5 * v1 / max(float(acc1[0]), 1e-9)  # from rest, as fast as it can
            keep = min(max(t1 - D[a], 0.0), -st.late_s)
            wait = dwell_as_written(-st.late_s - keep)
            wait_out[a], st.late_s = wait, st.late_s + wait
        sl = slice(a, b)
        Fa = np.linalg.norm(P1[sl] - P0[sl], axis=1) / D[sl]
        end_open = open_end and b == n
        if c == 0 and first_chain_continues and st.tail is not None:
            t0, t1, tde, tF, tD = st.tail
            q0, q1 = np.vstack([t0, P0[sl]]), np.vstack([t1, P1[sl]])
            dd = np.concatenate([tde, de[sl]])
            DD = np.concatenate([tD, D[sl]])
            FF = np.concatenate([tF, Fa if fixed_v is None else np.where(np.isnan(fixed_v[sl]), Fa, fixed_v[sl])])
            free = np.r_[np.zeros(len(tF), bool), np.ones(b - a, bool) if fixed_v is None else np.isnan(fixed_v[sl])]
            Fs, late_end, vin = _solve_chain(lim, q0, q1, dd, DD, free, st.tail_late_s, st.tail_v2, end_open, FF)
            nt = len(tF)
            F[sl] = Fs[nt:]
            late_start0 = st.tail_late_s
        else:
            q0, q1, dd, DD, FF = P0[sl], P1[sl], de[sl], D[sl], Fa
            free = np.ones(b - a, bool)
            if fixed_v is not None:
                free = np.isnan(fixed_v[sl])
                FF = np.where(free, Fa, fixed_v[sl])
            Fs, late_end, vin = _solve_chain(lim, q0, q1, dd, DD, free, st.late_s, 0.0, end_open, FF)
            F[sl] = Fs
            late_start0 = st.late_s
        st.late_s = float(late_end[-1])
        if end_open:
            k = max(0, len(Fs) - TAIL)
            late_starts = np.concatenate([[late_start0], late_end[:-1]])
            st.tail = (q0[k:], q1[k:], dd[k:], Fs[k:], DD[k:])
            st.tail_late_s = float(late_starts[k])
            st.tail_v2 = float(vin[k] ** 2)
        else:
            st.tail = None
    for h in hold_idx[np.searchsorted(hold_idx, k_hold):].tolist():
        st.late_s += pre_late[h]
        F[h] = _hold(lim, st, de[h], D[h])
    return F


def _close_tail(lim: ChainLimits, st: TimingState) -> None:
    """The chain left open by the last chunk ends here (the firmware stops): its final lateness."""
    t0, t1, tde, tF, tD = st.tail
    free = np.zeros(len(tF), bool)
    _, late_end, _ = _solve_chain(lim, t0, t1, tde, tD, free, st.tail_late_s, st.tail_v2, False, tF)
    st.late_s = float(late_end[-1])
    st.tail = None


def _hold(lim: ChainLimits, st: TimingState, de: float, D: float) -> float:
    """A hold segment: a ``G4`` (returns its duration, s: a rest gives back any lateness) or an
    extruder-only move timed as Klipper runs it (returns its feed, mm/s)."""
    if abs(de) <= 1e-9:
        dwell = dwell_as_written(max(D - st.late_s, 0.0))
        st.late_s += dwell - D
        return dwell
    want = max(D - st.late_s, MIN_SHARE * D)
    v = float(extrude_only_feed(np.array([de]), np.array([want]), lim.max_e_accel, lim.max_e_velocity)[0])
    v = max(round(v * 60.0, 3), 0.001) / 60.0  # as written (F in mm/min, three decimals)
    t = float(extrude_only_time(np.array([de]), np.array([v]), lim.max_e_accel)[0])
    st.late_s += t - D
    return v
