"""Running LPV prediction of the residual vibration of a compensated run, for its summary."""

from __future__ import annotations

import math
import time

import numpy as np

from ..compensate.kernels import DriveFilter
from ..compensate.ltv import simulate_piecewise
from ..kinematics import jacobian
from ..linalg3 import matvec3, sq_norm3
from ..model.lpv import LpvModel, mech_arrays

__all__ = ["Predictor"]


class Predictor:
    """Running LPV prediction of the nozzle error of the reference and of the command, together.

    The drive filters (LTI, per tower) run as recursive filters; the coupled mechanics run
    piecewise frozen (pose updated every ``seg`` samples) with the drive position and velocity as
    inputs, both streams through the same diagonalised matrices.  Same model as
    :func:`ffcomp.compensate.predict.predict_lpv`, split where it is exact.
    """

    def __init__(self, model: LpvModel, dt_s: float, seg: int = 100, batch: int = 16000):
        self.model, self.dt, self.seg, self.batch = model, dt_s, seg, batch
        self._buf: list = []
        self._nbuf = 0
        mats = model.matrices(np.zeros((1, 3)) + [0, 0, model.geometry.z_min_m], check=False)
        d = [(mats.d0[i], mats.d1[i], mats.d2[i], mats.lag_s[i], mats.delay_s[i]) for i in range(3)]
        self._mk = lambda: [[(DriveFilter(*d[i], dt_s), DriveFilter(*d[i], dt_s, derivative=True))
                             for i in range(3)] for _ in range(2)]
        self.sq = np.zeros(2)
        self.n = 0
        self.elapsed_s = 0.0  # time spent predicting, s
        self.mx = np.zeros(2)
        self.reset()

    def reset(self):
        self.flush()
        self.x = None
        self.w_last = None
        self.filters = self._mk()

    def push(self, q_cmd, q_ref, xyz_ref):
        """Predict both the command (run 0) and the uncompensated reference (run 1); samples are
        gathered into batches of ``batch`` (fewer, larger array operations)."""
        if len(q_cmd) == 0:
            return
        self._buf.append((q_cmd, q_ref, xyz_ref))
        self._nbuf += len(q_cmd)
        if self._nbuf >= self.batch:
            self.flush()

    def flush(self):
        """Predict the gathered samples."""
        if not self._buf:
            return
        q_cmd, q_ref, xyz_ref = (np.concatenate(a) for a in zip(*self._buf))
        self._buf.clear()
        self._nbuf = 0
        self._predict(q_cmd, q_ref, xyz_ref)

    def _predict(self, q_cmd, q_ref, xyz_ref):
        t0 = time.perf_counter()
        if self.x is None:
            self.q0 = q_ref[0].copy()
        ws = []
        for r, q in enumerate((q_cmd, q_ref)):
            rel = q - self.q0
            f = self.filters[r]
            ws.append(np.hstack([np.stack([f[i][0](rel[:, i]) for i in range(3)], 1),
                                 np.stack([f[i][1](rel[:, i]) for i in range(3)], 1)]))
        w = np.stack(ws, axis=2)  # (N, 6, 2)
        prefix = 0
        if self.x is not None:
            w = np.concatenate([self.w_last, w])
            prefix = 1
        X = np.concatenate([xyz_ref[:1], xyz_ref]) if prefix else xyz_ref
        S = -(-len(w) // self.seg)
        idx = np.minimum(np.arange(S) * self.seg + self.seg // 2, len(X) - 1)
        A, B = mech_arrays(self.model.matrices(X[idx], check=False))
        xs, _ = simulate_piecewise(A, B, w, self.dt, self.seg, x0=self.x)
        self.x = xs[-1]
        self.w_last = w[-1:]
        J = jacobian(self.model.geometry, xyz_ref, q=q_ref)
        for r in range(2):
            e = matvec3(J, xs[prefix:, :3, r] + self.q0 - q_ref)
            en = np.sqrt(sq_norm3(e))
            self.sq[r] += float(np.sum(en * en))
            self.mx[r] = max(self.mx[r], float(en.max()))
        self.n += len(q_cmd)
        self.elapsed_s += time.perf_counter() - t0

    def rms_um(self, r: int) -> float:
        return math.sqrt(self.sq[r] / max(self.n, 1)) * 1e6
