"""Where the G-code writer puts its points: Douglas-Peucker *in time*.

A segment ends where linear interpolation in time (the firmware moves a segment at constant speed)
would stray from the compensated samples by more than the tolerance.  Pure numeric kernels, no
state: :func:`adaptive_breakpoints` on one run, :func:`breakpoints_runs` on many runs at once (the
same points, one vectorised pass per level of the recursion).
"""

from __future__ import annotations

import numpy as np

from ..linalg3 import max_abs3

__all__ = ["adaptive_breakpoints", "breakpoints_runs"]


def adaptive_breakpoints(P: np.ndarray, tol: float) -> np.ndarray:
    """Indices (including 0 and len-1) such that time-linear interpolation between consecutive
    breakpoints stays within ``tol`` of every point of ``P`` (shape (n, d)); Douglas-Peucker in time."""
    n = len(P)
    if n <= 2:
        return np.arange(n)
    keep = np.zeros(n, bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        f = (np.arange(i + 1, j) - i) / (j - i)
        lerp = P[i] + f[:, None] * (P[j] - P[i])
        d = max_abs3(P[i + 1:j] - lerp)
        k = int(np.argmax(d))
        if d[k] > tol:
            mid = i + 1 + k
            keep[mid] = True
            stack.append((i, mid))
            stack.append((mid, j))
    return np.nonzero(keep)[0]


def breakpoints_runs(P: np.ndarray, first: np.ndarray, last: np.ndarray, tol: float,
                      keep: np.ndarray) -> np.ndarray:
    """:func:`adaptive_breakpoints` on many runs of ``P`` at once (the same points as run by run).

    Run ``r`` spans ``P[first[r]:last[r] + 1]``; ``keep`` marks the points kept already (at least
    each run's ends).  The Douglas-Peucker recursion runs breadth first: every open interval of
    every run is split in the same vectorised pass.
    """
    I, J = np.asarray(first), np.asarray(last)
    sel = J - I >= 2
    I, J = I[sel], J[sel]
    cols = [np.ascontiguousarray(P[:, c]) for c in range(P.shape[1])]  # (1-D passes are faster)
    while len(I):
        L = J - I - 1
        st = np.cumsum(L) - L
        rep = np.repeat(np.arange(len(I)), L)
        pos = np.arange(int(L.sum())) - np.repeat(st - I - 1, L)
        f = (pos - I[rep]) / (J - I)[rep]
        dev = None  # max over the columns of |P - lerp|, lerp = P_I + f (P_J - P_I)
        for Pc in cols:
            PI = Pc[I]
            d = np.abs(Pc[pos] - (PI[rep] + f * (Pc[J] - PI)[rep]))
            dev = d if dev is None else np.maximum(dev, d)
        mx = np.maximum.reduceat(dev, st)
        hit = np.nonzero(dev == mx[rep])[0]
        firsthit = hit[np.concatenate(([True], rep[hit[1:]] != rep[hit[:-1]]))]
        split = firsthit[mx[rep[firsthit]] > tol]
        if not len(split):
            break
        iv = rep[split]
        mid = pos[split]
        keep[mid] = True
        I = np.concatenate([I[iv], mid])
        J = np.concatenate([mid, J[iv]])
        sel = J - I >= 2
        I, J = I[sel], J[sel]
    return keep
