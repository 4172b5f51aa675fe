"""Predict carriage motion for a command with the linear LPV model (time-varying, first-order hold).

The model is evaluated at the reference pose of every sample (LPV), discretised exactly for
commands linear between samples, and stepped in chunks so memory stays bounded.  This is the
prediction the CLI summary reports; the nonlinear simulator in :mod:`ffcomp.sim` is the judge.
"""

from __future__ import annotations

import numpy as np

from ..model.lpv import LpvModel, state_space_arrays
from .kernels import modal_foh

__all__ = ["predict_lpv"]


def predict_lpv(model: LpvModel, q_cmd_m: np.ndarray, xyz_path_m: np.ndarray, dt_s: float, *,
                chunk: int = 4096, frozen_xyz_m: np.ndarray | None = None) -> np.ndarray:
    """Carriage positions (N, 3) for commands ``q_cmd_m`` (N, 3), starting at rest at ``q_cmd_m[0]``.

    ``frozen_xyz_m`` evaluates an LTI model at that one pose instead of along ``xyz_path_m``.
    """
    q_cmd_m = np.asarray(q_cmd_m, float)
    N = len(q_cmd_m)
    q0 = q_cmd_m[0]
    w = q_cmd_m - q0
    out = np.empty((N, 3))
    x = None
    for a in range(0, N, chunk):
        b = min(N, a + chunk)
        poses = np.repeat(frozen_xyz_m[None], 1, 0) if frozen_xyz_m is not None else xyz_path_m[a:b]
        A, B, C, _ = state_space_arrays(model.matrices(poses, check=False))
        Phi, G1, G2 = modal_foh(A, B, dt_s).dense()
        if x is None:
            x = np.zeros(A.shape[1])
        Cq = C[0]
        for k in range(a, b):
            kk = 0 if frozen_xyz_m is not None else k - a
            out[k] = Cq @ x
            wn = w[k + 1] if k + 1 < N else w[k]
            x = Phi[kk] @ x + G1[kk] @ w[k] + G2[kk] @ (wn - w[k])
    return out + q0
