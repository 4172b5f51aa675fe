"""Arc (G2/G3) geometry: Klipper's segmentation rule and Marlin's radius (R) form.

Klipper's ``[gcode_arcs]`` splits an arc into ``max(1, floor(L / resolution))`` chords of equal angle,
where ``L`` is the arc length (``hypot(r * theta, helical travel)`` for a helix) and ``resolution``
defaults to 1 mm.  The chord end points are ``centre + R(i * dtheta) (start - centre)``, the helical axis
advances linearly, and the last chord ends exactly at the programmed target.  A zero angular travel
with the target at the start is a full circle.  Stock Klipper rejects ``R``; the ``R`` form here
converts the radius to a centre offset the way Marlin does (positive R: the short arc, negative R: the
arc over 180 degrees) and then splits it with the same rule.
"""

from __future__ import annotations

import math

__all__ = ["offset_from_radius", "plan_arc"]


def offset_from_radius(p1: tuple, p2: tuple, r: float, clockwise: bool) -> tuple[float, float]:
    """Centre offset (I, J) from the start point, for a radius-form arc (Marlin's construction).

    Parameters
    ----------
    p1, p2 : (alpha, beta)
        Start and end in the arc plane, mm.
    r : float
        Radius, mm; negative selects the arc longer than 180 degrees.
    clockwise : bool

    Returns
    -------
    (i, j) : centre minus start, mm.  If |r| is shorter than half the chord the centre is the chord's
    midpoint (as Marlin does).

    Raises
    ------
    ValueError
        ``r == 0`` or start == end (a radius does not define a full circle).
    """
    if r == 0.0:
        raise ValueError("arc radius R must not be zero")
    dx = (p2[0] - p1[0]) * 0.5
    dy = (p2[1] - p1[1]) * 0.5
    half = math.hypot(dx, dy)
    if half == 0.0:
        raise ValueError("an R-form arc needs an end point different from its start")
    e = -1.0 if (clockwise ^ (r < 0)) else 1.0
    h2 = (r - half) * (r + half)
    h = math.sqrt(h2) if h2 >= 0.0 else 0.0
    sx, sy = -dy, dx  # perpendicular bisector (length = half)
    return dx + sx / half * e * h, dy + sy / half * e * h


def arc_travel(current: tuple, target: tuple, offset: tuple, clockwise: bool,
               axes: tuple[int, int, int]) -> tuple[float, float, float]:
    """``(angular_travel_rad, radius_mm, length_mm)`` of an arc (the numbers :func:`plan_arc` splits),
    without making its points: a caller can refuse an absurd arc before it costs memory."""
    a, b, h = axes
    r_p, r_q = -offset[0], -offset[1]
    center_p, center_q = current[a] - r_p, current[b] - r_q
    rt_alpha, rt_beta = target[a] - center_p, target[b] - center_q
    angular_travel = math.atan2(r_p * rt_beta - r_q * rt_alpha, r_p * rt_alpha + r_q * rt_beta)
    if angular_travel < 0.0:
        angular_travel += 2.0 * math.pi
    if clockwise:
        angular_travel -= 2.0 * math.pi
    if angular_travel == 0.0 and current[a] == target[a] and current[b] == target[b]:
        angular_travel = 2.0 * math.pi  # full circle
    linear_travel = target[h] - current[h]
    radius = math.hypot(r_p, r_q)
    flat_mm = radius * angular_travel
    return angular_travel, radius, (math.hypot(flat_mm, linear_travel) if linear_travel else math.fabs(flat_mm))


def plan_arc(
    current: tuple,
    target: tuple,
    offset: tuple,
    clockwise: bool,
    axes: tuple[int, int, int],
    resolution_mm: float,
) -> tuple[list[tuple[float, float, float]], tuple[float, float], float, float]:
    """Chord end points of an arc, by Klipper's rule.

    Parameters
    ----------
    current, target : sequence of 3 float
        Start and end (x, y, z) in G-code coordinates, mm.
    offset : (float, float)
        Centre minus start in the plane's two axes (I/J, I/K or J/K), mm.
    clockwise : bool
    axes : (alpha, beta, helical)
        Indices of the plane's axes and of the helical axis, e.g. (0, 1, 2) for G17.
    resolution_mm : float
        Nominal chord length.

    Returns
    -------
    points : list of (x, y, z)
        Chord end points; the last is ``target``.
    center : (float, float)
        Centre in the plane, mm.
    radius : float
    angular_travel : float
        Signed, rad (negative clockwise).
    """
    a, b, h = axes
    center_p = current[a] + offset[0]
    center_q = current[b] + offset[1]
    angular_travel, radius, mm_of_travel = arc_travel(current, target, offset, clockwise, axes)
    linear_travel = target[h] - current[h]
    segments = max(1.0, math.floor(mm_of_travel / resolution_mm))
    theta_per_segment = angular_travel / segments
    linear_per_segment = linear_travel / segments
    points: list[tuple[float, float, float]] = []
    for i in range(1, int(segments)):
        cos_ti = math.cos(i * theta_per_segment)
        sin_ti = math.sin(i * theta_per_segment)
        rp = -offset[0] * cos_ti + offset[1] * sin_ti
        rq = -offset[0] * sin_ti - offset[1] * cos_ti
        c = [0.0, 0.0, 0.0]
        c[a] = center_p + rp
        c[b] = center_q + rq
        c[h] = current[h] + i * linear_per_segment
        points.append((c[0], c[1], c[2]))
    points.append((float(target[0]), float(target[1]), float(target[2])))
    return points, (center_p, center_q), radius, angular_travel
