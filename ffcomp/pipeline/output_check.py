"""The compensated G-code judged on the simulator against the exact commands it stands for.

Plans and samples a source file, inverts it in memory (the exact commands), compensates it to
G-code, re-plans and samples that output as the firmware would, and simulates all three command
sets (none, exact, G-code) on the nonlinear plant against the source's planned path.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..compensate.inverse import InverseConfig, invert
from ..gcode.sampler import concat_blocks, sample_gcode
from ..model.lpv import LpvModel
from ..sim.metrics import ErrorReport, evaluate
from ..sim.plant import DeltaPlant
from .compensate_flow import CompensationSummary, compensate_file, inv_pre_samples

__all__ = ["OutputCheck", "check_gcode_output"]


@dataclass(frozen=True)
class OutputCheck:
    """Reports for the planned path run with no compensation, the exact commands and the G-code.

    ``drift_s`` is how much longer the re-planned output runs than the commands it stands for
    (the rest added before and after included in both).
    """

    none: ErrorReport
    exact: ErrorReport
    gcode: ErrorReport
    summary: CompensationSummary
    drift_s: float

    def kept(self, metric: str = "lag") -> float:
        """Share of the exact commands' RMS reduction the G-code output keeps."""
        n, e, g = (getattr(r, metric).rms_norm_um for r in (self.none, self.exact, self.gcode))
        return (n - g) / (n - e)


def check_gcode_output(profile, src: str | Path, out: str | Path, plant_profile=None, opts=None) -> OutputCheck:
    """Compensate ``src`` into ``out`` and judge the output on the simulator (single stream files).

    ``plant_profile``: the printer simulated (default ``profile``; e.g. the "true" dynamics of an
    identified profile); ``opts``: :class:`CompensateOptions` of the run.  The summary carries the
    self-check's drift on the absolute clock (``self_check_drift_ms``).
    """
    from ..gcode.start import resolve_start

    start = resolve_start(str(src), profile).position_mm  # where the compensation's plan starts
    ref = concat_blocks(sample_gcode(str(src), profile, overlap=0, start_position_mm=start))
    dt = ref.t_s[1] - ref.t_s[0]
    # the printer stands still before the file starts: the G-code output uses that time (pre_s) to
    # pre-actuate the first move, so the comparison starts at rest too
    cfg = InverseConfig()
    n_pre = inv_pre_samples(cfg, dt)
    X = np.vstack([np.repeat(ref.xyz_m[:1], n_pre, 0), ref.xyz_m])
    q = np.vstack([np.repeat(ref.q_m[:1], n_pre, 0), ref.q_m])
    t = np.arange(len(q)) * dt
    ideal = invert(LpvModel.from_profile(profile), q, X, dt).q_cmd
    summ = compensate_file(str(src), str(out), profile, *([opts] if opts is not None else []))
    got = concat_blocks(sample_gcode(str(out), profile, overlap=0, lenient=True,
                                     start_position_mm=start)).q_m[:len(q)]
    got = np.vstack([got, np.repeat(got[-1:], len(q) - len(got), 0)])
    sim = DeltaPlant.from_profile(plant_profile or profile).simulate(t, np.stack([q, ideal, got]), hold="linear")
    none, exact, gcode = (evaluate(t, X, sim.xyz_m[r]) for r in range(3))
    intended = (n_pre + round(cfg.post_s / dt)) * dt + summ.print_time_s
    return OutputCheck(none, exact, gcode, summ, summ.output_print_time_s - intended)
