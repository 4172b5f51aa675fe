"""Exact-stop trapezoidal test paths (independent of the planner under test)."""

import numpy as np


def trapezoid_path(points_mm, v_mm_s=150.0, a_mm_s2=10000.0, dt=1e-3, dwell_s=0.05):
    """Straight moves through ``points_mm`` with full stops, sampled every ``dt`` -> xyz (N, 3) m."""
    out = [np.repeat(np.asarray(points_mm[:1], float), int(dwell_s / dt), 0)]
    for p0, p1 in zip(points_mm[:-1], points_mm[1:]):
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        d = np.linalg.norm(p1 - p0)
        if d == 0:
            continue
        ta = v_mm_s / a_mm_s2
        da = 0.5 * a_mm_s2 * ta**2
        if 2 * da > d:
            ta, tc = np.sqrt(d / a_mm_s2), 0.0
            vmax = a_mm_s2 * ta
        else:
            vmax, tc = v_mm_s, (d - 2 * da) / v_mm_s
        T = 2 * ta + tc
        t = np.minimum(np.arange(dt, T + dt / 2, dt), T)
        s = np.where(t < ta, 0.5 * a_mm_s2 * t**2,
                     np.where(t < ta + tc, 0.5 * a_mm_s2 * ta**2 + vmax * (t - ta), d - 0.5 * a_mm_s2 * (T - t) ** 2))
        out.append(p0 + (p1 - p0) * (s / d)[:, None])
    out.append(np.repeat(np.asarray(points_mm[-1:], float), int(dwell_s / dt), 0))
    return np.concatenate(out) * 1e-3


def square(cx, cy, side=60.0, z=30.0):
    h = side / 2
    return [(cx - h, cy - h, z), (cx + h, cy - h, z), (cx + h, cy + h, z), (cx - h, cy + h, z), (cx - h, cy - h, z)]
