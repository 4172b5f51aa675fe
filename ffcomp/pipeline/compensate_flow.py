"""Compensation flow: G-code -> plan -> samples -> streaming inverse -> compensated G-code.

One pass streams the source through the firmware-faithful planner and the sampler into the
streaming inverse; finished commands go through forward kinematics to the writer, while the LPV
model predicts the residual vibration of the reference and of the command for the summary.  The
body is written to a temporary file; the header (which states the firmware settings the file
needs, from what the body turned out to need) is prepended, the result is re-planned by the same
planner as a self-check, and only then does it replace the output atomically.

The run's options and summary are in :mod:`.options`, the compensation stream (plan, samples,
inverse) in :mod:`.stream_flow`, the ``--jobs`` pieces in :mod:`.pieces`; this module writes the
body and orchestrates.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..compensate.delta_cap import DeltaCap, jacobian_table
from ..errors import GcodeError, SelfCheckError
from ..gcode.chain_plan import ChainLimits
from ..gcode.commands import UNKNOWN_POLICIES
from ..gcode.flavour import detect_flavour, flavour_mismatch
from ..gcode.parser import parse_gcode
from ..gcode.planner import GcodePlan
from ..gcode.signature import scan_gcode
from ..gcode.start import resolve_start
from ..gcode.writer import GcodeWriter
from ..io_atomic import check_output_path, commit, keep_temp, make_temp, release_temp, sweep_stale
from ..kinematics import forward, inverse
from ..model.lpv import LpvModel
from .header import firmware_needs, header_accel, header_lines, limit_warnings, quiet_z_period_s, shaper_summary
from .limited_moves import (
    LimitBound,
    ZLimited,
    after_firmware,
    enters_by_extruder,
    lead_into,
    moves_where,
    z_held,
    z_hop,
    z_moving,
)
from .options import (  # noqa: F401  (re-exported: the run's options and summary live in options.py)
    JUMP_M,
    PIECE_START_FEED_MM_MIN,
    REST_MOVE,
    Z_MODES,
    CompensateOptions,
    CompensationSummary,
)
from .pieces import Piece, _PieceState
from .pin_stream import PinStats, pin_repaired
from .predictor import Predictor
from .retime import retime_file
from .self_check import self_check
from .stream_flow import compensated_stream, inv_pre_samples, inverse_config

__all__ = ["CompensateOptions", "CompensationSummary", "compensate_file", "JUMP_M", "header_accel", "Piece",
           "write_body", "BodyResult", "compensated_stream", "inverse_config", "inv_pre_samples"]


def _refuse_compensated(path: str) -> int:
    """Compensating a file twice would invert the model twice: refuse a file ffcomp wrote, by the marks
    its body carries anywhere (:mod:`ffcomp.gcode.signature`).  Returns the file's line count."""
    scan = scan_gcode(path)
    if scan.mark_line is not None:
        raise GcodeError(path, scan.mark_line, "this file is already compensated by ffcomp (compensate the "
                         "slicer's original instead)", scan.mark_text)
    if scan.intrinsic:
        raise GcodeError(path, 0, f"this file is already compensated by ffcomp: {scan.segment_lines} of its "
                         f"{scan.g1_lines} G1 lines have the form ffcomp writes (compensate the slicer's "
                         "original instead)")
    return scan.lines


def compensate_file(src: str, out_path: str | None, profile, opts: CompensateOptions = CompensateOptions(),
                    progress: Callable[[int, int], None] | None = None) -> CompensationSummary:
    """See :func:`_compensate_file`; with ``out_path=None`` the G-code goes to stdout, and anything a
    library prints at the C level meanwhile is sent to stderr so it cannot corrupt the G-code."""
    if out_path is not None:
        return _compensate_file(src, out_path, profile, opts, progress)
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        return _compensate_file(src, None, profile, opts, progress, stdout_fd=saved)
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _compensate_file(src: str, out_path: str | None, profile, opts: CompensateOptions = CompensateOptions(),
                     progress: Callable[[int, int], None] | None = None, stdout_fd: int | None = None
                     ) -> CompensationSummary:
    """Compensate the G-code file ``src`` and write ``out_path`` atomically (``None``: stdout).

    On any error the output is not touched (and the source never is: with ``out_path == src`` the
    source is replaced only after the whole output, header and self-check are done).
    """
    t_wall = time.perf_counter()
    if opts.z_mode not in Z_MODES:
        raise ValueError(f"z_mode must be one of {', '.join(Z_MODES)}, got {opts.z_mode!r}")
    src = str(src)
    if not os.path.isfile(src):
        raise GcodeError(src, 0, "no such file")
    if not isinstance(opts.jobs, int) or opts.jobs < 1:
        raise ValueError(f"jobs must be an integer >= 1, got {opts.jobs!r}")
    if opts.unknown_policy not in UNKNOWN_POLICIES:
        raise ValueError(f"unknown_policy must be one of {', '.join(UNKNOWN_POLICIES)}, got {opts.unknown_policy!r}")
    total_lines = _refuse_compensated(src)
    if out_path is not None:  # a path that cannot be written fails now, not after all the work
        out_path = check_output_path(out_path)
    start = resolve_start(src, profile, opts.start_mm)
    geom = LpvModel.from_profile(profile).geometry
    summ = CompensationSummary(source=src, output=str(out_path) if out_path else "-", method=opts.method,
                               lines_in=total_lines, firmware=profile.limits.planner,
                               start_mm=list(start.position_mm[:3]), homed_first=start.homed_first)
    _check_flavour(src, profile, summ)
    summ.quiet_z_period_s = quiet_z_period_s(profile, opts)  # (here: with --jobs the workers count the moves)
    if opts.quiet_z and profile.limits.planner != "klipper":
        summ.warnings += 1
        summ.notes.append(f"quiet z moves (--quiet-z) are planned for Klipper only; the {profile.limits.planner} "
                          "plan of this file keeps its z moves as they are")
    start_warning = start.warning(src)
    out_dir = os.path.dirname(os.path.abspath(out_path)) if out_path else tempfile.gettempdir()
    summ.stale_temps_removed = len(sweep_stale(out_dir))  # leftovers of runs that were killed
    body_path = qfile = segfile = final_tmp = None
    try:
        qfile_fd, qfile = make_temp(out_dir, "q", ".f32")
        os.close(qfile_fd)
        seg_fd, segfile = make_temp(out_dir, "seg", ".i64")
        os.close(seg_fd)
        body_fd, body_path = make_temp(out_dir, "body", ".gcode")
        os.close(body_fd)
        if opts.jobs > 1:  # pieces cut where the toolhead stands still, on that many processes
            from .parallel_flow import write_body_parallel

            bd = write_body_parallel(src, profile, opts, start, summ, body_path, qfile, segfile, progress,
                                     total_lines, out_dir, opts.jobs)
        else:
            bd = write_body(src, profile, opts, start, summ, body_path, qfile, segfile, progress, total_lines)
        accel = bd.accel
        summ.warnings += bd.parser_warnings
        _count_commands(summ, bd.counts)
        if bd.counts.get("ignored"):
            summ.warnings += 1
            summ.notes.append(_ignored_note(bd.counts["ignored"], profile.limits.planner))
        if start_warning:
            summ.warnings += 1
            summ.notes.append(start_warning)
        summ.notes.extend(bd.warning_messages[:20])
        _stage(progress, "writing", total_lines)
        summ.segments = bd.stats.segments
        summ.micro_holds = bd.stats.micro_holds
        if bd.pred_n:
            summ.rms_before_um, summ.max_before_um = bd.rms_um(1), bd.pred_mx[1] * 1e6
            summ.rms_after_um, summ.max_after_um = bd.rms_um(0), bd.pred_mx[0] * 1e6
            summ.predict_time_s = bd.pred_time_s
        # header with the firmware settings this file needs, then the body
        summ.header_accel_mm_s2 = accel
        summ.peak_command_accel_mm_s2 = bd.stats.peak_accel_mm_s2
        needs = firmware_needs(profile, opts, accel, bd.stats)
        head, foot = header_lines(profile, opts, src, accel, needs, summ.firmware_retractions)
        if bd.firmware == "klipper":
            summ.input_shaper = shaper_summary(profile)
        final_fd, final_tmp = make_temp(out_dir, "out", ".gcode")
        n_out = 0
        with os.fdopen(final_fd, "w", encoding="utf-8", errors="surrogateescape", newline="") as fo, \
                open(body_path, encoding="utf-8", errors="surrogateescape", newline="") as fb:
            for ln in head:
                fo.write(ln + "\n")
            for ln in fb:
                fo.write(ln)
                n_out += 1
            for ln in foot:
                fo.write(ln + "\n")
            fo.flush()
            os.fsync(fo.fileno())
        summ.lines_out = n_out + len(head) + len(foot)
        retimed = bd.firmware != "klipper" and opts.retime_passes > 0
        if retimed:  # (the whole file: with --jobs, the pieces' own self-checks no longer hold)
            _stage(progress, "re-timing", total_lines)
            t_rt = time.perf_counter()
            rt = retime_file(final_tmp, qfile, profile, geom, summ.start_mm, segfile, len(head),
                             passes=opts.retime_passes)
            summ.retime_passes, summ.retime_before_ms, summ.retime_after_ms = rt.passes, rt.before_ms, rt.after_ms
            summ.retime_time_s = time.perf_counter() - t_rt
        if opts.self_check:
            _stage(progress, "self-check", total_lines)
            if bd.self_checks is not None and not opts.self_check_whole and not retimed:  # --jobs: per piece
                from .parallel_flow import judge_pieces

                judge_pieces(bd, summ, opts, profile)
            else:
                self_check(final_tmp, qfile, profile, geom, summ, opts, segfile, len(head))
        if bd.firmware == "klipper":  # (after the self-check: its drift is what the limits cost)
            lim_notes = limit_warnings(profile, needs, bd.stats, summ.self_check_drift_ms, summ.self_check_abs_max_um)
            summ.warnings += len(lim_notes)
            summ.notes.extend(lim_notes)
        # success: move into place
        if out_path is None:
            import shutil

            with open(final_tmp, "rb") as f, os.fdopen(os.dup(stdout_fd), "wb") as out:
                shutil.copyfileobj(f, out)
        else:
            try:
                os.chmod(final_tmp, os.stat(out_path).st_mode & 0o7777)
            except FileNotFoundError:
                os.chmod(final_tmp, 0o644)
            commit(final_tmp, out_path)
            keep_temp(final_tmp)
            final_tmp = None
    finally:
        for p in (body_path, qfile, segfile, final_tmp):
            release_temp(p)
    summ.wall_time_s = time.perf_counter() - t_wall
    summ.speed_ratio = summ.print_time_s / max(summ.wall_time_s, 1e-9)
    return summ


def _open_existing(path: str, mode: str):
    """Open a temporary file that already exists (``make_temp``) for writing, truncated, without
    creating it: a file a stop signal removed meanwhile is not brought back."""
    fd = os.open(path, os.O_WRONLY | os.O_TRUNC)
    if "b" in mode:
        return os.fdopen(fd, "wb")
    return os.fdopen(fd, "w", encoding="utf-8", errors="surrogateescape", newline="")


@dataclass
class BodyResult:
    """What :func:`write_body` wrote: the writer's statistics (the header's firmware needs come from
    them), the parser's counts, the prediction's sums, and for a piece (``--jobs``) where it was cut."""

    stats: object
    accel: float
    firmware: str
    parser_warnings: int
    counts: dict
    warning_messages: list
    pred_sq: list
    pred_n: int
    pred_mx: list
    pred_time_s: float = 0.0
    k_written: int = 0
    streams: int = 0
    n_xyz: int = 0
    cut_lo: tuple | None = None
    cut_hi: tuple | None = None
    lines_read: int = 0
    #: where the body's first stream starts (the plan's point) and where its last segment ends, mm
    start_mm: list | None = None
    end_mm: list | None = None
    #: ``--jobs``: the pieces' self-check numbers (:func:`ffcomp.pipeline.self_check.measure`), the
    #: first sample of each piece, and the largest gap between where a piece ends and the next starts
    self_checks: list | None = None
    k_offsets: list | None = None
    seam_gap_mm: float = 0.0

    def rms_um(self, r: int) -> float:
        return math.sqrt(self.pred_sq[r] / max(self.pred_n, 1)) * 1e6


def write_body(src: str, profile, opts: CompensateOptions, start, summ: CompensationSummary, body_path: str,
               qfile: str, segfile: str, progress=None, total_lines: int = 0, piece: Piece | None = None
               ) -> BodyResult:
    """Plan, sample, invert, pin-repair and write the compensated body of ``src`` (or of one
    :class:`Piece` of it) to ``body_path``, the intended carriage commands (float32 rows) to ``qfile``
    and the writer's segment table to ``segfile`` (all three exist already: they are opened without
    being created, so a file a stop signal removed is not re-created).  Counters go into ``summ``."""
    model = LpvModel.from_profile(profile)
    geom = model.geometry
    dt = 1.0 / profile.limits.sample_rate_hz
    icfg = inverse_config(profile, opts)
    cuts = _PieceState(piece) if piece is not None else None
    moves: dict = {}
    quiet_s = quiet_z_period_s(profile, opts)
    plan = GcodePlan(src, profile, lenient=opts.lenient, start_position_mm=start.position_mm,
                     unknown_policy=opts.unknown_policy,
                     **({} if quiet_s is None else {"quiet_z_period_s": quiet_s}))
    with _open_existing(body_path, "w") as body, _open_existing(qfile, "wb") as qf, \
            _open_existing(segfile, "wb") as sf:
        lines = iter(parse_gcode(src, lenient=True, dialect=plan.firmware,
                                 arc_resolution_mm=plan.parser.arc_resolution_mm,
                                 home_position_mm=(0.0, 0.0, profile.geometry.z_max_mm),
                                 start_position_mm=start.position_mm, unknown_policy=opts.unknown_policy,
                                 firmware_retraction=profile.firmware_retraction))
        if cuts is not None:  # the piece's own source lines only (known once its cuts are found)
            lines = cuts.window(lines)
        accel = header_accel(profile, opts)
        chain = ChainLimits(profile, accel, opts.corner_velocity_mm_s) if plan.firmware == "klipper" else None
        writer = GcodeWriter(lines, body, dt, opts.tol_um * 1e-3, moves, accel_mm_s2=accel,
                             # (Marlin: the header's M201 Z is the header's acceleration)
                             max_z_accel_mm_s2=profile.limits.max_z_accel_mm_s2 if chain is not None else accel,
                             max_z_velocity_mm_s=profile.limits.max_z_velocity_mm_s, segment_table=sf,
                             chain_limits=chain)
        writer.start_travel_mm_s = start.travel_mm_s if cuts is None or cuts.first else None
        if chain is None:  # Marlin: the source's extruder limits stay in force for its retractions
            writer.extruder_limits = True
        pred = Predictor(model, dt) if opts.predict else None
        # (Klipper: moves its extruder's limits bind follow the plan.  Marlin: none; letting Klipper's
        # rule pin them on Marlin too put more files off the clock: bench_marlin_clock.py)
        bound = LimitBound(chain) if opts.plan_where_limited and chain is not None else None
        pin_stats = PinStats()
        zlim = ZLimited(chain) if chain is not None else None
        k_written = 0
        last_qc = None
        ends = [None]  # where the body starts (the plan's point), mm

        def emit(qc, meta):
            nonlocal k_written, last_qc
            xyz = forward(geom, qc)
            if np.any(~np.isfinite(xyz)):
                bad = int(np.argmax(~np.isfinite(xyz).all(1)))
                raise SelfCheckError(f"compensated carriage command at sample {k_written + bad} has no "
                                     f"nozzle position (carriages {qc[bad] * 1e3} mm)")
            fix = np.zeros(len(xyz), bool)
            new_stream = bool(k_written) and np.max(np.abs(qc[0] - last_qc)) > JUMP_M  # a homing jump
            if opts.z_mode in ("hold", "auto"):
                hold = (z_held if opts.z_mode == "hold" else z_moving)(meta["move_index"], moves)
                if opts.z_mode == "auto":
                    hold = _rest_follows_moves(meta["move_index"], hold)
                xyz[hold, 2] = meta["xyz"][hold, 2]
                fix |= hold
            # moves the firmware's own limits bind (max_z_accel, the extruder's, the rim's slow
            # zones) cannot take a command that accelerates harder than the plan: they follow
            # the plan, sample by sample, so the clock holds (counted in the summary)
            dense = shift = None
            if bound is not None:
                # with the pin repair those moves are pinned (the plan, sample by sample): no blend
                w, wz = bound.weights(meta["move_index"], moves, blend_moves=not opts.pin_repair,
                                      z_limited=zlim.limited if zlim is not None else None,
                                      k_plan=meta.get("k"), dt_s=dt, new_stream=new_stream)
                dense = (w > 0) | (wz > 0)
                if dense.any():
                    xyz[dense] += w[dense, None] * (meta["xyz"][dense] - xyz[dense])
                    xyz[dense, 2] += wz[dense] * (meta["xyz"][dense, 2] - xyz[dense, 2])
                    fix |= dense
                    summ.plan_fallback_samples += int(np.sum(np.maximum(w, wz) >= 1.0))
            if quiet_s is not None:  # quiet z moves: their slow ramps, sample by sample (see below)
                qd = moves_where(meta["move_index"], moves, _is_quiet)
                if qd.any():
                    dense = qd if dense is None else (dense | qd)
            at_sample = None  # the command at the samples ZLimited moved onto a z reversal, m
            if zlim is not None:  # moves max_z_accel binds: every sample a segment (see ZLimited)
                pre = xyz.copy()
                zd, snapped, shift = zlim.dense(meta["move_index"], moves, xyz, k_plan=meta.get("k"), dt_s=dt,
                                                new_stream=new_stream)
                dense = zd if dense is None else (dense | zd)
                if snapped.any():
                    # the moved point is the command at the vertex's time, where the writer puts it;
                    # the intended command at the sample's own time stays (the self-check compares
                    # the re-planned output with it there: the point's value at the sample's time
                    # was up to 50 um off where the command moves fast in XY)
                    at_sample = (snapped, pre[snapped])
            # the firmware refuses positions outside its limits: a correction that pokes past
            # them (at z_max after homing, at the rim) is clamped to the boundary
            cl = _clamp_to_workspace(xyz, geom)
            if cl.any():
                summ.clamped += int(cl.sum())
                fix |= cl
            if fix.any() or at_sample is not None:
                qc = qc.copy()
                qc[fix] = inverse(geom, xyz[fix])
                if at_sample is not None:
                    sn, p_ = at_sample
                    _clamp_to_workspace(p_, geom)
                    qc[sn] = inverse(geom, p_)
            summ.max_correction_um = max(summ.max_correction_um,
                                         float(np.max(np.abs(qc - meta["q"]))) * 1e6)
            qf.write(qc.astype(np.float32).tobytes())
            if new_stream or not k_written:  # the machine stands where the plan starts the stream
                writer.flush_samples()  # (the last stream's held-back samples first)
                writer.last_pt = None
                writer.stream_start_mm = np.round(meta["xyz"][0] * 1e3, 4)
                if not k_written:
                    ends[0] = writer.stream_start_mm.tolist()
                    if cuts is not None and not cuts.first:
                        # a piece after a cut: the previous piece's last point is within micrometres
                        # of the plan's rest point, but the first segments of a stream crawl (the
                        # pre-actuation from rest), so those micrometres would cost tens of ms: go
                        # there first, at once, so the piece starts where its writer assumes
                        x, y, z = ends[0]
                        writer._w(f"G1 X{x:.4f} Y{y:.4f} Z{z:.4f} F{PIECE_START_FEED_MM_MIN:g} ; ffcomp: piece start "
                                  "(--jobs): the plan's rest point\n")
            if pred is not None:
                if new_stream:
                    pred.reset()
                pred.push(qc, meta["q"], meta["xyz"])
            writer.feed(k_written, xyz * 1e3, meta["e"], meta["move_index"], meta["lineno"], dense,
                        k_plan=meta.get("k"), plan_mm=meta["xyz"] * 1e3, t_shift=shift)
            k_written += len(qc)
            last_qc = qc[-1].copy()
            if progress is not None:
                progress(int(meta["lineno"][-1]), total_lines)

        stream = compensated_stream(plan, moves, profile, model, icfg, opts, summ, src, cuts)
        if opts.pin_repair:

            def hop_pinned(mv) -> bool:  # a z-hop right after a hold: the firmware must run its z as planned
                return bound is not None and opts.repair.pin_z_after_hold and z_hop(mv) and bound.z_after_hold(
                    mv, moves)

            def lift_after_move(mv) -> bool:  # a layer change's lift right after a printed line
                if not (opts.repair.pin_layer_lifts and zlim is not None and z_hop(mv) and zlim.limited(mv)):
                    return False
                prev = moves.get(mv.index - 1)
                return prev is not None and prev.kind == "move" and prev.end_mm[3] > prev.start_mm[3] + 1e-9

            def pinned(mv) -> bool:
                if mv.kind != "move":  # extruder-only move or dwell
                    return True
                if lift_after_move(mv):
                    return True
                return bound is not None and (bound.bound(mv) or (not opts.repair.z_only_hops and hop_pinned(mv)) or (
                    opts.repair.pin_z_before_hold and z_hop(mv) and bound.z_before_hold(mv, moves)
                    and zlim is not None and zlim.limited(mv)))

            def pinned_z(mv) -> bool:  # a pinned move that max_z_accel binds (a z-hop's move down)
                return mv.kind == "move" and zlim is not None and zlim.limited(mv) and pinned(mv)

            def led_in(mv) -> bool:  # the moves the one before runs into on the plan (lead_into)
                return pinned_z(mv) or (opts.repair.lead_in_extruder and chain is not None
                                        and enters_by_extruder(mv, moves, chain.instant_corner_v) and pinned(mv))

            def pins(meta):
                t_s = meta["k"] * dt
                return (moves_where(meta["move_index"], moves, pinned)
                        | after_firmware(meta["move_index"], moves, t_s, dt)
                        | lead_into(meta["move_index"], moves, t_s, opts.repair.lead_in_s, led_in,
                                    opts.repair.lead_in_printed_s, opts.repair.lead_in_z_s,
                                    opts.repair.lead_in_wet))

            zpins = (lambda meta: moves_where(meta["move_index"], moves, hop_pinned)) if opts.repair.z_only_hops \
                else None
            steep = (lambda meta: moves_where(meta["move_index"], moves, zlim.limited)) if zlim is not None else None
            cap = (DeltaCap(chain.max_z_accel * 1e-3, chain.accel * 1e-3, chain.jd * 1e-3, dt,
                            jacobian_bounds=jacobian_table(geom)) if chain is not None else None)
            stream = pin_repaired(stream, pins, model, dt, opts.repair, pin_stats, jump_m=JUMP_M, steep_fn=steep,
                                  zpin_fn=zpins, z_limit_m_s2=zlim.lim.max_z_accel * 1e-3 if zlim is not None else None,
                                  cap=cap)
        for qc, meta in stream:
            emit(qc, meta)
        if cuts is not None:
            writer.flush_samples()
            cuts.before_finish(writer)
        writer.finish()
    if pred is not None:
        pred.flush()
    summ.pin_windows, summ.pinned_samples = pin_stats.windows, pin_stats.pinned_samples
    summ.cap_windows, summ.cap_max_change_um = pin_stats.cap_windows, pin_stats.cap_max_change_m * 1e6
    summ.pin_max_change_um = pin_stats.max_change_m * 1e6
    if quiet_s is not None:
        summ.quiet_z_moves = plan.planner.quiet_moves
        summ.quiet_z_time_s = plan.planner.quiet_added_s
    parser = plan.parser
    return BodyResult(stats=writer.stats, accel=accel, firmware=plan.firmware,
                      parser_warnings=parser.warnings if hasattr(parser, "warnings") else 0,
                      counts=dict(parser.counts, ignored=dict(plan.planner.ignored)),
                      warning_messages=list(parser.warning_messages[:20]),
                      pred_sq=[float(x) for x in pred.sq] if pred is not None else [0.0, 0.0],
                      pred_n=pred.n if pred is not None else 0,
                      pred_mx=[float(x) for x in pred.mx] if pred is not None else [0.0, 0.0],
                      pred_time_s=pred.elapsed_s if pred is not None else 0.0,
                      k_written=k_written, streams=writer.stream + 1,
                      n_xyz=cuts.n_xyz if cuts is not None else 0,
                      cut_lo=cuts.lo if cuts is not None else None, cut_hi=cuts.hi if cuts is not None else None,
                      lines_read=parser.lines_read, start_mm=ends[0],
                      end_mm=writer.last_pt.tolist() if writer.last_pt is not None else None)


def _is_quiet(mv) -> bool:
    """A z move planned with quiet ramps (``CompensateOptions.quiet_z``).  Its samples are written one
    segment each, with their own feeds, so the firmware runs the slow ramps as the plan does: with
    points placed by the tolerance instead, cube_prusa on other_delta wrote 7 % fewer segments and
    kept the same drift, but its largest distance from the intended command at the same instant grew
    from 4.0 to 7.2 um.  (The ramps' sub-micrometre ends are :func:`~ffcomp.gcode.holds.merged_ramp_holds`'s.)"""
    return mv.quiet


def _stage(progress, name: str, total: int) -> None:
    """Tell a progress reporter that has a ``stage(name, total)`` method that a new stage begins."""
    f = getattr(progress, "stage", None)
    if f is not None:
        f(name, total)


def _check_flavour(src: str, profile, summ: CompensationSummary) -> None:
    """Warn (counted, in the notes) when the file was sliced for other firmware than the profile's."""
    fl = detect_flavour(src)
    summ.source_flavour = fl.name if fl else None
    msg = flavour_mismatch(fl, profile.limits.planner, src, profile.name)
    if msg:
        summ.warnings += 1
        summ.notes.append(msg)


def _ignored_note(ignored: dict, planner: str) -> str:
    """The warning for limit commands the profile's firmware ignores (planned as it runs them):
    ``ignored`` maps what they are to how many (the planner's ``ignored``)."""
    which = ", ".join(f"{k}: {v}" for k, v in sorted(ignored.items()))
    why = ("; an M204 without S or T is a Marlin per-feature acceleration, to which Klipper answers 'Invalid M204 "
           "command'" if "M204 without S or T" in ignored else "")
    return (f"{sum(ignored.values())} limit command(s) that {planner} ignores ({which}{why}). The plan and the "
            "output run as the firmware does, without them: the file's own limits there do not apply")


def _count_commands(summ: CompensationSummary, counts: dict) -> None:
    """The parser's per-class command counts into the summary (see :mod:`ffcomp.gcode.commands`)."""
    summ.commands_passed = counts.get("pass", 0)
    summ.commands_baked = counts.get("state", 0)
    summ.commands_stopped = counts.get("stop", 0)
    summ.commands_unknown = counts.get("unknown", 0)
    summ.lines_skipped = counts.get("skipped", 0)
    summ.commands_synced = counts.get("sync", 0)
    summ.firmware_retractions = counts.get("firmware_retraction", 0)


def _rest_follows_moves(move_index: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``mask`` with each rest sample a stream adds (move index < 0: before and after a stream,
    margins) given the value of the next planned move's samples in the chunk (its pre-actuation
    belongs to that move), else the previous one's.  ``--z-mode auto`` keeps the plan's z on moves
    that travel in z: a z pre-actuated in the rest before such a move would jump back onto the plan
    at the move (5 ms late after the homing of ``stress_square.gcode``)."""
    rest = move_index < 0
    if not rest.any() or rest.all():
        return mask
    n = len(move_index)
    idx = np.arange(n)
    nxt = np.minimum.accumulate(np.where(rest, n, idx)[::-1])[::-1]
    prv = np.maximum.accumulate(np.where(rest, -1, idx))
    src = np.where(nxt < n, nxt, prv)
    return np.where(rest, mask[src], mask)


def _clamp_to_workspace(xyz: np.ndarray, geom, margin_m: float = 2e-7) -> np.ndarray:
    """Clamp nozzle positions (m) in place into what Klipper's delta ``check_move`` accepts: the z
    range, the print radius, and the cone above ``limit_z`` where the radius shrinks to zero at the
    top (a command that pre-actuates away from the homed position would poke out of it).  Returns
    the mask of clamped rows.  ``margin_m`` keeps the printed (rounded) coordinates inside."""
    z = xyz[:, 2]
    bad = (z > geom.z_max_m - margin_m) | (z < geom.z_min_m)
    np.clip(z, geom.z_min_m, geom.z_max_m - margin_m, out=z)
    R = float(np.max(geom.delta_radius_m))
    L = float(np.min(geom.arm_length_m))
    limit_z = geom.z_max_m + np.sqrt(L * L - R * R) - L
    allowed = np.full(len(z), geom.print_radius_m)
    above = z - limit_z
    top = above > 0
    if top.any():
        allowed[top] = np.minimum(allowed[top], R - np.sqrt(np.maximum(L * L - (L - above[top]) ** 2, 0.0)))
    allowed = np.maximum(allowed - margin_m, 0.0)
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    far = r > allowed
    if far.any():
        scale = np.where(r[far] > 0, allowed[far] / np.maximum(r[far], 1e-300), 0.0)
        xyz[far, :2] *= scale[:, None]
    return bad | far
