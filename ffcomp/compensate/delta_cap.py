"""Klipper's delta caps on a written command, and the smallest change of the command that keeps them.

Klipper plans every segment of a delta at ``min(ACCEL, max_z_accel * d/|dz|)``: along the segment
(its trapezoid) and, through its junction rules, across it (the centripetal rule
``v^2 <= a d / tan``, and the square-corner rule ``v^2 <= R_jd * junction_deviation * a``, which on
dense samples bounds the turn per segment: ``a_n <= sqrt(8 junction_deviation a) / dt`` for small
angles).  Where the z rule makes ``a`` small (a steep segment), a compensated command that brakes,
or bends, harder than that runs late: the fidelity bench's z travel on other_delta (max_z_accel
3,000 mm/s^2, ACCEL 10,000) ran 0.93 ms off the clock into an XZ reversal, where the correction
turned the command steeper than the plan while it braked at the plan's 10,000 mm/s^2.

:func:`cap_breaks` finds such samples; :func:`cap_window` changes a window's command as little as the
model's response allows (the pin repair's least squares, :mod:`ffcomp.compensate.pin_repair`, every
sample a knot) so that its nozzle acceleration keeps the caps, with the plan's own acceleration as
the licence where the plan itself runs past them.  Pure numeric kernels: SI units throughout.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import cho_solve
from scipy.sparse import csr_matrix

from ..kinematics import forward, jacobian
from ..linalg3 import sq_norm3
from .pin_repair import MAX_BOUND_CHANGE_M, STILL_M_S, XY_SHARE, RepairConfig, _cached, _operator, _second_difference
from .qp import active_set_qp

__all__ = ["DeltaCap", "cap_breaks", "cap_window", "jacobian_table", "CAP_SHARE", "CAP_SLACK", "EDGE_ACROSS_SHARE"]

#: :func:`cap_window` keeps the command within this share of the caps
CAP_SHARE = 0.97
#: :func:`cap_breaks` flags a sample past this multiple of :data:`CAP_SHARE` of a cap
CAP_SLACK = 1.02
#: the cap across the path is this much lower where a pinned run meets the free command: the writer
#: ends a pinned run on the plan's corner, at its time, so a short segment meets the first free one
#: there, and Klipper's centripetal rule takes the shorter segment's length (a random file's free
#: command bent 1.4 degrees off a pinned z-hop, 2 um, and the firmware braked it from 84 to 76 mm/s)
EDGE_ACROSS_SHARE = 0.5


def jacobian_table(geom, margin: float = 1.25, rings: int = 32, spokes: int = 72) -> tuple:
    """Bounds of the delta's Jacobian ``J = dX/dq`` by distance from the centre (J depends on x and
    y only): ``(r_m, sigma, zdev)``, at ``rings + 1`` radii from 0 to the print radius, the largest
    singular value of J and the largest norm of its z row less ``(1, 1, 1)/3`` (the carriages'
    mean) over ``spokes`` angles within each ring's outer radius, times ``margin``; beyond the
    print radius, the values at the rim times 2."""
    r = geom.print_radius_m * np.linspace(0.0, 1.0, rings + 1)
    ang = np.linspace(0.0, 2 * np.pi, spokes, endpoint=False)
    rr, aa = np.meshgrid(r, ang)
    J = jacobian(geom, np.c_[(rr * np.cos(aa)).ravel(), (rr * np.sin(aa)).ravel(), np.zeros(rr.size)])
    sig = np.linalg.norm(J, ord=2, axis=(1, 2)).reshape(rr.shape).max(axis=0)
    zdev = np.linalg.norm(J[:, 2, :] - 1.0 / 3.0, axis=1).reshape(rr.shape).max(axis=0)
    # within each ring's outer radius (bounds grow outward), the next ring's value covers the gap
    sig, zdev = np.maximum.accumulate(sig), np.maximum.accumulate(zdev)
    sig, zdev = np.r_[sig[1:], sig[-1]], np.r_[zdev[1:], zdev[-1]]
    return (np.r_[r, 10.0], margin * np.r_[sig, 2 * sig[-1]], margin * np.r_[zdev, 2 * zdev[-1]])


def _edges(pin: np.ndarray | None, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, share)``: the samples whose acceleration moves with the free ones (free, or pinned
    next to a free one), and the share (n,) of the cap across the path at each sample
    (:data:`EDGE_ACROSS_SHARE` at a pinned run's last sample and the free one after it)."""
    if pin is None or not np.any(pin):
        return np.ones(n, bool), np.ones(n)
    pin = np.asarray(pin, bool)
    prev, nxt = np.concatenate((pin[:1], pin[:-1])), np.concatenate((pin[1:], pin[-1:]))
    free_near = ~prev | ~nxt
    rows = ~pin | free_near
    edge = (pin & ~nxt) | (~pin & prev)  # where a pinned run ends (the writer's short segment)
    return rows, np.where(edge, EDGE_ACROSS_SHARE, 1.0)


@dataclass(frozen=True)
class DeltaCap:
    """The firmware numbers of the caps (SI).

    max_z_accel_m_s2 : ``[printer] max_z_accel``
    accel_m_s2 : the run-time ACCEL the output sets
    junction_deviation_m : Klipper's ``junction_deviation`` at that ACCEL (from square_corner_velocity)
    dt_s : the written segments' time (the sample time)
    """

    max_z_accel_m_s2: float
    accel_m_s2: float
    junction_deviation_m: float
    dt_s: float
    #: :func:`jacobian_table` of the printer: :func:`cap_breaks`'s cheap screen of the samples that
    #: cannot break a cap (None: no screen)
    jacobian_bounds: tuple | None = None

    def limits(self, u_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(along, across)`` for unit directions with z component ``u_z`` (n,): the segment's
        acceleration (the largest nozzle acceleration along it) and the largest across it, m/s^2."""
        along = np.minimum(self.accel_m_s2, self.max_z_accel_m_s2 / np.maximum(np.abs(u_z), 1e-9))
        across = np.minimum(along, np.sqrt(8.0 * self.junction_deviation_m * along) / self.dt_s)
        return along, across


def _split(a: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Acceleration ``a`` (n, 3) along unit ``u`` (n, 3) (signed) and across it (magnitude)."""
    at = np.einsum("ij,ij->i", a, u)
    return at, np.sqrt(sq_norm3(a - at[:, None] * u))


def _diffs(p: np.ndarray, idx: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Speed (k,), unit velocity (k, 3) and acceleration (k, 3) of positions ``p`` (n >= 3, 3) at the
    samples ``idx`` (k,), by central differences (at the two ends: the velocity one-sided, the
    acceleration the neighbour's)."""
    n = len(p)
    lo, hi = np.maximum(idx - 1, 0), np.minimum(idx + 1, n - 1)
    v = (p[hi] - p[lo]) / ((hi - lo) * dt_s)[:, None]
    c = np.clip(idx, 1, n - 2)
    a = (p[c + 1] - 2 * p[c] + p[c - 1]) / dt_s**2
    sp = np.sqrt(sq_norm3(v))
    return sp, v / np.maximum(sp, 1e-15)[:, None], a


def _licence(cap: DeltaCap, xyz_plan: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
    """Per sample (or at the samples ``idx``), how far the plan itself runs past its own caps (at
    least 1): the command may too."""
    sp, u, a = _diffs(xyz_plan, np.arange(len(xyz_plan)) if idx is None else idx, cap.dt_s)
    along, across = cap.limits(u[:, 2])
    at, an = _split(a, u)
    over = np.maximum(np.abs(at) / along, an / across) / CAP_SHARE
    return np.where(sp >= STILL_M_S, np.maximum(over, 1.0), 1.0)


def _screen(q: np.ndarray, q_plan: np.ndarray, xyz_plan: np.ndarray, cap: DeltaCap) -> np.ndarray:
    """Samples (n,) that may break a cap, from cheap bounds: the command's nozzle velocity and
    acceleration differ from the plan's by at most the Jacobian's norm times the carriage
    differences' (to first order in the correction, micrometres), its z velocity by the carriages'
    mean and the z row's deviation from it (:func:`jacobian_table`, by distance from the centre).
    A break needs ``|a| |v_z| > mza |v|`` (along, or across at the centripetal cap) or
    ``|a| > sqrt(8 jd mza |v|/|v_z|) / dt`` (the square-corner cap).  Columns, not reductions over
    the axis of three (:mod:`ffcomp.linalg3`): this runs on every sample."""
    n = len(q)
    out = np.zeros(n, bool)
    if n < 3:
        return out
    dt = cap.dt_s
    r_tab, sig_tab, zdev_tab = cap.jacobian_bounds
    r = np.hypot(xyz_plan[1:-1, 0], xyz_plan[1:-1, 1])
    k = np.minimum(np.searchsorted(r_tab, r), len(r_tab) - 1)  # the ring at or beyond r
    jb, jz = sig_tab[k], zdev_tab[k]
    d1 = np.diff(xyz_plan, axis=0)
    v2 = sq_norm3(d1[1:] + d1[:-1]) * (0.5 / dt) ** 2  # the plan's speed^2, interior samples
    vz = np.abs(d1[1:, 2] + d1[:-1, 2]) * (0.5 / dt)
    a = np.sqrt(sq_norm3(d1[1:] - d1[:-1])) / dt**2
    e1 = np.diff(q - q_plan, axis=0)
    ev = e1[1:] + e1[:-1]
    dvn = np.sqrt(sq_norm3(ev)) * (0.5 / dt)
    dv = jb * dvn
    a += jb * np.sqrt(sq_norm3(e1[1:] - e1[:-1])) / dt**2
    # the correction's z velocity: the carriages' mean, and the z row's deviation from it
    vz += np.abs(ev[:, 0] + ev[:, 1] + ev[:, 2]) * (0.5 / (3 * dt)) + jz * dvn
    sp = np.sqrt(v2)
    sp_lo = np.maximum(sp - dv, 0.0)
    mza = 0.9 * CAP_SHARE * cap.max_z_accel_m_s2  # (0.9: room for the second-order terms)
    ratio = sp_lo / np.maximum(vz, 1e-15)  # at most 1/|u_z|
    lim = np.minimum(mza * ratio, np.sqrt(8.0 * cap.junction_deviation_m * mza * ratio) / dt)
    out[1:-1] = (vz * cap.accel_m_s2 > mza * sp_lo) & (sp + dv >= STILL_M_S) & (a > lim)
    return out


def cap_breaks(geom, q: np.ndarray, xyz_plan: np.ndarray, cap: DeltaCap, pin: np.ndarray | None = None,
               q_plan: np.ndarray | None = None) -> np.ndarray:
    """Samples (n,) where the command ``q`` (n, 3, carriage heights, m) accelerates along or across
    its path past :data:`CAP_SLACK` times :data:`CAP_SHARE` of the caps, on steep segments (where
    ``max_z_accel`` binds more than ACCEL) that move, and past what the plan ``xyz_plan`` (n, 3,
    m) takes there; never the two end samples.  ``pin`` (n,), optional: samples held (a pin
    window's); only those next to a free one are judged, at :data:`EDGE_ACROSS_SHARE` across where a
    pinned run meets the free command.  ``q_plan`` (n, 3), optional: the plan's carriage heights;
    with ``cap.jacobian_bounds`` only the samples a cheap screen cannot clear are judged
    exactly (the nozzle positions by forward kinematics cost most of the check)."""
    n = len(q)
    out = np.zeros(n, bool)
    if n < 3:
        return out
    rows, share = _edges(pin, n)
    at_idx = np.arange(n)
    if q_plan is not None and cap.jacobian_bounds is not None:
        cand = _screen(q, q_plan, xyz_plan, cap) & rows
        cand[0] = cand[-1] = False
        if not cand.any():
            return out
        c = np.nonzero(cand)[0]
        if c.size < n // 3:  # the candidates and their neighbours only
            near = np.zeros(n, bool)
            near[c - 1] = near[c] = near[c + 1] = True
            at_idx = np.flatnonzero(near)
    if at_idx.size == n:
        p, judged = forward(geom, q), at_idx
    else:  # the candidates (inner samples), from their own neighbours
        p, judged = np.zeros((n, 3)), c
        p[at_idx] = forward(geom, q[at_idx])
    sp, u, a = _diffs(p, judged, cap.dt_s)
    along, across = cap.limits(u[:, 2])
    at, an = _split(a, u)
    lic = _licence(cap, xyz_plan, judged)
    k = CAP_SHARE * CAP_SLACK * lic
    rj = rows[judged]
    if pin is not None:  # a pinned sample where the plan turns past its caps is the plan's own corner
        rj = rj & ~(np.asarray(pin, bool)[judged] & (lic > 1.0))
    bad = (rj & (sp >= STILL_M_S) & (along < cap.accel_m_s2)
           & ((np.abs(at) > k * along) | (an > k * share[judged] * across)))
    out[judged] = bad
    out[0] = out[-1] = False
    return out


def _rows(c: np.ndarray, J: np.ndarray, xyz_plan: np.ndarray, cap: DeltaCap, pin: np.ndarray | None = None):
    """Directions (R, 3), samples (R,) and limits (R,) of the cap rows of a window's command ``c``:
    on every inner sample of a steep segment that moves, the nozzle acceleration along the command's
    velocity and along two directions across it (each within ``1/sqrt(2)`` of the cap across: a box
    inside its disk).  ``J`` (n, 3, 3): the Jacobian per sample (the rows are linear in ``c``);
    ``pin``: as for :func:`cap_breaks`."""
    n = len(c)
    rows, share = _edges(pin, n)
    v = np.einsum("nij,nj->ni", J, np.gradient(c, axis=0)) / cap.dt_s
    sp = np.linalg.norm(v, axis=1)
    u = v / np.maximum(sp, 1e-15)[:, None]
    along, across = cap.limits(u[:, 2])
    lic = _licence(cap, xyz_plan)
    if pin is not None:  # (as in cap_breaks)
        rows = rows & ~(np.asarray(pin, bool) & (lic > 1.0))
    lic = CAP_SHARE * lic
    sel = np.nonzero(rows & (sp >= STILL_M_S) & (along < cap.accel_m_s2))[0]
    sel = sel[(sel > 0) & (sel < n - 1)]
    t = u[sel]
    # two unit normals per row: t x e (e the axis least along t), then t x n1
    e = np.zeros_like(t)
    e[np.arange(len(t)), np.argmin(np.abs(t), axis=1)] = 1.0
    n1 = np.cross(t, e)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    n2 = np.cross(t, n1)
    dirs = np.concatenate([t, n1, n2])
    samp = np.tile(sel, 3)
    ac = XY_SHARE * share[sel] * across[sel]
    lim = np.concatenate([along[sel], ac, ac]) * np.tile(lic[sel], 3)
    return dirs, samp, lim


def cap_window(H: np.ndarray, c: np.ndarray, J: np.ndarray, J_rows: np.ndarray, xyz_plan: np.ndarray,
               cap: DeltaCap, cfg: RepairConfig = RepairConfig(), pin: np.ndarray | None = None,
               cache: dict | None = None, key=None) -> np.ndarray:
    """The window's command ``c`` (n, 3, carriage heights, m) changed as little as the model's
    response allows so that its nozzle acceleration keeps the caps (:func:`_rows`); ``c`` itself
    where it does already or the exact solve gives up.

    ``H`` (L, 3, 3) and ``J`` (3, 3): the pulse response and Jacobian at the window's pose cell (the
    objective's, as in :func:`~ffcomp.compensate.pin_repair.repair_window`); ``J_rows`` (n, 3, 3):
    the Jacobian at each sample of the plan ``xyz_plan`` (n, 3) (the rows'); ``pin`` (n,), optional:
    samples held as they are (a pin window's, repaired already).  Every free sample is a knot: a
    coarser basis cannot change the acceleration between its knots.  ``cache``/``key``: the
    factorised normal equations per pose cell and pin pattern.  The correction vanishes beyond
    the window.
    """
    n = len(c)
    if n < 3:
        return c
    pin = np.zeros(n, bool) if pin is None else np.asarray(pin, bool)
    cfg1 = replace(cfg, knot_samples=1)
    dt_s = cap.dt_s
    op = _cached(cache, (key, n, "cap", np.packbits(pin).tobytes()), lambda: _operator(H, pin, J, dt_s, cfg1))
    if op.nf == 0:
        return c
    dirs, samp, lim = _rows(c, J_rows, xyz_plan, cap, pin)
    if not len(samp):
        return c
    DJ = np.einsum("ri,rij->rj", dirs, J_rows[samp]) / dt_s**2  # (R, 3): per carriage acceleration
    base = np.einsum("rj,rj->r", DJ, np.diff(c, 2, axis=0)[samp - 1])
    if np.all(np.abs(base) <= lim):
        return c
    D2 = _second_difference(op.S)[samp]  # (R, nf)
    A = np.hstack([DJ[:, j:j + 1] * D2 for j in range(3)])  # carriage-major
    zv = active_set_qp(np.zeros(3 * op.nf), csr_matrix(A), -lim - base, lim - base,
                        lambda r: cho_solve(op.factor, r, check_finite=False), 3 * op.nf, 1)
    if zv is None or not np.all(np.isfinite(zv)) or float(np.max(np.abs(zv))) > MAX_BOUND_CHANGE_M:
        return c
    return c + op.S @ zv.reshape(3, op.nf).T
