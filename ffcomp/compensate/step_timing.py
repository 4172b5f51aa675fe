"""Quantisation-aware G-code points: time the firmware's steps by where the points put the crossings.

A stepper stands on whole (micro)steps.  Klipper steps where the commanded carriage position, linear
between two G-code points, crosses a half-step boundary of the lattice that homing fixed (step 0 at
the homed carriage height).  The carriage command the drive sees is then a staircase, and where a
carriage moves slowly (corners, reversals, the compensation's small settling motions) the steps are
sparse: the staircase's error has low-frequency content that rings the lightly damped 60 Hz drive
pair.  A G-code file cannot dither (one point per 1 kHz sample), but it decides *when* each
boundary is crossed: a point moved by a fraction of a step moves the crossings of the segments on
either side.

:class:`StepTimer` chooses, sample by sample, the point of every slowly moving carriage within
``span_steps`` of its command, among ``candidates`` values, that leaves the least vibration: the
staircase error of each candidate (evaluated on ``ticks`` sub-ticks per sample, so the crossing
times count to a fiftieth of a sample) is fed through the model linearised at the stream's pose,
and the candidate is scored by the energy of the nozzle's response that it leaves (the state's
quadratic form with the observability Gramian, ``P = A^T P A + C^T C``).  The three carriages are
chosen in turn, twice per sample.  A model-predictive error feedback, greedy (no look-ahead).

Status: measured on the commands (``benchmarks/bench_step_timing.py``: the firmware's exact
staircase, step times to 20 us, on the simulator), not yet in the G-code output.  The timed points
reverse a slowly moving or standing carriage by a step from one sample to the next (a 1 kHz
dither), and the firmware runs those reversals late: wired into the writer with every timed sample a
point, a zig-zag ran 117 ms late (a scratch run; the wiring was removed).  Forbidding reversals
(each point moves with its command or stays) lost the whole gain (1.2-2.6x the firmware's own
staircase error, scratch runs of the benchmark's cases).

Pure numerics: no files, no G-code; SI units (m, s).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_discrete_lyapunov

from ..kinematics import jacobian, reachable
from ..model.lpv import LpvModel, state_space

__all__ = ["StepTimer"]


class _PoseModel:
    """The discretised model at one pose, in the form the timer needs."""

    __slots__ = ("A_up", "M", "P")

    def __init__(self, model: LpvModel, pose_m: np.ndarray, dt_s: float, ticks: int):
        sys_ = state_space(model, pose_m, frame="joint", dt_s=dt_s / ticks, method="zoh")
        A, B, C = (np.asarray(x) for x in (sys_.A, sys_.B, sys_.C))
        Cn = jacobian(model.geometry, np.asarray(pose_m, float)[None])[0] @ C  # nozzle response
        self.P = solve_discrete_lyapunov(A.T, Cn.T @ Cn)
        pw = [np.eye(A.shape[0])]
        for _ in range(ticks):
            pw.append(A @ pw[-1])
        self.A_up = pw[ticks]
        # the state at the end of a sample from the input held on its ticks 1..ticks
        self.M = np.stack([pw[ticks - m] @ B for m in range(1, ticks + 1)])  # (ticks, n, 3)


class StepTimer:
    """Streamed step-timing of carriage commands (state carried across calls).

    Parameters
    ----------
    model : LpvModel
        The printer's model (its drive pair and mechanics weigh the staircase's error).
    dt_s : float
        Sample time of the commands, s.
    steps_per_mm : float
        Microsteps per mm of carriage travel.
    origin_m : array_like, shape (3,)
        Carriage heights of step 0 (the homed carriage heights: homing fixes the lattice), m.
    ticks : int
        Sub-ticks per sample on which the staircase is evaluated.
    span_steps : float
        Largest move of a point from its command, steps.
    candidates : int
        Candidate values per carriage and sample, evenly spread over ``+-span_steps``.
    slow_m_s : float
        Only a carriage moving slower than this, m/s (over the sample), is timed; faster carriages
        step at more than ``1000 * slow_m_s * steps_per_mm`` Hz (1.6 kHz by default at 80 steps/mm),
        where the drive hardly responds.
    cell_m : float
        Pose grid of the cached linearisations, m.
    """

    def __init__(self, model: LpvModel, dt_s: float, steps_per_mm: float, origin_m, *, ticks: int = 50,
                 span_steps: float = 1.0, candidates: int = 13, slow_m_s: float = 0.02, cell_m: float = 0.02):
        if ticks < 1 or candidates < 1:
            raise ValueError(f"ticks and candidates must be >= 1, got {ticks} and {candidates}")
        self.model, self.dt, self.ticks = model, float(dt_s), int(ticks)
        self.step = 1e-3 / float(steps_per_mm)
        self.origin = np.broadcast_to(np.asarray(origin_m, float), (3,)).copy()
        self.offs = np.linspace(-span_steps, span_steps, int(candidates)) * self.step
        self.slow = float(slow_m_s) * self.dt
        self.cell = float(cell_m)
        self.fr = np.arange(1, self.ticks + 1) / self.ticks
        self._cache: dict[tuple, _PoseModel] = {}
        self.x = None  # the response state to the staircase's error so far
        self.q_last = self.c_last = None  # the last written point and its command

    def reset(self) -> None:
        """Forget the past: the next call starts a new stream at rest (after a homing, a stop)."""
        self.x = self.q_last = self.c_last = None

    def _pose_model(self, pose_m: np.ndarray) -> _PoseModel:
        key = tuple(np.floor(np.asarray(pose_m) / self.cell + 0.5).astype(int).tolist())
        pm = self._cache.get(key)
        if pm is None:
            if len(self._cache) > 256:
                self._cache.clear()
            centre = np.asarray(key, float) * self.cell
            if not bool(reachable(self.model.geometry, centre)):  # (a cell across the rim)
                centre = np.asarray(pose_m, float)
            pm = self._cache[key] = _PoseModel(self.model, centre, self.dt, self.ticks)
        return pm

    def _stair_err(self, q0, q1, c0, c1, origin):
        """Staircase error on the ticks of one sample (first axis) for point values ``q0 -> q1``
        against the command ``c0 -> c1`` on a lattice through ``origin`` (broadcast)."""
        fr = self.fr.reshape((-1,) + (1,) * np.ndim(q1))
        lq = q0 + fr * (q1 - q0)
        lc = c0 + fr * (c1 - c0)
        return origin + self.step * np.round((lq - origin) / self.step) - lc

    def __call__(self, c_m: np.ndarray, pose_m: np.ndarray, free: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Timed points for the commands of consecutive samples.

        Parameters
        ----------
        c_m : (n, 3) carriage commands, m
        pose_m : (n, 3) nozzle positions (the linearisation's pose: the chunk's middle one), m
        free : (n,) bool, optional
            Samples whose points may move (False: pinned to the command, e.g. where the G-code
            cannot move or the plan is followed on purpose).

        Returns
        -------
        q : (n, 3) the points' carriage heights, m
        moved : (n,) bool, samples with a point moved off its command
        """
        c = np.asarray(c_m, float)
        n = len(c)
        q = c.copy()
        moved = np.zeros(n, bool)
        if n == 0:
            return q, moved
        pm = self._pose_model(np.asarray(pose_m, float)[n // 2])
        A_up, M, P = pm.A_up, pm.M, pm.P
        free = np.ones(n, bool) if free is None else np.asarray(free, bool).copy()
        if self.x is None:
            free[0] = False  # a stream starts on its command (the machine stands there)
            self.x = np.zeros(A_up.shape[0])
            self.q_last = self.c_last = c[0].copy()
        x, q_prev, c_prev = self.x, self.q_last, self.c_last
        offs = self.offs
        for k in range(n):
            ck = c[k]
            slow = np.nonzero(free[k] & (np.abs(ck - c_prev) <= self.slow))[0]
            nxt = ck.copy()
            if slow.size:
                for _ in range(2):
                    for i in slow.tolist():
                        E = self._stair_err(q_prev, nxt, c_prev, ck, self.origin)  # (ticks, 3)
                        E[:, i] = 0.0
                        base = A_up @ x + np.einsum("mnc,mc->n", M, E)
                        Ei = self._stair_err(q_prev[i], ck[i] + offs, c_prev[i], ck[i], self.origin[i])  # (ticks, nc)
                        xT = base[None, :] + Ei.T @ M[:, :, i]
                        cost = np.einsum("cn,nm,cm->c", xT, P, xT)
                        nxt[i] = ck[i] + offs[int(np.argmin(cost))]
            E = self._stair_err(q_prev, nxt, c_prev, ck, self.origin)
            x = A_up @ x + np.einsum("mnc,mc->n", M, E)
            q[k] = nxt
            if np.any(nxt != ck):
                moved[k] = True
            q_prev, c_prev = nxt, ck
        self.x, self.q_last, self.c_last = x, q_prev.copy(), c_prev.copy()
        return q, moved
