"""Corner (junction) speed rules of the firmware, as pure functions of the geometry.

Both firmware use the "approximated centripetal velocity" idea (Grbl): a circle of radius
``R = d_j sin(theta/2) / (1 - sin(theta/2))`` tangent to both moves, where ``theta`` is the angle
*between* the two path directions seen from the corner (180 deg = straight on, 0 deg = full reversal)
and ``d_j`` the junction deviation; the corner speed is ``v^2 = a R``.

Klipper (``klippy/toolhead.py``, ``Move.calc_junction``)
    ``d_j = scv^2 (sqrt(2) - 1) / max_accel`` (so a 90 deg corner allows exactly
    ``square_corner_velocity``), evaluated for both moves with their own accel and d_j; in addition the
    circle must touch each move no further than its middle: ``v^2 <= 0.5 * move_d * accel * tan(theta/2)``.
    A full reversal allows zero speed; a straight continuation has no corner limit.

Marlin (``Marlin/src/module/planner.cpp``, junction deviation)
    ``v^2 = a_j d_j sin(theta/2) / (1 - sin(theta/2))`` with ``a_j`` the block acceleration limited by the
    per-axis maxima along the junction vector; ``cos theta > 0.999999`` (reversal) gives the minimum
    planner speed; with ``JD_HANDLE_SMALL_SEGMENTS`` (default on) a block shorter than 1 mm whose corner
    is gentler than 135 deg is also limited to ``v^2 <= L a_j / theta_approx`` (the speed of an arc through
    the segments), with Marlin's polynomial acos approximation.

:data:`JUNCTION_RULES` maps a planner name to its rule.
"""

from __future__ import annotations

import math

__all__ = [
    "klipper_junction_deviation",
    "klipper_corner_v2",
    "marlin_fast_acos_neg",
    "marlin_corner_v2",
    "JUNCTION_RULES",
]

SQRT2_MINUS_1 = math.sqrt(2.0) - 1.0


def klipper_junction_deviation(square_corner_velocity_mm_s: float, accel_mm_s2: float) -> float:
    """Klipper's equivalent junction deviation ``scv^2 (sqrt2 - 1) / accel`` (mm)."""
    return square_corner_velocity_mm_s ** 2 * SQRT2_MINUS_1 / accel_mm_s2


def klipper_corner_v2(junction_cos_theta: float, jd: float, accel: float, delta_v2: float,
                      prev_jd: float, prev_accel: float, prev_delta_v2: float) -> float:
    """Klipper's corner limit on v^2 (mm^2/s^2); ``inf`` when there is no corner limit.

    Parameters
    ----------
    junction_cos_theta : float
        ``-(u_prev . u)`` for the unit XYZ directions: 1 for a reversal, -1 straight on.
    jd, accel, delta_v2 : float
        This move's junction deviation (mm), acceleration (mm/s^2) and ``2 * move_d * accel``.
    prev_jd, prev_accel, prev_delta_v2 : float
        The same for the previous move.
    """
    s2 = 0.5 * (1.0 - junction_cos_theta)
    c2 = 0.5 * (1.0 + junction_cos_theta)
    # max(x, 0.0) written out (a planner hot path): NaN and -0.0 pass as max() lets them
    sin_theta_d2 = math.sqrt(0.0 if s2 < 0.0 else s2)
    cos_theta_d2 = math.sqrt(0.0 if c2 < 0.0 else c2)
    one_minus_sin_theta_d2 = 1.0 - sin_theta_d2
    if one_minus_sin_theta_d2 > 0.0 and cos_theta_d2 > 0.0:
        r_jd = sin_theta_d2 / one_minus_sin_theta_d2
        quarter_tan_theta_d2 = 0.25 * sin_theta_d2 / cos_theta_d2
        return min(r_jd * jd * accel, r_jd * prev_jd * prev_accel,
                   delta_v2 * quarter_tan_theta_d2, prev_delta_v2 * quarter_tan_theta_d2)
    return math.inf


def marlin_fast_acos_neg(t: float) -> float:
    """Marlin's polynomial approximation of ``acos(-t)`` (max error about 0.033 rad)."""
    neg = -1.0 if t < 0 else 1.0
    x = neg * t
    asinx = 0.032843707 + x * (-1.451838349 + x * (29.66153956 + x * (-131.1123477 + x * (
        262.8130562 + x * (-242.7199627 + x * 84.31466202)))))
    return math.pi / 2 + neg * asinx


def marlin_corner_v2(junction_cos_theta: float, junction_accel: float, junction_deviation_mm: float,
                     millimeters: float, min_planner_v2: float = 0.0,
                     small_segments: bool = True) -> float:
    """Marlin's junction-deviation limit on v^2 (before the nominal-speed caps).

    Parameters
    ----------
    junction_cos_theta : float
        ``-(u_prev . u)``.
    junction_accel : float
        Block acceleration limited by the axis maxima along the junction vector, mm/s^2.
    junction_deviation_mm : float
    millimeters : float
        Length of the new block.
    min_planner_v2 : float
        Value returned for a reversal (Marlin: the minimum planner speed squared).
    small_segments : bool
        ``JD_HANDLE_SMALL_SEGMENTS``.
    """
    if junction_cos_theta > 0.999999:
        return min_planner_v2
    c = max(junction_cos_theta, -0.999999)
    sin_theta_d2 = math.sqrt(0.5 * (1.0 - c))
    v2 = junction_accel * junction_deviation_mm * sin_theta_d2 / (1.0 - sin_theta_d2)
    if small_segments and millimeters < 1.0 and junction_cos_theta < -0.7071067812:
        theta = marlin_fast_acos_neg(junction_cos_theta)
        v2 = min(v2, millimeters * junction_accel / theta)
    return v2


JUNCTION_RULES = {
    "klipper": klipper_corner_v2,
    "marlin": marlin_corner_v2,
}
