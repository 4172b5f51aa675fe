"""Klipper's plan of a chain of straight G1 segments, vectorised (the writer's timing model).

The compensated G-code is a long chain of short segments whose feed rates carry the timing.  The
writer must know, for candidate feed rates, how long Klipper will take over every segment; running
:class:`~ffcomp.gcode.klipper.KlipperPlanner` move by move inside the feed solve would be far too
slow, so this module computes the same plan for a whole chain at once with numpy:

* per-segment limits as Klipper's ``Move`` / delta ``check_move`` / extruder ``check_move`` apply
  them (:func:`segment_limits`): the toolhead's velocity and acceleration, the delta rules
  ``max_z_velocity * d/|dz|`` and ``max_z_accel * d/|dz|``, the slow zones near the rim and the
  extruder's limits on retracting or z-only segments;
* junction limits (:func:`junction_v2`): both cruise speeds, the corner rule with
  ``square_corner_velocity``, the extruder's ``instantaneous_corner_velocity / |delta e ratio|``;
* the lookahead (:func:`plan_chain`): the forward reachability ``v2 <= v2_prev + 2 d a`` and the
  backward pass are min-plus recurrences, solved in closed form with cumulative sums and running
  minima; then Klipper's ``set_junction`` trapezoid for every segment.

With ``minimum_cruise_ratio = 0`` (the compensated file's header sets it) Klipper's smoothed
("accel_to_decel") pass equals the plain one and its delayed full-acceleration moves end up on the
same trapezoids, so the plan is exact; ``tests/test_chain_plan.py`` checks it against the
move-by-move planner.
"""

from __future__ import annotations

import numpy as np

from .junction import klipper_junction_deviation
from .klipper import KlipperDelta

__all__ = ["ChainLimits", "segment_limits", "extruder_limited", "corner_v2", "junction_v2", "plan_chain", "trapezoids"]


class ChainLimits:
    """The firmware numbers a chain's plan depends on (config values and the header's run-time ones).

    Parameters
    ----------
    profile : PrinterProfile
        ``[printer]`` config: max_velocity, max_accel (the delta's slow zones use these),
        max_z_velocity, max_z_accel, the extruder's limits.
    accel_mm_s2 : float
        The run-time ACCEL (the header's ``SET_VELOCITY_LIMIT``).
    square_corner_velocity_mm_s : float
        The run-time SQUARE_CORNER_VELOCITY.
    """

    def __init__(self, profile, accel_mm_s2: float, square_corner_velocity_mm_s: float):
        lim = profile.limits
        kin = KlipperDelta(profile, lim.max_velocity_mm_s, lim.max_accel_mm_s2)
        self.max_velocity = lim.max_velocity_mm_s
        self.accel = float(accel_mm_s2)
        self.jd = klipper_junction_deviation(square_corner_velocity_mm_s, self.accel)
        self.max_z_velocity, self.max_z_accel = kin.max_z_velocity, kin.max_z_accel
        self.cfg_velocity, self.cfg_accel = kin.max_velocity, kin.max_accel
        self.slow_xy2, self.very_slow_xy2 = kin.slow_xy2, kin.very_slow_xy2
        self.instant_corner_v = lim.instantaneous_corner_velocity_mm_s
        self.max_e_velocity = lim.max_extrude_only_velocity_mm_s
        self.max_e_accel = lim.max_extrude_only_accel_mm_s2


def segment_limits(lim: ChainLimits, start: np.ndarray, end: np.ndarray, de: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Speed cap (mm/s, before the feed rate) and acceleration (mm/s^2) of every segment.

    ``start``, ``end``: (n, 3) XYZ in mm (as printed); ``de``: (n,) extrusion in mm.
    """
    d = end - start
    dist = np.sqrt(np.einsum("ij,ij->i", d, d))
    vmax = np.full(len(dist), lim.max_velocity)
    acc = np.full(len(dist), lim.accel)
    dz = np.abs(d[:, 2])
    z = dz > 0
    if z.any():
        ratio = dist[z] / dz[z]
        vmax[z] = np.minimum(vmax[z], lim.max_z_velocity * ratio)
        acc[z] = np.minimum(acc[z], lim.max_z_accel * ratio)
    xy2 = np.maximum(start[:, 0] ** 2 + start[:, 1] ** 2, end[:, 0] ** 2 + end[:, 1] ** 2)
    slow = xy2 > lim.slow_xy2
    if slow.any():
        r = np.where(xy2[slow] > lim.very_slow_xy2, 0.25, 0.5)
        vmax[slow] = np.minimum(vmax[slow], lim.cfg_velocity * r)
        acc[slow] = np.minimum(acc[slow], lim.cfg_accel * r)
    with np.errstate(divide="ignore", invalid="ignore"):
        er = np.where(dist > 0, de / dist, 0.0)
    ext = extruder_limited(d, de)
    if ext.any():
        with np.errstate(divide="ignore"):  # (an extruder-only segment: no XYZ length, no cap from it)
            inv = 1.0 / np.abs(er[ext])
        vmax[ext] = np.minimum(vmax[ext], lim.max_e_velocity * inv)
        acc[ext] = np.minimum(acc[ext], lim.max_e_accel * inv)
    return vmax, acc


def extruder_limited(d: np.ndarray, de: np.ndarray) -> np.ndarray:
    """The segments Klipper's extruder ``check_move`` limits (and checks against
    ``max_extrude_only_distance``): retractions and extrusion without XY travel.  ``d``: (n, 3) XYZ
    travel, ``de``: (n,) extrusion, mm."""
    return (de != 0) & ((de < 0) | ((d[:, 0] == 0) & (d[:, 1] == 0)))


def corner_factors(unit: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Klipper's corner terms at the junctions of a chain of ``unit`` (n, 3) directions: ``(ok,
    r_jd, qt)``, each of length ``n - 1``.  Where ``ok`` (not a straight line), the junction allows
    ``v^2 <= min(r_jd * jd * a, delta_v2 * qt)`` for either segment's acceleration ``a`` and
    ``delta_v2 = 2 d a`` (``r_jd = sin(theta/2) / (1 - sin(theta/2))``, ``qt = tan(theta/2) / 4``);
    elsewhere both are 0."""
    cos = -np.einsum("ij,ij->i", unit[1:], unit[:-1])
    sin2 = np.sqrt(np.maximum(0.5 * (1.0 - cos), 0.0))
    cos2 = np.sqrt(np.maximum(0.5 * (1.0 + cos), 0.0))
    oms = 1.0 - sin2
    ok = (oms > 0) & (cos2 > 0)
    r_jd, qt = np.zeros(len(cos)), np.zeros(len(cos))
    r_jd[ok] = sin2[ok] / oms[ok]
    qt[ok] = 0.25 * sin2[ok] / cos2[ok]
    return ok, r_jd, qt


def corner_v2(lim: ChainLimits, unit: np.ndarray, acc: np.ndarray, delta_v2: np.ndarray) -> np.ndarray:
    """The corner rule's limit on v^2 at the start of segments ``1..n-1`` (length ``n - 1``; ``inf``
    on a straight line): :func:`junction_v2` without the extruder's."""
    ok, r_jd_all, qt_all = corner_factors(unit)
    out = np.full(len(ok), np.inf)
    if ok.any():
        r_jd, qt = r_jd_all[ok], qt_all[ok]
        a1, a0 = acc[1:][ok], acc[:-1][ok]
        d1, d0 = delta_v2[1:][ok], delta_v2[:-1][ok]
        out[ok] = np.minimum.reduce([r_jd * lim.jd * a1, r_jd * lim.jd * a0, d1 * qt, d0 * qt])
    return out


def junction_v2(lim: ChainLimits, unit: np.ndarray, erat: np.ndarray, acc: np.ndarray,
                delta_v2: np.ndarray) -> np.ndarray:
    """Corner and extruder limits on v^2 at the start of segments ``1..n-1`` (length ``n - 1``).

    ``unit``: (n, 3) unit directions; ``erat``: (n,) extrusion per mm; ``acc``, ``delta_v2``: each
    segment's acceleration and ``2 d a``.  Cruise-speed limits are applied by :func:`plan_chain`.
    """
    out = corner_v2(lim, unit, acc, delta_v2)
    diff = np.abs(erat[1:] - erat[:-1])
    with np.errstate(divide="ignore"):
        ev2 = np.where(diff > 0, (lim.instant_corner_v / np.where(diff > 0, diff, 1.0)) ** 2, np.inf)
    return np.minimum(out, ev2)


def plan_chain(dist: np.ndarray, cruise_v2: np.ndarray, acc: np.ndarray, junc_v2: np.ndarray,
               start_v2: float, end_v2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Klipper's lookahead over a chain: durations and entry/exit speeds of every segment.

    Parameters
    ----------
    dist : (n,) segment lengths, mm (all > 0)
    cruise_v2 : (n,) largest cruise speed squared (feed rate and caps), mm^2/s^2
    acc : (n,) accelerations, mm/s^2
    junc_v2 : (n,) limit on the entry speed squared from the corner and extruder rules (the first
        entry: how fast the chain may be entered, e.g. 0 from rest)
    start_v2 : float
        Largest speed squared the chain can be entered with (the previous segment's reachable speed).
    end_v2 : float
        Speed squared the chain must be able to leave with (0: the firmware stops after it).

    Returns
    -------
    dur : (n,) durations, s
    v_in, v_out : (n,) entry and exit speeds, mm/s
    """
    t1, t2, t3, vi, vc, vo = trapezoids(dist, cruise_v2, acc, junc_v2, start_v2, end_v2)
    return t1 + t2 + t3, vi, vo


def trapezoids(dist: np.ndarray, cruise_v2: np.ndarray, acc: np.ndarray, junc_v2: np.ndarray,
               start_v2: float, end_v2: float) -> tuple[np.ndarray, ...]:
    """:func:`plan_chain`'s trapezoids in full: the acceleration, cruise and deceleration times (s)
    and the entry, cruise and exit speeds (mm/s) of every segment (the same arguments).

    ``cruise_v2`` may carry leading batch axes, ``(..., n)``: several chains of the same segments
    with other feed rates planned at once (each row bit for bit as on its own)."""
    n = len(dist)
    delta = 2.0 * dist * acc
    # junction: both cruise speeds and the rules
    J = np.empty(cruise_v2.shape)
    J[..., 0] = np.minimum(min(junc_v2[0], start_v2), cruise_v2[..., 0])
    np.minimum(np.minimum(junc_v2[1:], cruise_v2[..., 1:]), cruise_v2[..., :-1], out=J[..., 1:])
    # forward: ms_i = min(J_i, ms_{i-1} + delta_{i-1}) = S_i + cummin(J_k - S_k)
    S = np.empty(n + 1)
    S[0] = 0.0
    np.cumsum(delta, out=S[1:])
    S0 = S[:-1]
    ms = S0 + np.minimum.accumulate(J - S0, axis=-1)
    # backward: s_i = min(ms_i, s_{i+1} + delta_i), s_n = end_v2
    tail = np.empty(cruise_v2.shape[:-1] + (n + 1,))
    np.add(ms, S0, out=tail[..., :-1])
    tail[..., -1] = end_v2 + S[-1]
    sv = np.minimum.accumulate(tail[..., ::-1], axis=-1)[..., ::-1] - S
    s_in, s_out = sv[..., :-1], sv[..., 1:]
    cruise = np.minimum((s_in + s_out + delta) * 0.5, cruise_v2)
    np.maximum(cruise, s_in, out=cruise)
    e_out = np.minimum(s_out, cruise)
    vi, vc, vo = np.sqrt(np.maximum(s_in, 0)), np.sqrt(cruise), np.sqrt(np.maximum(e_out, 0))
    half_inv = 0.5 / acc
    accel_d = (cruise - s_in) * half_inv
    decel_d = (cruise - e_out) * half_inv
    cruise_d = np.maximum(dist - accel_d - decel_d, 0.0)
    # (divisions only where they are defined: no floating-point state to save and restore)
    shape = cruise.shape
    t1 = np.divide(accel_d, (vi + vc) * 0.5, out=np.zeros(shape), where=accel_d > 0)
    t2 = np.divide(cruise_d, vc, out=np.full(shape, np.inf), where=vc > 0)
    t3 = np.divide(decel_d, (vo + vc) * 0.5, out=np.zeros(shape), where=decel_d > 0)
    return t1, t2, t3, vi, vc, vo


def z_accel_needed(d: np.ndarray, dt: np.ndarray, jd_mm: float | None) -> np.ndarray:
    """The ``max_z_accel`` (mm/s^2) each junction of a chain of segments needs for Klipper to run
    it at the segments' own speeds: length ``n - 1`` for ``d`` (n, 3) segment vectors (mm) and ``dt``
    (n,) their durations (s).

    Klipper's delta caps a segment's acceleration at ``max_z_accel * d / |dz|``, so ``max_z_accel``
    must cover, on the steeper of the two segments at a junction, the change of speed there
    (``|v_i - v_{i-1}|`` over the mean of their durations: a command whose speed ramps through the
    junction) times ``|dz| / d``; and, with junction deviation ``jd_mm`` (None: not checked), the
    acceleration each segment's corner rules need to pass the junction at the mean of the two
    speeds, ``v^2 / min(R_jd jd, 2 d tan(theta/2) / 4)``, times its ``|dz| / d`` (see
    :func:`junction_v2`).  A direction change at constant speed needs no ``max_z_accel`` beyond
    what the corner rules ask: it is not an acceleration along either segment.
    """
    ln = np.linalg.norm(d, axis=1)
    ok = ln > 0
    u = np.where(ok[:, None], d / np.where(ok, ln, 1.0)[:, None], 0.0)
    sp = ln / dt
    uz = np.abs(u[:, 2])
    along = np.abs(np.diff(sp)) / (0.5 * (dt[1:] + dt[:-1])) * np.maximum(uz[1:], uz[:-1])
    if jd_mm is None or len(d) < 2:
        return along
    corner_ok, r_jd_all, qt_all = corner_factors(u)
    v2 = (0.5 * (sp[1:] + sp[:-1])) ** 2
    # (a reversal, r_jd = 0, stops the firmware whatever the limits: no max_z_accel helps there)
    turn = corner_ok & (r_jd_all > 1e-9) & ok[1:] & ok[:-1]
    corner = np.zeros(len(turn))
    if turn.any():
        r_jd, qt = r_jd_all[turn], qt_all[turn]
        need = []
        for side in (1, 0):  # the segment after, then before the junction
            l_s = ln[side:len(ln) - 1 + side][turn]
            a_s = v2[turn] / np.minimum(r_jd * jd_mm, 2.0 * l_s * qt)
            need.append(a_s * uz[side:len(uz) - 1 + side][turn])
        corner[turn] = np.maximum(*need)
    return np.maximum(along, corner)
