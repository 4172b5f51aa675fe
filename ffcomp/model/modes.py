"""Modal summary of the LPV model: natural frequencies, damping ratios and mode shapes per pose.

The coupled mechanical poles are the eigenvalues of ``[[0, I], [-M^-1 K, -M^-1 C]]``; the drive
(electrical) poles are those of each tower's drive filter and do not depend on the pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .lpv import LpvModel, PoseMatrices, frequency_response, mech_arrays

__all__ = ["ModalSummary", "modes", "workspace_grid", "DriveMode", "drive_modes", "z_resonance_hz"]

_AXIS = np.array(["x", "y", "z"])


@dataclass(frozen=True)
class ModalSummary:
    """Coupled mechanical modes at P poses, sorted by frequency.

    Attributes
    ----------
    xyz_m : ndarray, shape (P, 3)
    freq_hz : ndarray, shape (P, 3)
        Undamped natural frequencies ``|lambda| / 2 pi``, Hz.
    damping : ndarray, shape (P, 3)
        Damping ratios ``-Re(lambda) / |lambda|``.
    shape_joint : ndarray, shape (P, 3, 3)
        Mode shapes in carriage coordinates, unit norm, ``shape_joint[p, :, j]`` for mode j.
    shape_task : ndarray, shape (P, 3, 3)
        The same mapped through ``J`` to nozzle motion, unit norm.
    """

    xyz_m: np.ndarray
    freq_hz: np.ndarray
    damping: np.ndarray
    shape_joint: np.ndarray
    shape_task: np.ndarray

    @property
    def direction(self) -> np.ndarray:
        """Dominant task-space axis of each mode, shape (P, 3) of ``"x"|"y"|"z"``."""
        return _AXIS[np.argmax(np.abs(self.shape_task), axis=1)]

    def to_dict(self) -> dict:
        out = []
        for p in range(self.xyz_m.shape[0]):
            out.append({
                "position_mm": (self.xyz_m[p] * 1e3).round(6).tolist(),
                "modes": [
                    {
                        "freq_hz": float(self.freq_hz[p, j]),
                        "damping_ratio": float(self.damping[p, j]),
                        "direction": str(self.direction[p, j]),
                        "shape_task": self.shape_task[p, :, j].round(6).tolist(),
                        "shape_joint": self.shape_joint[p, :, j].round(6).tolist(),
                    }
                    for j in range(self.freq_hz.shape[1])
                ],
            })
        return {"poses": out}


def modes(model_or_mats, xyz_m=None) -> ModalSummary:
    """Coupled mechanical modes at each pose (batched eigen-decomposition)."""
    mats = model_or_mats if isinstance(model_or_mats, PoseMatrices) else model_or_mats.matrices(xyz_m)
    A, _ = mech_arrays(mats)
    lam, vec = np.linalg.eig(A)
    # keep one of each conjugate pair (Im > 0); overdamped real pairs keep the slower one
    order = np.argsort(-lam.imag, axis=1)[:, :3]
    lam3 = np.take_along_axis(lam, order, axis=1)
    v3 = np.take_along_axis(vec, order[:, None, :], axis=2)[:, :3, :]
    wn = np.abs(lam3)
    zeta = -lam3.real / np.where(wn > 0, wn, 1.0)
    srt = np.argsort(wn, axis=1)
    wn = np.take_along_axis(wn, srt, axis=1)
    zeta = np.take_along_axis(zeta, srt, axis=1)
    v3 = np.take_along_axis(v3, srt[:, None, :], axis=2)
    # real mode shapes: rotate each complex vector so its largest entry is real, keep the real part
    k = np.argmax(np.abs(v3), axis=1)
    ph = np.take_along_axis(v3, k[:, None, :], axis=1)
    vr = (v3 * np.conj(ph) / np.abs(ph)).real
    vr /= np.linalg.norm(vr, axis=1, keepdims=True)
    _align_degenerate(wn, vr, mats.J)
    vt = mats.J @ vr
    vt /= np.linalg.norm(vt, axis=1, keepdims=True)
    return ModalSummary(mats.xyz_m, wn / (2 * np.pi), zeta, vr, vt)


def _align_degenerate(wn: np.ndarray, vr: np.ndarray, J: np.ndarray, rtol: float = 1e-6) -> None:
    """Within a (numerically) repeated mode pair the eigenvectors are arbitrary; replace them, in
    place, by the pair whose nozzle motions lie along coordinate axes (x and y at the bed centre)."""
    for p in range(wn.shape[0]):
        for j in range(wn.shape[1] - 1):
            if abs(wn[p, j + 1] - wn[p, j]) > rtol * wn[p, j]:
                continue
            S, _ = np.linalg.qr(vr[p][:, j:j + 2])  # joint-space subspace (3, 2)
            T = J[p] @ S  # its nozzle motions
            coef, *_ = np.linalg.lstsq(T, np.eye(3), rcond=None)  # best combination for each axis
            fit = np.linalg.norm(T @ coef - np.eye(3), axis=0)
            axes = np.sort(np.argsort(fit)[:2])
            for k, a in enumerate(axes):
                v = S @ coef[:, a]
                vr[p][:, j + k] = v / np.linalg.norm(v)


@dataclass(frozen=True)
class DriveMode:
    """The drive (electrical) resonance of one tower."""

    tower: str
    freq_hz: float
    damping: float
    rhp_zero_hz: float | None


def drive_modes(model: LpvModel) -> list[DriveMode]:
    """The electrical pair of each tower, and its right-half-plane zero if ``d1 < 0``."""
    cp = model.carriage
    out = []
    for i, name in enumerate("ABC"):
        wn = np.sqrt(cp.d0[i])
        z = -cp.d0[i] / cp.d1[i] if cp.d1[i] != 0 else None
        out.append(DriveMode(name, float(wn / (2 * np.pi)), float(cp.d2[i] / (2 * wn)),
                             float(z / (2 * np.pi)) if z is not None and z > 0 else None))
    return out


def workspace_grid(geometry, z_m: float, step_m: float = 0.01) -> np.ndarray:
    """Grid points (N, 3) inside the print radius at height ``z_m`` (for mode and error maps)."""
    r = geometry.print_radius_m
    g = np.arange(-r, r + 1e-12, step_m)
    X, Y = np.meshgrid(g, g, indexing="xy")
    ok = X**2 + Y**2 <= r**2 + 1e-12
    return np.stack([X[ok], Y[ok], np.full(ok.sum(), z_m)], axis=1)


def z_resonance_hz(model: LpvModel, xyz_m=(0.0, 0.0, 0.0), *, f_min_hz: float = 5.0, f_max_hz: float = 500.0,
                   n: int = 4000) -> float:
    """The resonance a z move excites most: the frequency (Hz) of the largest peak of the nozzle's
    z response to a z command, ``|H_zz(f)|`` of the full model (drive pair, coupled mechanics and
    every effect), at ``xyz_m`` (m, default the bed centre), searched on ``n`` log-spaced
    frequencies from ``f_min_hz`` to ``f_max_hz`` and refined by a parabola through the peak."""
    f = np.geomspace(f_min_hz, f_max_hz, n)
    h = np.abs(np.asarray(frequency_response(model, np.atleast_2d(np.asarray(xyz_m, float)), f))[0, 2, 2])
    k = int(np.clip(np.argmax(h), 1, n - 2))
    lf, y = np.log(f[k - 1:k + 2]), h[k - 1:k + 2]
    den = y[0] - 2 * y[1] + y[2]
    off = 0.5 * (y[0] - y[2]) / den if den < 0 else 0.0
    return float(np.exp(lf[1] + off * (lf[2] - lf[1])))
