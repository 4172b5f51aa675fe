"""Model predictions for measurements: the same coordinates, pose and frequencies as the file.

A measurement's frame follows from its input and output (``x, y, z`` task, ``qA..qC`` joint):
the prediction is :func:`~ffcomp.model.lpv.frequency_response` at ``position_mm`` with that frame.
``kind = carriage`` means the effector and forearms detached: the carriage sub-model ``G_qd`` of
that tower alone at the carriage heights ``position_mm`` maps to, i.e. the joint response of the
model with ``m_nt = b_nt = m_f = 0`` (effects still apply: belt span, tower scale, coupling to the
other carriages through the frame, drive delay).

:class:`BatchPredictor` evaluates a whole data set for many parameter values (the fits of
:mod:`ffcomp.loop.fit`): one set of pose matrices per call, one joint response per frequency
grid, measurements picked out by row/column of ``J G J^-1``; :func:`predict` is the reference.
"""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np

from ..errors import MeasurementError
from ..kinematics import reachable
from ..model.lpv import AXES, PoseMatrices, frequency_response, joint_response
from .frf_file import FrfMeasurement

__all__ = ["frame_for", "detached", "predict", "BatchPredictor", "check_measurements"]

_TASK = ("x", "y", "z")


def frame_for(input_: str, output: str) -> str:
    """Response frame of an input/output pair (see :data:`ffcomp.model.lpv.FRAMES`)."""
    tin, tout = input_ in _TASK, output in _TASK
    return {(True, True): "task", (False, False): "joint", (True, False): "task_to_joint",
            (False, True): "joint_to_task"}[(tin, tout)]


def detached(model):
    """The model with effector and forearms detached (the paper's carriage sweep, Fig. 5)."""
    return replace(model, m_nt=0.0, b_nt=0.0, m_f=0.0)


def check_measurements(model, measurements) -> None:
    """Raise :class:`MeasurementError` naming the file if a measurement cannot be predicted."""
    for m in measurements:
        where = m.path or m.label
        if m.input not in AXES or m.output not in AXES:
            raise MeasurementError(where, None, f"unknown input/output {m.input!r}->{m.output!r}")
        if m.kind == "carriage" and (m.input in _TASK or m.output in _TASK):
            raise MeasurementError(where, None, "kind: carriage (effector detached) needs a carriage input and "
                                   f"output (qA, qB, qC), got {m.input}->{m.output}")
        if not reachable(model.geometry, np.asarray(m.position_mm, float)[None] * 1e-3)[0]:
            p = ", ".join(f"{v:g}" for v in m.position_mm)
            raise MeasurementError(where, None, f"position_mm ({p}) is outside the profile's workspace "
                                   "(print radius, z range, arm angle): wrong profile?")


def predict(model, meas: FrfMeasurement, freq_hz=None) -> np.ndarray:
    """Predicted FRF for one measurement, shape (F,), complex (at ``meas.freq_hz`` by default)."""
    f = meas.freq_hz if freq_hz is None else np.asarray(freq_hz, float)
    pos = np.asarray(meas.position_mm, float)[None] * 1e-3
    if meas.kind == "carriage":
        check_measurements(model, [meas])
        H = frequency_response(detached(model), pos, f, frame="joint")
    else:
        H = frequency_response(model, pos, f, frame=frame_for(meas.input, meas.output))
    return H[0, AXES[meas.output], AXES[meas.input]]


def _base_key(model):
    g, c = model.geometry, model.carriage
    arrays = (g.arm_length_m, g.tower_xy_m, c.m, c.c, c.b, c.k, c.d0, c.d1, c.d2)
    return (tuple(np.concatenate([np.ravel(a) for a in arrays])), g.effector_offset_z_m, model.m_nt, model.b_nt,
            model.m_f)


def _take(mats: PoseMatrices, idx) -> PoseMatrices:
    per_pose = {"xyz_m", "q_m", "J", "M", "C", "K", "B_c", "B_k"}
    return PoseMatrices(**{f.name: (getattr(mats, f.name)[idx] if f.name in per_pose else getattr(mats, f.name))
                           for f in fields(PoseMatrices)})


class BatchPredictor:
    """Fast repeated prediction of a fixed list of measurements.

    Parameters
    ----------
    measurements : sequence of FrfMeasurement

    Calling ``predictor(model)`` returns a list of complex arrays, one per measurement, equal to
    :func:`predict` for each (tested).  The pose matrices without effects (kinematics, Jacobians,
    the paper's M, C, K) are cached per model and the effects applied on top, as
    :meth:`LpvModel.matrices` does: a fit that only changes effect parameters re-evaluates only
    the effects and the responses.
    """

    def __init__(self, measurements):
        self.measurements = list(measurements)
        self._cache: dict = {}
        self._groups = []  # (kind, pose keys array (P,3) mm, [(grid, pose index per meas, [meas idx])])
        for kind in ("assembled", "carriage"):
            idx = [i for i, m in enumerate(self.measurements) if m.kind == kind]
            if not idx:
                continue
            keys = np.array([np.round(np.asarray(self.measurements[i].position_mm, float), 6) for i in idx])
            poses, inv = np.unique(keys, axis=0, return_inverse=True)
            inv = np.asarray(inv).reshape(-1)
            grids: dict[bytes, list] = {}
            for j, i in enumerate(idx):
                f = np.asarray(self.measurements[i].freq_hz, float)
                grids.setdefault(f.tobytes(), [f, []])[1].append((i, int(inv[j])))
            plan = []
            for f, items in grids.values():
                pidx = np.unique([p for _, p in items])
                where = {p: k for k, p in enumerate(pidx)}
                plan.append((f, pidx, [(i, where[p]) for i, p in items]))
            self._groups.append((kind, poses * 1e-3, plan))

    def __call__(self, model) -> list[np.ndarray]:
        out: list = [None] * len(self.measurements)
        for kind, poses_m, plan in self._groups:
            mdl = detached(model) if kind == "carriage" else model
            mats = self._matrices(mdl, kind, poses_m)
            Jinv = np.linalg.inv(mats.J)
            for f, pidx, items in plan:
                sub = _take(mats, pidx)
                G = joint_response(sub, f)  # (P, 3, 3, F)
                for i, p in items:
                    m = self.measurements[i]
                    o, n = AXES[m.output], AXES[m.input]
                    row = mats.J[pidx[p], o] if m.output in _TASK else np.eye(3)[o]
                    col = Jinv[pidx[p], :, n] if m.input in _TASK else np.eye(3)[:, n]
                    out[i] = np.einsum("i,ijf,j->f", row, G[p], col)
        return out

    def _matrices(self, model, kind, poses_m) -> PoseMatrices:
        key = (kind, _base_key(model))
        base = self._cache.get(key)
        if base is None:
            base = self._cache[key] = replace(model, effects=()).matrices(poses_m)
            if len(self._cache) > 8:
                self._cache.pop(next(iter(self._cache)))
        mats = base
        for eff in model.effects:
            mats = eff.apply(mats, model)
        return mats
