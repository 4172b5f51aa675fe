"""The physical limit of compensation for a model: the commands that make the model's own nonlinear
plant follow the reference as closely as 1 kHz commands can.

The benchmarks compare every row with it.  Two ingredients take away everything the default
inverse approximates:

* **the finest basis the firmware can execute**: a linear spline with a knot at every sample.  The
  firmware moves linearly between command samples (G-code points at the sample rate, or a step
  stream), so this basis holds *every* command the printer can be given at that rate, and the
  kernels (first-order hold) are exact for it.  The default quintic spline with 4 ms knots is far
  smoother (its bandwidth is about 125 Hz);
* **iteration on the nonlinear plant**: the inverse's two-stage split, its centre-model weighting and
  its forcing along the *reference* (not the actual) pose are approximations of the simulator's
  physics.  Each iteration simulates the command on :class:`~ffcomp.sim.plant.DeltaPlant` built
  from the *same* model (exact kinematics, ``J' q'`` term, every effect), and moves the inverse's
  reference by the tracking error (``r <- r - e``): a Newton step whose Jacobian is the inverse's
  own linearisation along the path.  One iteration reaches the fixed point (about 0.1 um on the
  model's plant for a square at 10,000 mm/s^2); later ones drift by a few hundredths of a um, so the
  best iterate is kept (default: one iteration).

No bounds: at the limit the commands jerk (hundreds of m/s^2 of carriage acceleration on a 250 Hz
polygon), far beyond what the profile's ``max_carriage_accel_mm_s2`` lets the default do.

The result is what the model allows, not what the real printer does: on another plant (a held-out
"truth" profile) model error adds to it, for every row alike.

:func:`limit_commands` is a plain function so that any benchmark can add the row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.lpv import LpvModel
from .inverse import InverseConfig, invert

__all__ = ["LIMIT_CONFIG", "LimitResult", "limit_commands", "limit_for_profile"]

#: the inverse of the limit row: linear spline, one knot per sample (the firmware's own interpolation)
LIMIT_CONFIG = InverseConfig(method="lpv", degree=1, knot_samples=1)


@dataclass(frozen=True)
class LimitResult:
    """Commands at the limit and how the iteration went.

    q_cmd : (N, 3) carriage commands, m (the best iterate);
    rms_um : tracking RMS (nozzle, time-aligned, um) on the model's plant, per iterate (0 = no iteration);
    best : index of the returned iterate.
    """

    q_cmd: np.ndarray
    rms_um: tuple
    best: int


def limit_commands(model: LpvModel, q_ref_m: np.ndarray, xyz_ref_m: np.ndarray, dt_s: float, *,
                   iterations: int = 1, hold: str = "linear", cfg: InverseConfig = LIMIT_CONFIG) -> LimitResult:
    """The physical-limit commands for one trajectory held in memory (see the module notes).

    Parameters
    ----------
    model : LpvModel
        The model the commands are computed for; the iteration runs on ``DeltaPlant(model)``.
    q_ref_m, xyz_ref_m : ndarray, shape (N, 3)
        Reference carriage heights and nozzle positions on a uniform grid of step ``dt_s`` (at rest
        at both ends), m.
    iterations : int
        Newton iterations on the nonlinear plant (0: the fine inverse alone).
    hold : {"linear", "zoh"}
        How the plant interpolates the commands (the firmware's: linear).
    cfg : InverseConfig
        Inverse settings (default :data:`LIMIT_CONFIG`).
    """
    from ..sim.plant import DeltaPlant

    q_ref = np.asarray(q_ref_m, float)
    x_ref = np.asarray(xyz_ref_m, float)
    plant = DeltaPlant(model)
    t = np.arange(len(q_ref)) * dt_s
    r_q, r_x = q_ref.copy(), x_ref.copy()
    cmds, rms = [], []
    for it in range(int(iterations) + 1):
        c = invert(model, r_q, r_x, dt_s, cfg).q_cmd
        cmds.append(c)
        res = plant.simulate(t, c, hold=hold, check=False)
        e_x = res.xyz_m[0] - x_ref
        rms.append(float(np.sqrt(np.mean(np.sum(e_x**2, axis=1)))) * 1e6)
        if it < iterations:
            r_q = r_q - (res.q_m[0] - q_ref)
            r_x = r_x - e_x
    best = int(np.argmin(rms))
    return LimitResult(cmds[best], tuple(rms), best)


def limit_for_profile(profile, t_s, xyz_ref_m, q_ref_m, *, iterations: int = 1) -> np.ndarray:
    """Bench-row form: ``fn(profile, t_s, xyz_ref_m, q_ref_m) -> q_cmd_m`` (see :mod:`ffcomp.sim.bench`)."""
    dt = float(np.median(np.diff(np.asarray(t_s, float))))
    model = LpvModel.from_profile(profile)
    return limit_commands(model, q_ref_m, xyz_ref_m, dt, iterations=iterations).q_cmd
