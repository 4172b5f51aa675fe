"""Step-stream flow: G-code -> compensated carriage commands -> per-carriage step times.

The step stream carries the compensated carriage commands exactly (to half a step): no firmware
re-planning, no z throttling, no G-code segment tolerance.  The file is written atomically.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import asdict, dataclass

import numpy as np

from ..gcode.planner import GcodePlan
from ..model.lpv import LpvModel
from ..steps import STEPPERS, positions_from_steps, read_ffsteps, read_plain, step_events, write_ffsteps, write_plain
from .compensate_flow import CompensateOptions, CompensationSummary, compensated_stream, inverse_config

__all__ = ["StepsSummary", "steps_file"]


@dataclass
class StepsSummary:
    source: str
    output: str
    method: str
    print_time_s: float = 0.0
    steps: int = 0
    queue_lines: int = 0
    max_step_error_steps: float = 0.0
    wall_time_s: float = 0.0
    speed_ratio: float = 0.0
    restarts: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def steps_file(src: str, out_path: str, profile, *, method: str = "lpv", lenient: bool = False,
               csv: bool = False) -> StepsSummary:
    """Compensate ``src`` and write its step stream to ``out_path`` (``.ffsteps`` compact; with
    ``csv`` the plain CSV, or NPZ if the name ends in ``.npz``).  Checks the reconstruction."""
    t0 = time.perf_counter()
    model = LpvModel.from_profile(profile)
    dt = 1.0 / profile.limits.sample_rate_hz
    spm = profile.limits.steps_per_mm
    opts = CompensateOptions(method=method, lenient=lenient, predict=False, self_check=False)
    icfg = inverse_config(profile, opts)
    summ_c = CompensationSummary(source=src, output=out_path, method=method)
    plan = GcodePlan(src, profile, lenient=lenient)
    per = {n: ([], []) for n in STEPPERS}
    n0 = None
    k = 0
    qs = []
    last = None
    for qc, _meta in compensated_stream(plan, {}, profile, model, icfg, opts, summ_c, src):
        # keep one sample of overlap so crossings between chunks are found
        block = qc if last is None else np.vstack([last, qc])
        t_start = (k - (0 if k == 0 else 1)) * dt
        starts = []
        for i, name in enumerate(STEPPERS):
            t, d, s0 = step_events(block[:, i], t_start, dt, spm,
                                   None if n0 is None else int(np.rint(block[0, i] * 1e3 * spm)))
            per[name][0].append(t)
            per[name][1].append(d)
            starts.append(s0)
        if n0 is None:
            n0 = tuple(starts)
        last = qc[-1:]
        qs.append(qc[::10].copy())
        k += len(qc)
    tt = {n: (np.concatenate(per[n][0]) if per[n][0] else np.zeros(0),
              np.concatenate(per[n][1]) if per[n][1] else np.zeros(0, np.int8)) for n in STEPPERS}
    out_dir = os.path.dirname(os.path.abspath(out_path))
    fd, tmp = tempfile.mkstemp(prefix=".ffcomp-steps-", suffix=os.path.splitext(out_path)[1], dir=out_dir)
    summ = StepsSummary(src, out_path, method, print_time_s=k * dt, restarts=summ_c.restarts)
    try:
        if csv or out_path.endswith(".npz"):
            os.close(fd)
            write_plain(tmp, tt, spm, n0 or (0, 0, 0))
            stream = read_plain(tmp)
        else:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                summ.queue_lines = write_ffsteps(f, tt, spm, n0 or (0, 0, 0))
            stream = read_ffsteps(tmp)
        # reconstruction check on every 10th sample
        q = np.concatenate(qs) if qs else np.zeros((0, 3))
        ts = np.arange(len(q)) * 10 * dt
        if len(q):
            rec = positions_from_steps(stream, ts)
            summ.max_step_error_steps = float(np.max(np.abs(rec - q)) * 1e3 * spm)
        summ.steps = stream.n_steps()
        os.chmod(tmp, 0o644)
        os.replace(tmp, out_path)
        tmp = None
    finally:
        if tmp and os.path.exists(tmp):
            os.unlink(tmp)
    summ.wall_time_s = time.perf_counter() - t0
    summ.speed_ratio = summ.print_time_s / max(summ.wall_time_s, 1e-9)
    return summ
