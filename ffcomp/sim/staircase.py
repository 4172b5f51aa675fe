"""The step staircase a stepper actually executes for a carriage command.

The firmware (Klipper) steps where the commanded position, linear between its points, crosses a
half-step boundary (:func:`ffcomp.steps.step_events`); the carriage command the drive sees is
then a staircase of whole steps, not the command.  :func:`staircase` samples that staircase on a
grid ``upsample`` times finer than the command's (each step lands within ``dt / upsample`` of its
exact time, held in between), so :meth:`~ffcomp.sim.plant.DeltaPlant.simulate` with
``hold="zoh"`` runs the steps themselves.  Units: SI (m, s).
"""

from __future__ import annotations

import numpy as np

from ..steps import step_events

__all__ = ["staircase", "shaped_staircase", "simulate_steps"]


def staircase(q_cmd_m: np.ndarray, dt_s: float, steps_per_mm: float, upsample: int = 10,
              origin_m=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Step positions (N_f, 3) on the fine grid ``t_f`` (N_f,) for commands ``q_cmd_m`` (N, 3).

    Step 0 sits at ``origin_m`` (m, one value or one per carriage: the lattice is fixed by homing);
    the run starts on the step nearest to the first command.  ``N_f = (N - 1) * upsample + 1``.
    """
    q = np.asarray(q_cmd_m, float)
    step = 1e-3 / float(steps_per_mm)
    n_f = (len(q) - 1) * upsample + 1
    t_f = np.arange(n_f) * (dt_s / upsample)
    out = np.empty((n_f, q.shape[1]))
    org = np.broadcast_to(np.asarray(origin_m, float), (q.shape[1],))
    for i in range(q.shape[1]):
        t, d, n0 = step_events(q[:, i] - org[i], 0.0, dt_s, steps_per_mm)
        # the count after every event at or before each fine time (an event between grid points
        # acts from the next one: at most dt / upsample late)
        k = np.searchsorted(t, t_f, side="right")
        cum = np.concatenate([[0], np.cumsum(d.astype(np.int64))])
        out[:, i] = org[i] + (n0 + cum[k]) * step
    return t_f, out


def simulate_steps(plant, t_s: np.ndarray, q_cmd_m: np.ndarray, steps_per_mm: float, upsample: int = 10,
                   substeps: int = 2, shaped: bool = False, origin_m=0.0):
    """Nozzle path (N, 3) on ``t_s`` when the plant executes the steps of ``q_cmd_m`` (N, 3): the
    firmware's staircase (on the lattice through ``origin_m``), or with ``shaped`` the
    quantisation-aware stream's.  ``q_cmd_m`` (R, N, 3) runs R commands through the plant together
    (one pass of its integrator, about the cost of one) and returns (R, N, 3)."""
    dt = float(t_s[1] - t_s[0])
    q = np.asarray(q_cmd_m, float)
    runs = q[None] if q.ndim == 2 else q
    q_f = []
    for r in runs:
        if shaped:
            t_f, f = shaped_staircase(r, dt, steps_per_mm, upsample)
        else:
            t_f, f = staircase(r, dt, steps_per_mm, upsample, origin_m)
        q_f.append(f)
    res = plant.simulate(t_f, np.stack(q_f), hold="zoh", substeps=substeps, check=False)
    xyz = res.xyz_m[:, ::upsample]
    return xyz[0] if q.ndim == 2 else xyz


def shaped_staircase(q_cmd_m: np.ndarray, dt_s: float, steps_per_mm: float, upsample: int = 10,
                     order: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The staircase of the quantisation-aware step stream (:mod:`ffcomp.compensate.quantise`) of
    commands ``q_cmd_m`` (N, 3), on the fine grid of :func:`staircase`: the events the step writer
    would emit, each held from the tick it falls in."""
    from ..compensate.quantise import NoiseShaper, shaped_step_events

    q = np.asarray(q_cmd_m, float)
    step = 1e-3 / float(steps_per_mm)
    shaper = NoiseShaper(steps_per_mm, order, q.shape[1])
    events, _ = shaped_step_events(q, 0.0, dt_s, shaper, None, upsample)
    n_f = (len(q) - 1) * upsample + 1
    h = dt_s / upsample
    t_f = np.arange(n_f) * h
    out = np.empty((n_f, q.shape[1]))
    n0 = np.rint(q[0] / step)
    for i, (t, d) in enumerate(events):
        k = np.searchsorted(t, t_f, side="right")  # a tick's steps fall inside it, before its end
        cum = np.concatenate([[0], np.cumsum(d.astype(np.int64))])
        out[:, i] = (n0[i] + cum[k]) * step
    return t_f, out
