"""The mechanics stage's windowed least squares, split into the delta's modes.

At the centre of a delta whose three towers are alike (the same arms, carriages and drives,
120 degrees apart), the mechanics' response to a basis function on each tower's drive,
``K[i, :, j]`` (input tower ``i``, output carriage ``j``), is a symmetric circulant matrix of
kernels: one for a tower's own carriage and one for each of the others.  The orthonormal mode
shapes ``MODES`` (all carriages together: z; two differential shapes: x and y) diagonalise it:
``K_m = MODES K MODES^T = diag(k_common, k_diff, k_diff)``.  Since ``MODES`` is orthonormal, the
least squares ``min |tgt - Phi c|^2 + lam |c - prior|^2`` keeps its value in modal coordinates
and splits into one single-input problem for the common mode and one, with two right-hand sides,
for the differential modes, with the same Tikhonov weight ``lam`` (that of the coupled problem).

The coupled window operator is ``3 nJ x 3 rows``; the modal ones are ``nJ x rows``: a ninth of
the products, in operators that stay in cache.  :func:`modal_split` says whether a kernel splits
(the model at the centre of any profile whose towers are alike; a profile with per-tower
differences keeps the coupled solve).  Pure numerics.
"""

from __future__ import annotations

import numpy as np

from .bspline import UniformBasis
from .fbs import _dense_basis

__all__ = ["MODES", "modal_split", "ModalFbs"]

#: rows: the common mode and the two differential mode shapes of the three carriages (orthonormal)
MODES = np.array([[1.0, 1.0, 1.0] / np.sqrt(3.0), [1.0, -1.0, 0.0] / np.sqrt(2.0),
                  [1.0, 1.0, -2.0] / np.sqrt(6.0)])


def modal_split(kernel: np.ndarray, rtol: float = 1e-9) -> tuple[np.ndarray, np.ndarray] | None:
    """The common and differential kernels ``(L,)`` of a three-tower kernel ``(3, L, 3)`` if the
    mode shapes diagonalise it (to ``rtol`` of its largest value), else None."""
    K = np.asarray(kernel, float)
    if K.ndim != 3 or K.shape[0] != 3 or K.shape[2] != 3:
        return None
    Km = np.einsum("ai,ilj,bj->alb", MODES, K, MODES)
    tol = rtol * max(float(np.abs(K).max()), 1e-300)
    off = Km.copy()
    for a in range(3):
        off[a, :, a] = 0.0
    if np.abs(off).max() > tol or np.abs(Km[1, :, 1] - Km[2, :, 2]).max() > tol:
        return None
    return Km[0, :, 0].copy(), 0.5 * (Km[1, :, 1] + Km[2, :, 2])


class ModalWeight:
    """The coupled problem's Tikhonov weight for a window of ``rows`` samples (``weight(rows)``):
    ``reg`` times the mean diagonal of its Gram matrix, the same in modal coordinates (a trace)."""

    def __init__(self, kernels: tuple, basis: UniformBasis, reg: float, row_stride: int):
        self.kernels, self.basis, self.reg, self.rs = kernels, basis, reg, row_stride
        self._lams: dict[int, float] = {}

    def __call__(self, rows: int) -> float:
        hit = self._lams.get(rows)
        if hit is None:
            m = self.basis.m
            nJ = -(-rows // m)
            tr = []
            for k in self.kernels:
                Kb = np.broadcast_to(k[None, None, :, None], (nJ, 1, len(k), 1))
                Ph = _dense_basis(Kb, np.arange(nJ) * m, rows, self.rs)
                tr.append(float(np.sum(Ph * Ph)))
            hit = self._lams[rows] = self.reg * max((tr[0] + 2.0 * tr[1]) / (3.0 * nJ), 1e-30)
        return hit


class ModalFbs:
    """A three-tower :class:`~ffcomp.compensate.stream.FbsStream` (same parameters, same
    ``feed`` / ``finish``) solved in the modes of :func:`modal_split`'s kernels."""

    def __init__(self, k_common: np.ndarray, k_diff: np.ndarray, basis: UniformBasis, window: int, advance: int,
                 reg: float, row_stride: int = 1):
        from .stream import FbsStream

        self.kernels = (np.asarray(k_common, float), np.asarray(k_diff, float))
        # (a weight of its own, not a bound method: the two streams referring back to this object
        # made a reference cycle, freed only by the cyclic collector, which the CLI runs rarely; a
        # file with a stop at every retraction kept every stream's solves, 5 MB each: 1.5 GB)
        self.lam = ModalWeight(self.kernels, basis, reg, row_stride)
        self.common = FbsStream(self.kernels[0][None, :, None], basis, window, advance, reg, row_stride,
                                lam_fn=self.lam)
        self.diff = FbsStream(self.kernels[1][None, :, None], basis, window, advance, reg, row_stride, channels=2,
                              lam_fn=self.lam)

    def feed(self, target: np.ndarray) -> np.ndarray:
        """Target rows (n, 3) of the three carriages; returns the spline values (m, 3) of the
        samples that became final."""
        tm = np.asarray(target, float).reshape(-1, 3) @ MODES.T
        return self._back(self.common.feed(tm[:, :1]), self.diff.feed(tm[:, 1:]))

    def finish(self) -> np.ndarray:
        return self._back(self.common.finish(), self.diff.finish())

    @staticmethod
    def _back(vc: np.ndarray, vd: np.ndarray) -> np.ndarray:
        if len(vc) != len(vd):  # (the same windows: never)
            raise RuntimeError("the modal streams went out of step")
        return np.hstack([vc.reshape(-1, 1), vd.reshape(-1, 2)]) @ MODES
