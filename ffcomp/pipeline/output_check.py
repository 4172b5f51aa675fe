"""The compensated G-code judged on the simulator against the exact commands it stands for.

Plans and samples a source file, inverts it in memory (the exact commands), compensates it to
G-code, re-plans and samples that output as the firmware would, and simulates all three command
sets (none, exact, G-code) on the nonlinear plant against the source's planned path; optionally
also the physical limit's commands for the same path (:func:`ffcomp.compensate.limit.limit_commands`),
so that every row can say how far it sits from what the model allows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..compensate.inverse import InverseConfig, invert
from ..gcode.margins import with_margins
from ..gcode.sampler import concat_blocks, sample_gcode
from ..model.lpv import LpvModel
from ..sim.metrics import ErrorReport, evaluate_masked, extruding_mask
from ..sim.plant import DeltaPlant
from .compensate_flow import CompensateOptions, CompensationSummary, compensate_file, inv_pre_samples
from .header import quiet_z_period_s

__all__ = ["OutputCheck", "check_gcode_output"]


@dataclass(frozen=True)
class OutputCheck:
    """Reports for the planned path run with no compensation, the exact commands and the G-code.

    ``drift_s`` is how much longer the re-planned output runs than the commands it stands for
    (the rest added before and after included in both).  ``extruding`` holds the same three runs'
    lag-aligned and contour RMS (um) over the samples where the plan extrudes while it moves (what
    marks the part), as ``{"none": (lag, contour), "exact": ..., "gcode": ...}``; empty when the
    file does not extrude.  ``limit``: the physical limit's report (the same path, the finest
    command the firmware executes, iterated on the model's own plant), or None when not asked for;
    ``extruding`` then holds its ``"limit"`` entry too.  ``shaped``: for each Klipper input shaper
    asked for, ``{"none": ..., "gcode": ...}``: the uncompensated file and the compensated output
    run with that shaper on (what the printer does if its ``[input_shaper]`` stays on under the
    output; the output's header switches it off).  ``source_clock``: where the run's options change
    the intended timeline (quiet z moves, rest margins), ``{"none": ..., "gcode": ...}`` judged
    against the source's own plan instead, as an independent judge that plans the source file sees
    them (the added time then counts as error); None where the two timelines are the same.
    """

    none: ErrorReport
    exact: ErrorReport
    gcode: ErrorReport
    summary: CompensationSummary
    drift_s: float
    extruding: dict
    limit: ErrorReport | None = None
    shaped: dict = field(default_factory=dict)
    source_clock: dict | None = None

    def over_limit(self, run: str = "gcode", metric: str = "lag") -> float:
        """How many times the physical limit's RMS ``run`` (``"exact"`` or ``"gcode"``) leaves, for
        ``metric`` (``"lag"`` or ``"contour"``); NaN without the limit."""
        if self.limit is None:
            return float("nan")
        return getattr(getattr(self, run), metric).rms_norm_um / max(getattr(self.limit, metric).rms_norm_um, 1e-12)

    def kept(self, metric: str = "lag") -> float:
        """Share of the exact commands' RMS reduction the G-code output keeps."""
        n, e, g = (getattr(r, metric).rms_norm_um for r in (self.none, self.exact, self.gcode))
        return (n - g) / (n - e)

    def kept_extruding(self, metric: str = "lag") -> float:
        """:meth:`kept` over the extruding samples only (NaN when the file does not extrude)."""
        if not self.extruding:
            return float("nan")
        i = 0 if metric == "lag" else 1
        n, e, g = (self.extruding[k][i] for k in ("none", "exact", "gcode"))
        return (n - g) / (n - e)


def _at_rest_first(X: np.ndarray, q: np.ndarray, e: np.ndarray, n_pre: int) -> tuple:
    """The records ``X``, ``q`` (rows) and ``e`` with ``n_pre`` samples of rest at their first
    sample put before them."""
    return (np.vstack([np.repeat(X[:1], n_pre, 0), X]), np.vstack([np.repeat(q[:1], n_pre, 0), q]),
            np.concatenate([np.repeat(e[:1], n_pre), e]))


def _fit(a: np.ndarray, n: int) -> np.ndarray:
    """The record ``a`` cut to ``n`` samples, or held at its last sample up to ``n``."""
    return a[:n] if len(a) >= n else np.vstack([a, np.repeat(a[-1:], n - len(a), 0)])


def check_gcode_output(profile, src: str | Path, out: str | Path, plant_profile=None, opts=None,
                       limit: bool = False, shapers: tuple = ()) -> OutputCheck:
    """Compensate ``src`` into ``out`` and judge the output on the simulator (single stream files).

    ``plant_profile``: the printer simulated (default ``profile``; e.g. the "true" dynamics of an
    identified profile); ``opts``: :class:`CompensateOptions` of the run; ``limit``: also run the
    physical limit's commands for the same path (computed for ``profile``'s model, as the exact
    commands are; about 1.5 s of CPU per second of motion); ``shapers``: ``(name, freq_hz)`` pairs of
    Klipper input shapers to run the uncompensated file and the output with as well (X and Y shaped
    before the kinematics, as Klipper does; :attr:`OutputCheck.shaped`, keyed ``"name@freq"``).  The
    summary carries the self-check's drift on the absolute clock (``self_check_drift_ms``).
    """
    from ..gcode.start import resolve_start

    start = resolve_start(str(src), profile).position_mm  # where the compensation's plan starts
    qp = quiet_z_period_s(profile, opts if opts is not None else CompensateOptions())
    qkw = {} if qp is None else {"quiet_z_period_s": qp}  # (the quiet z moves are part of the intended motion)
    ref = concat_blocks(sample_gcode(str(src), profile, overlap=0, start_position_mm=start, **qkw))
    dt = ref.t_s[1] - ref.t_s[0]
    # the printer stands still before the file starts: the G-code output uses that time (pre_s) to
    # pre-actuate the first move, so the comparison starts at rest too
    cfg = InverseConfig()
    n_pre = inv_pre_samples(cfg, dt)
    Xs, qs, es = ref.xyz_m, ref.q_m, ref.e_mm
    margin_s = 0.0 if opts is None else opts.hold_margin_s
    if margin_s > 0:  # the rest the output adds around retractions is part of the intended motion
        from ..gcode.planner import GcodePlan

        moves = {mv.index: mv for mv in GcodePlan(str(src), profile, start_position_mm=start, **qkw)}
        Xs, qs, es = with_margins((Xs, qs, es), ref.move_index, moves, int(round(margin_s / dt)))
    X, q, e = _at_rest_first(Xs, qs, es, n_pre)
    t = np.arange(len(q)) * dt
    ideal = invert(LpvModel.from_profile(profile), q, X, dt).q_cmd
    summ = compensate_file(str(src), str(out), profile, *([opts] if opts is not None else []))
    out_s = concat_blocks(sample_gcode(str(out), profile, overlap=0, lenient=True, start_position_mm=start))
    got, got_x = _fit(out_s.q_m, len(q)), _fit(out_s.xyz_m, len(q))
    runs = [q, ideal, got]
    if limit:
        from ..compensate.limit import limit_commands

        runs.append(limit_commands(LpvModel.from_profile(profile), q, X, dt).q_cmd)
    n_fixed = len(runs)
    if shapers:
        from ..kinematics import inverse
        from ..sim.shapers import shape_cartesian, shaper_impulses

        geom = profile.geometry_si()
        for name, freq in shapers:
            imp = shaper_impulses(name, freq)
            runs += [inverse(geom, shape_cartesian(t, x, imp, imp)) for x in (X, got_x)]
    sim = DeltaPlant.from_profile(plant_profile or profile).simulate(t, np.stack(runs), hold="linear")
    # extruding while moving: E rises over the sample and the nozzle moves faster than 1 mm/s
    ext = extruding_mask(X, e, dt)
    reps = [evaluate_masked(t, X, sim.xyz_m[r], ext) for r in range(len(runs))]
    (none, n_ex), (exact, e_ex), (gcode, g_ex) = reps[:3]
    extruding = {"none": n_ex, "exact": e_ex, "gcode": g_ex} if ext.any() else {}
    if limit and ext.any():
        extruding["limit"] = reps[3][1]
    shaped = {f"{name}@{freq:g}": {"none": reps[n_fixed + 2 * i][0], "gcode": reps[n_fixed + 2 * i + 1][0]}
              for i, (name, freq) in enumerate(shapers)}
    intended = (n_pre + round(cfg.post_s / dt)) * dt + summ.print_time_s + summ.hold_margin_time_s
    source_clock = None
    if qkw or margin_s > 0:  # the output judged against the source's own plan as well
        # (without quiet moves the plan sampled above is the source's own: only the margins differ)
        src_ref = ref if not qkw else concat_blocks(sample_gcode(str(src), profile, overlap=0,
                                                                 start_position_mm=start))
        Xo, qo, eo = _at_rest_first(src_ref.xyz_m, src_ref.q_m, src_ref.e_mm, n_pre)
        to = np.arange(len(qo)) * dt
        so = DeltaPlant.from_profile(plant_profile or profile).simulate(
            to, np.stack([qo, _fit(out_s.q_m, len(qo))]), hold="linear")
        ext_o = extruding_mask(Xo, eo, dt)
        source_clock = {k: evaluate_masked(to, Xo, so.xyz_m[r], ext_o)[0] for r, k in enumerate(("none", "gcode"))}
    return OutputCheck(none, exact, gcode, summ, summ.output_print_time_s - intended, extruding,
                       reps[3][0] if limit else None, shaped, source_clock)
