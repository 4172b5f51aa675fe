"""Benchmark: the least error any G-code can leave where it must stand still (a bound).

Run: ``python benchmarks/bench_hold_bound.py [--quick] [--only NAME] [--profiles default,other_delta]
[--accel 10]``.  On the fidelity bench's files (``bench_gcode_fidelity.py``, the same profiles and
plants), every layer change and z-hop has samples where a G-code file cannot move the command (the
extruder-only moves: retraction, unretraction) and a z move between them that the firmware ramps at
``max_z_accel`` at most.  Around each cluster of such samples (0.15 s either side, plus the ringing
tail) :func:`ffcomp.compensate.hold_bound.pinned_optimum` finds the command with the least tracking
error that equals the plan on the extruder-only moves, every other sample free (a knot per sample),
with only a light penalty on its acceleration (``--accel`` m/s^2 of command acceleration cost as much
as 1 um of error; the default 10 lets the command accelerate at hundreds of m/s^2, so the bound is
optimistic).  Outside those windows the command is the exact one.  The whole file is then simulated
on the profile's plant, as the fidelity bench does.

Three bounds, by what the z move (more z than XY, next to an extruder-only move) may do:

* ``limits``: the nozzle's acceleration stays, per axis, within the profile's ``max_z_accel`` in z
  (Klipper caps a segment's acceleration at ``max_z_accel * d/|dz|``: along a segment, a cap on its
  z acceleration) and the output header's ``ACCEL`` in x and y, on every sample of the window: the
  best a file at the profile's limits can do;
* ``planned``: as ``limits``, and the z move's z fixed to the plan: the pipeline's own choice;
* ``free``: the z move free and no bound on z: what a firmware whose ``max_z_accel`` let the z move
  carry its compensation could reach.

In all three the acceleration in x and y stays within the header's ``ACCEL``.

For each file it prints, as the fidelity bench does (lag-aligned and contour RMS as a fraction of the
uncompensated file's), the exact commands, the written G-code and the three bounds, then the share of
the exact commands' reduction each keeps, over the whole file and over the samples where the plan
extrudes while it moves (what marks the part).  A ``limits`` share below 0.90 says the fidelity bench's
target is out of reach for that file whatever the pipeline does, to this model's linearisation.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_gcode_fidelity as fid  # noqa: E402

from ffcomp.compensate.hold_bound import pinned_optimum  # noqa: E402
from ffcomp.compensate.inverse import InverseConfig, invert  # noqa: E402
from ffcomp.compensate.pin_repair import PulseResponses, RepairConfig, pinned_clusters  # noqa: E402
from ffcomp.gcode.planner import GcodePlan  # noqa: E402
from ffcomp.gcode.sampler import concat_blocks, sample_gcode  # noqa: E402
from ffcomp.gcode.start import resolve_start  # noqa: E402
from ffcomp.kinematics import forward, jacobian  # noqa: E402
from ffcomp.model.lpv import LpvModel  # noqa: E402
from ffcomp.pipeline.compensate_flow import CompensateOptions  # noqa: E402
from ffcomp.pipeline.header import header_accel  # noqa: E402
from ffcomp.pipeline.limited_moves import z_hop  # noqa: E402
from ffcomp.pipeline.output_check import _at_rest_first, check_gcode_output  # noqa: E402
from ffcomp.pipeline.stream_flow import inv_pre_samples  # noqa: E402
from ffcomp.sim.metrics import evaluate_masked, extruding_mask  # noqa: E402
from ffcomp.sim.plant import DeltaPlant  # noqa: E402

MARGIN_S = 0.15  # free command either side of a cluster of fixed samples, s
GAP_S = 0.3  # clusters closer than this share a window, s
TAIL_S = 0.3  # ringing counted after the window, s


def fixed_masks(move_index: np.ndarray, moves: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: on an extruder-only move or dwell (a hold), and on a z move (more z than XY)
    right after or right before one."""
    def hold(i) -> bool:
        mv = moves.get(int(i))
        return mv is not None and mv.kind != "move"

    def z_next_to_hold(i) -> bool:
        mv = moves.get(int(i))
        return (mv is not None and mv.kind == "move" and z_hop(mv)
                and (hold(mv.index - 1) or hold(mv.index + 1)))

    ids = np.unique(move_index)
    h = {int(i): hold(i) for i in ids}
    z = {int(i): z_next_to_hold(i) for i in ids}
    return (np.array([h[int(i)] for i in move_index]), np.array([z[int(i)] for i in move_index]))


def bound_command(model: LpvModel, X: np.ndarray, q: np.ndarray, ideal: np.ndarray, fixed: np.ndarray,
                  fixed_z: np.ndarray, dt: float, accel: float, box_m_s2: tuple | None = None,
                  windows: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """The exact command with every window around ``fixed`` samples (all axes) and ``fixed_z`` samples
    (the nozzle's z only) replaced by its optimum; with ``box_m_s2`` (x, y, z) the nozzle's
    acceleration stays within it on every sample of the windows; the windows around ``windows``
    samples if given."""
    pr = PulseResponses(model, dt, RepairConfig(tail_s=TAIL_S))
    u = ideal.copy()
    m, N = int(round(MARGIN_S / dt)), len(q)
    base = forward(model.geometry, ideal) if box_m_s2 is not None else None
    wins = pinned_clusters(fixed | fixed_z if windows is None else windows, int(round(GAP_S / dt)))
    for a0, b0 in wins:
        a, b = max(a0 - m, 0), min(b0 + m, N)
        pose = X[(a0 + b0) // 2]
        box = None if box_m_s2 is None else (np.ones(b - a, bool), base[a:b], box_m_s2)
        opt = pinned_optimum(pr.at(pose), jacobian(model.geometry, pose), fixed[a:b], (q - ideal)[a:b], dt,
                             pin_z=fixed_z[a:b], accel_box=box, accel_m_s2=accel)
        u[a:b] += opt.correction_m
    return u, len(wins)


@dataclass
class FileBounds:
    """One file's runs: ``check`` (none, exact, G-code; :func:`check_gcode_output`), the number of
    windows, and the reports of the three bounds (``limits``: holds fixed, the nozzle's acceleration
    within ``ACCEL`` and ``max_z_accel``; ``planned``: the same and the z moves' z fixed; ``free``:
    holds fixed, z unbounded), none of them when the file has no hold."""

    check: object
    windows: int
    none: object = None
    limits: object = None
    planned: object = None
    free: object = None
    #: lag-aligned and contour RMS (um) of ``none`` and the bounds over the samples where the plan
    #: extrudes while it moves (what marks the part)
    extruding: dict | None = None

    def ratio(self, run: str, metric: str = "lag") -> float:
        """RMS of ``run`` (``exact``, ``gcode`` or a bound) over the uncompensated file's."""
        if run in ("exact", "gcode"):
            return getattr(getattr(self.check, run), metric).rms_norm_um / getattr(self.check.none, metric).rms_norm_um
        return getattr(getattr(self, run), metric).rms_norm_um / getattr(self.none, metric).rms_norm_um

    def kept(self, run: str, metric: str = "lag") -> float:
        """Share of the exact commands' reduction ``run`` keeps."""
        return (1 - self.ratio(run, metric)) / (1 - self.ratio("exact", metric))

    def kept_extruding(self, run: str, metric: str = "lag") -> float:
        """:meth:`kept` over the extruding samples only (NaN when the file does not extrude)."""
        ext = self.check.extruding
        if not ext:
            return float("nan")
        if run == "exact":
            return 1.0
        if run == "gcode":
            return self.check.kept_extruding(metric)
        i = 0 if metric == "lag" else 1
        r_run = self.extruding[run][i] / self.extruding["none"][i]
        r_exact = ext["exact"][i] / ext["none"][i]
        return (1 - r_run) / (1 - r_exact)


def file_bounds(prof, truth, text: str, tmp: Path, accel: float = 10.0) -> FileBounds:
    """The fidelity bench's runs of one file (G-code ``text``) and the three bounds."""
    src = tmp / "in.gcode"
    src.write_text(text)
    c = check_gcode_output(prof, src, tmp / "out.gcode", plant_profile=truth,
                           opts=CompensateOptions(predict=False, self_check_tol_um=1e9, self_check_drift_ms=1e9))
    # the same reference as check_gcode_output's: the plan with the inverse's rest before it
    start = resolve_start(str(src), prof).position_mm
    ref = concat_blocks(sample_gcode(str(src), prof, overlap=0, start_position_mm=start))
    moves = {mv.index: mv for mv in GcodePlan(str(src), prof, start_position_mm=start)}
    dt = float(ref.t_s[1] - ref.t_s[0])
    n_pre = inv_pre_samples(InverseConfig(), dt)
    X, q, e = _at_rest_first(ref.xyz_m, ref.q_m, ref.e_mm, n_pre)
    mi = np.concatenate([np.full(n_pre, -1), ref.move_index])
    hold, zmove = fixed_masks(mi, moves)
    if not hold.any():
        return FileBounds(c, 0)
    model = LpvModel.from_profile(prof)
    t = np.arange(len(q)) * dt
    ideal = invert(model, q, X, dt).q_cmd
    no = np.zeros_like(hold)
    # Klipper caps a segment's acceleration at max_z_accel * d/|dz|: along a segment that is a cap on
    # its z acceleration, |a_z| <= max_z_accel, on every move (the z moves and the rest alike); and
    # at the run's ACCEL (the output's header) in x and y
    a_xy = header_accel(prof, CompensateOptions()) * 1e-3
    u_lim, nw = bound_command(model, X, q, ideal, hold, no, dt, accel,
                              (a_xy, a_xy, prof.limits.max_z_accel_mm_s2 * 1e-3), windows=hold | zmove)
    u_planned, _ = bound_command(model, X, q, ideal, hold, zmove, dt, accel,
                                 (a_xy, a_xy, prof.limits.max_z_accel_mm_s2 * 1e-3), windows=hold | zmove)
    u_free, _ = bound_command(model, X, q, ideal, hold, no, dt, accel, (a_xy, a_xy, np.inf), windows=hold | zmove)
    sim = DeltaPlant.from_profile(truth or prof).simulate(t, np.stack([q, u_lim, u_planned, u_free]), hold="linear")
    ext = extruding_mask(X, e, dt)
    reps = [evaluate_masked(t, X, sim.xyz_m[r], ext) for r in range(4)]
    extruding = {k: reps[r][1] for r, k in enumerate(("none",) + BOUNDS)} if ext.any() else None
    return FileBounds(c, nw, *(r[0] for r in reps), extruding=extruding)


BOUNDS = ("limits", "planned", "free")


def _cells(fb: FileBounds, metric: str) -> str:
    return " / ".join(f"{fb.ratio(b, metric):.3f}" for b in BOUNDS)


def _kept(fb: FileBounds, metric: str) -> str:
    return " / ".join(f"{fb.kept(r, metric):.2f}" for r in ("gcode",) + BOUNDS)


def _kept_ext(fb: FileBounds, metric: str) -> str:
    return " / ".join(f"{fb.kept_extruding(r, metric):.2f}" for r in ("gcode",) + BOUNDS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the fidelity bench's quick files")
    ap.add_argument("--only", default=None, help="only files whose name contains this")
    ap.add_argument("--profiles", default="default,other_delta")
    ap.add_argument("--accel", type=float, default=10.0,
                    help="command acceleration (m/s^2) that costs as much as 1 um of error (default 10)")
    a = ap.parse_args()
    profiles = fid.bench_profiles()
    tmp = Path(tempfile.mkdtemp(prefix="bench_hold_bound_"))
    for pname, (prof, truth) in profiles.items():
        if pname not in a.profiles.split(","):
            continue
        print(f"\n### {pname}\n")
        print("| file | windows | exact lag | G-code lag | bound lag: profile's limits / z as planned / z free "
              "| exact contour | G-code contour | bound contour: limits / planned / free "
              "| kept lag: G-code / bounds | kept contour: G-code / bounds "
              "| kept lag, extruding: G-code / bounds | kept contour, extruding: G-code / bounds |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for name, text in fid.files(a.quick).items():
            if a.only and a.only not in name:
                continue
            fb = file_bounds(prof, truth, text, tmp, a.accel)
            if not fb.windows:
                print(f"| {name} | 0 | {fb.ratio('exact'):.3f} | {fb.ratio('gcode'):.3f} | (no holds) "
                      f"| {fb.ratio('exact', 'contour'):.3f} | {fb.ratio('gcode', 'contour'):.3f} | | "
                      f"{fb.kept('gcode'):.2f} | {fb.kept('gcode', 'contour'):.2f} "
                      f"| {fb.kept_extruding('gcode'):.2f} | {fb.kept_extruding('gcode', 'contour'):.2f} |", flush=True)
                continue

            print(f"| {name} | {fb.windows} | {fb.ratio('exact'):.3f} | {fb.ratio('gcode'):.3f} | {_cells(fb, 'lag')} "
                  f"| {fb.ratio('exact', 'contour'):.3f} | {fb.ratio('gcode', 'contour'):.3f} "
                  f"| {_cells(fb, 'contour')} | {_kept(fb, 'lag')} | {_kept(fb, 'contour')} "
                  f"| {_kept_ext(fb, 'lag')} | {_kept_ext(fb, 'contour')} |", flush=True)


if __name__ == "__main__":
    main()
