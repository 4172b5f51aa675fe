"""Bounded least squares: the exact active-set QP and the OSQP call that keeps Ctrl-C.

The windows of the streaming inverse, the pin repair, Klipper's delta caps and the holds' bound all
solve ``argmin 1/2 c^T G c - g^T c`` subject to ``lo <= A c <= hi``.  :func:`active_set_qp` solves
it exactly from the unconstrained minimiser where the working set stays small (the usual case: a
few rows of a window bind); where it gives up, the caller builds OSQP's problem and solves it with
:func:`osqp_solve`.
"""

from __future__ import annotations

import numpy as np

from ..errors import Interrupted

__all__ = ["active_set_qp", "osqp_solve"]


def osqp_solve(solver):
    """``solver.solve()`` that keeps Ctrl-C: OSQP installs its own SIGINT handler while it iterates,
    so a Ctrl-C then only ends the solve (status ``"interrupted"``) and never reaches Python's
    handler; it is raised here as :class:`~ffcomp.errors.Interrupted` (the run stops, exit 130)."""
    res = solver.solve(raise_error=False)
    if res.info.status == "interrupted":
        import signal

        raise Interrupted(signal.SIGINT)
    return res


def active_set_qp(c0: np.ndarray, A, lo: np.ndarray, hi: np.ndarray, g_solve, nJ: int, C: int,
                   max_iter: int = 60) -> np.ndarray | None:
    """``argmin 1/2 c^T G c - g^T c`` subject to ``lo <= A c <= hi``, exactly, from the unconstrained
    minimiser ``c0 = G^-1 g`` (channel-major, C blocks of nJ; ``G`` block-diagonal with one block
    per channel, applied inverted by ``g_solve``).  Rows that ``c`` breaks join the working set at the
    bound they break; while a row's multiplier has the wrong sign, the worst such row leaves it; the
    equality-constrained minimiser ``c0 - G^-1 A_W^T lambda`` is solved again.  None when a working set
    comes back (a cycle), the rounds run out, or the working set is degenerate: the caller falls back
    to OSQP.
    """
    A = A.tocsr()
    m = A.shape[0]
    scale = np.where(np.isfinite(hi), np.abs(hi), 0.0) + np.where(np.isfinite(lo), np.abs(lo), 0.0)
    tol = 1e-9 * np.maximum(scale, 1e-12)
    side = np.zeros(m, np.int8)  # +1: held at hi, -1: held at lo
    cols: dict = {}  # row -> G^-1 a_row (reused while the row stays in the working set)
    seen: set = set()
    c = c0
    for _ in range(max_iter):
        v = A @ c
        new_hi, new_lo = (v > hi + tol) & (side == 0), (v < lo - tol) & (side == 0)
        if not (new_hi.any() or new_lo.any()):
            return c
        side[new_hi], side[new_lo] = 1, -1
        while True:  # the working set's minimiser; the worst wrong-signed row leaves, one at a time
            w = np.nonzero(side)[0]
            key = (w.tobytes(), side[w].tobytes())
            if key in seen:
                return None
            seen.add(key)
            if not w.size:
                lam, Y = np.zeros(0), np.zeros((C * nJ, 0))
                break
            Aw = A[w].toarray()  # (k, C nJ)
            for i, row in zip(w.tolist(), Aw):
                if i not in cols:
                    cols[i] = np.concatenate([g_solve(row[ch * nJ:(ch + 1) * nJ]) for ch in range(C)])
            Y = np.stack([cols[i] for i in w.tolist()], axis=1)
            b = np.where(side[w] > 0, hi[w], lo[w])
            try:
                lam = np.linalg.solve(Aw @ Y, Aw @ c0 - b)
            except np.linalg.LinAlgError:
                return None
            score = side[w] * lam
            if not (score < 0).any():
                break
            side[w[int(np.argmin(score / np.sqrt(np.maximum(np.einsum("ij,ji->i", Aw, Y), 1e-300))))]] = 0
        c = c0 - Y @ lam
        if not np.all(np.isfinite(c)):
            return None
    return None
