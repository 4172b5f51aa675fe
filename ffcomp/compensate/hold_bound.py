"""The best command that stands still where a G-code file cannot move it: a bound, not a method.

A G-code file cannot move the nozzle during an extruder-only move or a dwell (a *hold*), and a z
move between two holds (a layer change's lift, a z-hop's lift and its move down) is a rest-to-rest
move whose z the firmware ramps at ``max_z_accel`` at most.  This module finds, for one window
around such samples, the command that follows the plan best under those constraints, every other
sample free (a knot per sample: the finest command the firmware can be given) with only a light
penalty on the correction's acceleration:

    min_Y  || J (H * J^-1 Y) ||^2  +  || (err / acc) D2 Y / dt^2 ||^2,
    J^-1 Y = c - c*  (c* the exact, unconstrained command),   J^-1 Y = q - c*  on the holds,

``H`` the pulse response (carriage command -> carriage position) of the model linearised at the
window's pose, ``J = dX/dq`` there (``Y`` is the correction in the nozzle frame, the first term the
change of the nozzle's tracking error over the window and its ringing tail), ``D2`` the second
difference.  On a z move either the nozzle's z is fixed to the plan (``pin_z``: what the pipeline
does) or the command's acceleration is boxed, per axis of the nozzle frame (``accel_box``: what the
firmware allows, Klipper's ``max_z_accel`` in z and the run's ``ACCEL`` in x and y); its x and y
stay free.

Since the exact command already follows the plan, the minimum is the least tracking error any
command under those constraints can leave, to the linearisation and to the penalty's weight
(``acc`` m/s^2 of acceleration in a sample cost as much as ``err`` of nozzle error; the default lets
the command accelerate at hundreds of m/s^2, far beyond what a firmware runs on time).  The
pipeline's pin repair (:mod:`ffcomp.compensate.pin_repair`) solves a coarser version of the same
problem (knots every few samples, heavier acceleration penalties that keep the firmware on its
clock).  ``benchmarks/bench_hold_bound.py`` applies it at every layer change and z-hop of the
fidelity bench's files.  Pure numerics: no files, no G-code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import osqp
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse import csc_matrix, csr_matrix

from ..errors import SolverError
from .qp import active_set_qp, osqp_solve

__all__ = ["PinnedOptimum", "pinned_optimum", "response_matrix"]


@dataclass(frozen=True)
class PinnedOptimum:
    """The optimal correction of one window.

    correction_m : (n, 3) ``D``, the change of the command, m (equal to the given values on the pins)
    response_m : (n + L, 3) the nozzle's response to it (window and tail), m
    objective : the minimised value (nozzle error part plus penalty, m^2)
    """

    correction_m: np.ndarray
    response_m: np.ndarray
    objective: float


def response_matrix(H: np.ndarray, J: np.ndarray, n: int) -> np.ndarray:
    """The linear map from a window's correction in the nozzle frame ``Y`` (n, 3) (the command's
    change ``D = J^-1 Y``), flattened sample-major, to the nozzle's response (n + L, 3), flattened
    likewise: ``J (H * J^-1 Y)``.

    ``H``: (L, 3, 3) pulse responses (``H[i]`` maps the command at sample k to the carriage positions
    at k + i); ``J``: (3, 3) ``dX/dq``.
    """
    H = np.asarray(H, float)
    J = np.asarray(J, float)
    L = H.shape[0]
    JHJi = np.einsum("ij,ljk,km->lim", J, H, np.linalg.inv(J))  # (L, 3 out, 3 in)
    T = np.zeros((n + L, 3, n, 3))
    for k in range(n):
        T[k:k + L, :, k, :] = JHJi
    return T.reshape(3 * (n + L), 3 * n)


def pinned_optimum(H: np.ndarray, J: np.ndarray, pin: np.ndarray, pinned_m: np.ndarray, dt_s: float,
                   pin_z: np.ndarray | None = None, accel_box: tuple | None = None, accel_m_s2: float = 10.0,
                   err_m: float = 1e-6) -> PinnedOptimum:
    """The correction ``D`` of least nozzle error with ``D = pinned_m`` on the pins (see the module).

    Parameters
    ----------
    H : ndarray, shape (L, 3, 3)
        Pulse responses, carriage command -> carriage position, of the model at the window's pose.
    J : ndarray, shape (3, 3)
        ``dX/dq`` at the window's pose.
    pin : ndarray of bool, shape (n,)
        Samples where the command is fixed (all three carriages).
    pinned_m : ndarray, shape (n, 3)
        The correction there (the plan minus the exact command, carriage frame), m; ignored on
        free samples.
    dt_s : float
        Sample period, s.
    pin_z : ndarray of bool, shape (n,), optional
        Samples where only the nozzle's z is fixed (to ``J pinned_m``'s z, at the window's pose): a z
        move the firmware runs as planned in z, with x and y free.
    accel_box : (mask, base_m, limits_m_s2), optional
        On the samples ``mask`` (n,) selects (the second differences that touch them, but for those
        of pinned samples alone), the nozzle's acceleration of the whole command, ``base_m`` (n, 3)
        (the exact command's nozzle position) plus the correction's, stays within ``limits_m_s2``
        (3,) per axis (``inf``: no bound on that axis): a box on second differences, solved exactly
        by an active-set method (OSQP where it gives up).
    accel_m_s2, err_m : float
        The penalty on the correction's nozzle acceleration: ``accel_m_s2`` in a sample costs as
        much as ``err_m`` of nozzle error (default 10 m/s^2 per micrometre: commands up to hundreds
        of m/s^2, so the bound is optimistic).
    """
    pin = np.asarray(pin, bool)
    n = len(pin)
    pin_z = np.zeros(n, bool) if pin_z is None else np.asarray(pin_z, bool) & ~pin
    if np.shape(pinned_m) != (n, 3):
        raise ValueError(f"pinned_m must have shape ({n}, 3), got {np.shape(pinned_m)}")
    if len(pin_z) != n:
        raise ValueError(f"pin_z must have {n} samples, got {len(pin_z)}")
    if not accel_m_s2 > 0 or not err_m > 0:
        raise ValueError(f"accel_m_s2 and err_m must be positive, got {accel_m_s2} and {err_m}")
    J = np.asarray(J, float)
    A = response_matrix(H, J, n)
    S2 = np.kron(np.diff(np.eye(n), 2, axis=0), np.eye(3))  # second differences, row 3 k + axis
    D2 = S2 * (err_m / accel_m_s2 / dt_s**2)
    fixed = np.repeat(pin, 3)
    fixed[2::3] |= pin_z
    y = np.zeros(3 * n)  # the correction in the nozzle frame
    y[fixed] = (np.asarray(pinned_m, float) @ J.T).reshape(-1)[fixed]
    free = ~fixed
    if free.any():
        Af, Df = A[:, free], D2[:, free]
        rhs = -(Af.T @ (A[:, fixed] @ y[fixed]) + Df.T @ (D2[:, fixed] @ y[fixed]))
        G = Af.T @ Af + Df.T @ Df
        G[np.diag_indices_from(G)] += 1e-12 * max(float(np.mean(np.diag(G))), 1e-300)
        factor = cho_factor(G, lower=True, check_finite=False)
        y[free] = cho_solve(factor, rhs, check_finite=False)
        if accel_box is not None:
            y[free] = _boxed(y, free, fixed, G, rhs, factor, accel_box, S2, dt_s)
    resp = A @ y
    obj = float(resp @ resp + np.sum((D2 @ y) ** 2))
    return PinnedOptimum(y.reshape(n, 3) @ np.linalg.inv(J).T, resp.reshape(-1, 3), obj)


def _boxed(y: np.ndarray, free: np.ndarray, fixed: np.ndarray, G: np.ndarray, rhs: np.ndarray, factor,
           accel_box: tuple, S2: np.ndarray, dt_s: float) -> np.ndarray:
    """The free values of ``y`` with the acceleration box of :func:`pinned_optimum` (``y[free]``
    holds the unconstrained minimiser; ``S2`` the second differences, row ``3 k + axis``)."""
    n = len(y) // 3
    mask, base, lims = accel_box
    mask, base, lims = np.asarray(mask, bool), np.asarray(base, float), np.asarray(lims, float)
    if len(mask) != n or base.shape != (n, 3) or lims.shape != (3,):
        raise ValueError(f"accel_box's mask, base_m and limits_m_s2 must have shapes ({n},), ({n}, 3) and (3,)")
    # every second difference that touches a masked sample (k spans samples k, k + 1, k + 2): the
    # firmware enters and leaves such a stretch at its acceleration too, not with a step of speed
    centres = np.nonzero(mask[:-2] | mask[1:-1] | mask[2:])[0]
    axes = np.nonzero(np.isfinite(lims))[0]
    idx = (3 * centres[None, :] + axes[:, None]).reshape(-1)
    rows = S2[idx]
    shift = rows @ base.reshape(-1) + rows[:, fixed] @ y[fixed]
    room = np.repeat(lims[axes], centres.size) * dt_s**2
    live = np.any(rows[:, free] != 0, axis=1)  # (a difference of pinned samples alone is the pins')
    rows, shift, room = rows[live], shift[live], room[live]
    if not len(rows):
        return y[free]
    A = csr_matrix(rows[:, free])
    lo, hi = -room - shift, room - shift
    c = active_set_qp(y[free], A, lo, hi, lambda r: cho_solve(factor, r, check_finite=False), int(free.sum()), 1)
    if c is None:  # (a cycle or a degenerate working set) OSQP, to its tolerance
        prob = osqp.OSQP()
        prob.setup(csc_matrix(np.triu(G)), -rhs, A.tocsc(), lo, hi, verbose=False, eps_abs=1e-12,
                   eps_rel=1e-10, max_iter=20000, polishing=True)
        res = osqp_solve(prob)
        if res.info.status not in ("solved", "solved inaccurate"):
            raise SolverError(f"hold bound: the acceleration QP was not solved (OSQP: {res.info.status})")
        c = res.x
    return c
