"""Uniform B-spline basis on a sample grid (the command parametrisation of the FBS inverse).

Knots are spaced ``m`` samples apart (``h = m dt``); basis ``j`` starts at sample ``s_j`` and is
supported on ``(p + 1) m`` samples, so every basis function is a shifted copy of one sampled shape.
That shift structure is what makes filtered bases cheap: one filtered kernel per pose (or one in
total for an LTI filter).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.interpolate import BSpline

__all__ = ["UniformBasis"]


@dataclass(frozen=True)
class UniformBasis:
    """Cardinal B-spline of degree ``degree`` with knots every ``m`` samples of ``dt_s``.

    Attributes
    ----------
    degree : int
        Spline degree (5 = quintic: continuous jerk and snap).
    m : int
        Samples per knot interval.
    dt_s : float
        Sample time, s.
    """

    degree: int = 5
    m: int = 5
    dt_s: float = 1e-3

    @property
    def h_s(self) -> float:
        """Knot spacing, s."""
        return self.m * self.dt_s

    @property
    def support(self) -> int:
        """Samples spanned by one basis function (its values at both ends are zero)."""
        return (self.degree + 1) * self.m

    @cached_property
    def _element(self) -> BSpline:
        return BSpline.basis_element(np.arange(self.degree + 2, dtype=float), extrapolate=False)

    def shape(self, deriv: int = 0) -> np.ndarray:
        """The sampled basis shape (``support`` samples) or its ``deriv``-th time derivative."""
        x = np.arange(self.support) / self.m
        el = self._element if deriv == 0 else self._element.derivative(deriv)
        v = np.nan_to_num(el(x))
        return v / self.h_s**deriv

    def evaluate(self, coef: np.ndarray, n: int, deriv: int = 0) -> np.ndarray:
        """Spline values at samples ``0..n-1`` for coefficients of bases starting at ``j m``.

        ``coef`` has shape (J,) or (J, k); basis ``j`` starts at sample ``j * m``.
        """
        coef = np.asarray(coef, float)
        one = coef.ndim == 1
        c = coef[:, None] if one else coef
        b = self.shape(deriv)
        up = np.zeros((len(c) * self.m + self.support, c.shape[1]))
        up[:: self.m][: len(c)] = c
        out = np.empty((n, c.shape[1]))
        for i in range(c.shape[1]):
            full = np.convolve(up[:, i], b)[:n]
            out[: len(full), i] = full
            out[len(full):, i] = 0.0
        return out[:, 0] if one else out

    def greville_offset(self) -> int:
        """Sample offset of a basis function's centre from its start."""
        return self.support // 2
