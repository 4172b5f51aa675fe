"""Compensation flow: G-code -> plan -> samples -> streaming inverse -> compensated G-code.

One pass streams the source through the firmware-faithful planner and the sampler into the
streaming inverse; finished commands go through forward kinematics to the writer, while the LPV
model predicts the residual vibration of the reference and of the command for the summary.  The
body is written to a temporary file; the header (which states the firmware settings the file
needs, from what the body turned out to need) is prepended, the result is re-planned by the same
planner as a self-check, and only then does it replace the output atomically.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Callable

import numpy as np

from ..compensate.inverse import InverseConfig
from ..compensate.pin_repair import RepairConfig
from ..compensate.stream import StreamingInverse
from ..errors import GcodeError, SelfCheckError
from ..gcode.chain_plan import ChainLimits
from ..gcode.commands import UNKNOWN_POLICIES
from ..gcode.flavour import detect_flavour, flavour_mismatch
from ..gcode.moves import MOVE
from ..gcode.parser import parse_gcode
from ..gcode.planner import GcodePlan
from ..gcode.sampler import sample_blocks
from ..gcode.signature import scan_gcode
from ..gcode.start import resolve_start
from ..gcode.writer import GcodeWriter
from ..io_atomic import check_output_path, keep_temp, make_temp, release_temp, sweep_stale
from ..kinematics import carriage_rates, forward, inverse
from ..linalg3 import max_abs3
from ..model.lpv import LpvModel
from .header import firmware_needs, header_accel, header_lines, limit_warnings
from .limited_moves import LimitBound, ZLimited, holds, moves_where, z_held, z_hop, z_moving
from .pin_stream import PinStats, pin_repaired
from .predictor import Predictor
from .self_check import self_check

__all__ = ["CompensateOptions", "CompensationSummary", "compensate_file", "JUMP_M", "header_accel", "Piece",
           "write_body", "BodyResult"]

#: the z modes (see :class:`CompensateOptions`)
Z_MODES = ("keep", "hold", "auto")

#: move index of the rest samples before and after a compensation stream (no planned move: the
#: machine stands while the command pre-actuates the first move or settles after the last, so these
#: samples are motion of their own, never part of an extruder-only move or dwell)
REST_MOVE = -1

#: a carriage jump larger than this between two samples is a homing (the stream restarts), m
JUMP_M = 2e-3

#: feed of the move to the plan's rest point at the start of a piece (``--jobs``), mm/min: a few
#: micrometres at the header's acceleration take well under a millisecond
PIECE_START_FEED_MM_MIN = 600.0


@dataclass(frozen=True)
class CompensateOptions:
    """Options of :func:`compensate_file` (documented defaults).

    method : inverse variant (``lpv`` or ``lti-centre`` stream)
    tol_um : point placement tolerance of the G-code writer, micrometres
    z_mode : ``keep`` (emit the compensated z of every point), ``hold`` (keep z at the planned z
        wherever the plan holds it: no z motion on layer moves, for firmware with a low max_z_accel)
        or ``auto`` (the planned z on every move that travels in z: z travel runs on the clock at
        any max_z_accel, uncompensated).  In every mode the z of a z-hop right after an
        extruder-only move or dwell follows the plan (see ``plan_where_limited``).
    self_check : re-plan the output and compare with the intended commands
    self_check_tol_um : largest allowed deviation of the re-planned carriages, micrometres (at least
        3 x tol_um)
    self_check_drift_ms : largest allowed drift of the re-planned output on the absolute clock, ms
    predict : predict the residual vibration before/after with the LPV model for the summary
    lenient : malformed G-code lines become counted warnings
    accel_factor : the header's ACCEL is this times the profile's max_accel (at least 100,000 mm/s^2):
        the segments carry the timing, so the firmware should change speed between them at once
    pin_holds : (older, drive stage only) penalise the command's distance from the reference while the
        plan holds the nozzle still; superseded by ``pin_repair``
    corner_velocity_mm_s : the SQUARE_CORNER_VELOCITY the header sets: the compensated path already
        slows where the plan slows, so the firmware must not slow it again at every small turn
    start_mm : (x, y, z) where the toolhead stands before a file that moves before homing (``--start``);
        None: the target of the file's first move (:mod:`ffcomp.gcode.start`)
    unknown_policy : what an unknown macro or G code is: ``stop`` (the toolhead comes to rest before it,
        with a warning), ``pass`` (copied verbatim, with a warning) or ``refuse`` (an error); see
        :mod:`ffcomp.gcode.commands`
    """

    method: str = "lpv"
    tol_um: float = 5.0
    z_mode: str = "keep"
    self_check: bool = True
    self_check_tol_um: float = 50.0
    predict: bool = True
    lenient: bool = False
    accel_factor: float = 20.0
    pin_holds: bool = False
    corner_velocity_mm_s: float = 100.0
    block_len: int = 4096
    inverse: InverseConfig = field(default_factory=InverseConfig)
    start_mm: tuple | None = None
    unknown_policy: str = "stop"
    #: the self-check fails when the re-planned output runs more than this off the intended clock, ms
    self_check_drift_ms: float = 50.0
    #: moves the extruder's limits bind, and the z of z-hops right after a hold, follow the plan
    #: (see :class:`LimitBound`): the firmware could not run the compensated command on time there
    plan_where_limited: bool = True
    #: the command equals the plan wherever a G-code file cannot move it (extruder-only moves,
    #: dwells, the moves of ``plan_where_limited``) and is re-solved around those stretches
    #: (:mod:`ffcomp.compensate.pin_repair`), instead of moving on and catching up after them
    pin_repair: bool = True
    repair: RepairConfig = field(default_factory=RepairConfig)
    #: worker processes (``--jobs``): 1 is the serial run; N > 1 cuts the file into N pieces where the
    #: toolhead stands still and compensates them in parallel (:mod:`ffcomp.pipeline.parallel_flow`)
    jobs: int = 1
    #: with ``jobs`` > 1: re-plan the whole merged output in the self-check (one process, as the
    #: serial run does) instead of each piece in its worker from rest at its cut
    self_check_whole: bool = False


@dataclass
class CompensationSummary:
    """The closing summary of a run (all lengths in micrometres, times in seconds)."""

    source: str
    output: str
    method: str
    lines_in: int = 0
    lines_out: int = 0
    segments: int = 0
    print_time_s: float = 0.0
    output_print_time_s: float | None = None
    wall_time_s: float = 0.0
    speed_ratio: float = 0.0
    rms_before_um: float | None = None
    max_before_um: float | None = None
    rms_after_um: float | None = None
    max_after_um: float | None = None
    self_check_max_um: float | None = None
    self_check_rms_um: float | None = None
    self_check_catch_up_max_um: float | None = None
    max_correction_um: float = 0.0
    header_accel_mm_s2: float = 0.0
    restarts: int = 0
    clamped: int = 0
    peak_command_accel_mm_s2: float = 0.0
    warnings: int = 0
    notes: list = field(default_factory=list)
    firmware: str = ""
    source_flavour: str | None = None
    stale_temps_removed: int = 0
    #: non-motion commands by class (ffcomp.gcode.commands): passed through verbatim, baked in (kept as
    #: comments), stops (the toolhead rests there: known stops and unknown commands the policy made
    #: stops), unknown commands (whatever the policy did), malformed lines skipped (--lenient)
    commands_passed: int = 0
    commands_baked: int = 0
    commands_stopped: int = 0
    commands_unknown: int = 0
    lines_skipped: int = 0
    #: where the plan starts (x, y, z mm) and whether the file homes before its first move
    start_mm: list | None = None
    homed_first: bool | None = None
    #: the self-check on the absolute clock: largest lateness of a re-planned segment end against
    #: the intended command timeline (ms, signed), where (s), and at the end of the file (ms)
    self_check_drift_ms: float | None = None
    self_check_drift_at_s: float | None = None
    self_check_drift_end_ms: float | None = None
    #: largest carriage deviation from the intended commands at the same absolute time, um
    self_check_abs_max_um: float | None = None
    #: samples written from the plan (uncompensated) because the firmware's limits bind there
    plan_fallback_samples: int = 0
    #: pin repair (:mod:`ffcomp.compensate.pin_repair`): windows re-solved, samples held on the plan,
    #: largest change of the command (um)
    pin_windows: int = 0
    pinned_samples: int = 0
    pin_max_change_um: float = 0.0
    #: worker processes (``--jobs``) and, with more than one, each piece: its first source line, how
    #: it ends (the cut's kind: ``stop``, ``hold`` or None at the end of the file), its samples' print
    #: time, and its worker's wall and CPU time (s)
    jobs: int = 1
    pieces: list | None = None

    def to_dict(self) -> dict:
        return asdict(self)


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
        if start_warning:
            summ.warnings += 1
            summ.notes.append(start_warning)
        summ.notes.extend(bd.warning_messages[:20])
        _stage(progress, "writing", total_lines)
        summ.segments = bd.stats.segments
        if bd.pred_n:
            summ.rms_before_um, summ.max_before_um = bd.rms_um(1), bd.pred_mx[1] * 1e6
            summ.rms_after_um, summ.max_after_um = bd.rms_um(0), bd.pred_mx[0] * 1e6
        # header with the firmware settings this file needs, then the body
        summ.header_accel_mm_s2 = accel
        summ.peak_command_accel_mm_s2 = bd.stats.peak_accel_mm_s2
        needs = firmware_needs(profile, opts, accel, bd.stats)
        lim_notes = limit_warnings(profile, needs) if bd.firmware == "klipper" else []
        summ.warnings += len(lim_notes)
        summ.notes.extend(lim_notes)
        head, foot = header_lines(profile, opts, src, accel, needs)
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
        if opts.self_check:
            _stage(progress, "self-check", total_lines)
            if bd.self_checks is not None and not opts.self_check_whole:  # --jobs: each piece by its worker
                from .parallel_flow import judge_pieces

                judge_pieces(bd, summ, opts, profile)
            else:
                self_check(final_tmp, qfile, profile, geom, summ, opts, segfile, len(head))
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
            os.replace(final_tmp, out_path)
            keep_temp(final_tmp)
            final_tmp = None
    finally:
        for p in (body_path, qfile, segfile, final_tmp):
            release_temp(p)
    summ.wall_time_s = time.perf_counter() - t_wall
    summ.speed_ratio = summ.print_time_s / max(summ.wall_time_s, 1e-9)
    return summ


@dataclass(frozen=True)
class Piece:
    """One part of a file compensated on its own (``--jobs``, :mod:`ffcomp.pipeline.parallel_flow`).

    The piece runs from the first *cut* at or after source line ``lo_line`` (None: the file's start)
    to the first cut at or after ``hi_line`` (None: the file's end).  A cut is a point where the
    planned toolhead stands still: a stop the planner reports (M600, M400, a heater wait, an unknown
    macro: ``planner.on_stop``), or the start of an extruder-only move or dwell that follows a move
    ending at rest (a retraction).  Every piece plans the file from its start, so the pieces find the
    same cuts independently; a compensation stream ends at each cut (``post_s`` of rest) and the next
    begins there (``pre_s`` of rest), as at a stop.
    """

    lo_line: int | None = None
    hi_line: int | None = None


#: a cut within this of a sample time counts as at it (the stream split rule at stops), s
_CUT_EPS_S = 1e-9


def _first_sample_at(t_s: float, fs_hz: float) -> int:
    """Index of the first sample at or after ``t_s`` (the stream split rule of :func:`compensated_stream`)."""
    k = max(int(math.ceil((t_s - _CUT_EPS_S) * fs_hz)), 0)
    while k > 0 and (k - 1) / fs_hz >= t_s - _CUT_EPS_S:
        k -= 1
    while k / fs_hz < t_s - _CUT_EPS_S:
        k += 1
    return k


class _CutFinder:
    """The first cut (see :class:`Piece`) at or after a source line, found as the plan goes by: feed
    it every planned move in order (``check``) and every stop the planner reports (``on_stop``)."""

    def __init__(self, line: int):
        self.line = line
        self.stop: tuple | None = None  # (t, line) of the first stop at or after the line
        self.stops: list[tuple] = []  # every stop reported, (t, line)
        self.v_end = 0.0  # speed at the end of the last XYZ move, mm/s

    def on_stop(self, t_s: float, lineno: int) -> None:
        self.stops.append((t_s, lineno))
        if self.stop is None and lineno >= self.line:
            self.stop = (t_s, lineno, "stop")

    def check(self, mv) -> tuple | None:
        """``(t, line, kind)`` of the cut if it is at the start of ``mv`` (the first move of the next
        piece); kind ``stop`` (a stream ends there anyway) or ``hold`` (a retraction or dwell after a
        move ending at rest: the cut adds a stream end and start there)."""
        if self.stop is not None and mv.t_start_s >= self.stop[0] - _CUT_EPS_S:
            return self.stop
        v = self.v_end
        if mv.kind == MOVE:
            self.v_end = mv.end_v_mm_s
            return None
        if mv.lineno >= self.line and v < 1e-9:
            return (mv.t_start_s, mv.lineno, "hold")
        return None


class _PieceState:
    """Where one piece begins and ends, found while its worker plans the file (see :class:`Piece`)."""

    def __init__(self, piece: Piece):
        self.piece = piece
        self.first = piece.lo_line is None
        self.lo: tuple | None = None  # (t, line) of the cut the piece starts at
        self.hi: tuple | None = None  # (t, line) of the cut it ends at
        self.k_lo = 0
        self.k_hi = 0
        self.empty = False
        self.n_xyz = 0
        self.fs = 1.0
        self._hi = _CutFinder(piece.hi_line) if piece.hi_line is not None else None
        self._skip_check = False  # the piece's first move was checked by the end finder already

    def begin(self, plan, planned, stops: list, fs_hz: float):
        """Skip the moves before the piece's first cut; returns the moves from it on (None: the piece
        is empty).  ``stops`` gets the times of the stops after the cut."""
        self.fs = float(fs_hz)
        hi = self._hi

        def stop_hook(finder):
            def f(t_s, lineno):
                finder.on_stop(t_s, lineno)
                if hi is not None and finder is not hi:
                    hi.on_stop(t_s, lineno)
            return f

        if self.first:
            if hi is not None:
                plan.planner.on_stop = lambda t_s, lineno: (stops.append(t_s), hi.on_stop(t_s, lineno))
            return planned
        lo = _CutFinder(self.piece.lo_line)
        plan.planner.on_stop = stop_hook(lo)
        for mv in planned:
            c = lo.check(mv)
            c_hi = hi.check(mv) if hi is not None else None
            if c is None:
                continue
            self.lo, self.k_lo = c, _first_sample_at(c[0], self.fs)
            if c_hi is not None:  # no cut between the two lines: nothing here
                self.empty = True
                return None
            stops.extend(t for t, _ in lo.stops if t > c[0] + _CUT_EPS_S)
            if hi is not None:
                plan.planner.on_stop = lambda t_s, lineno: (stops.append(t_s), hi.on_stop(t_s, lineno))
            else:
                plan.planner.on_stop = lambda t_s, lineno: stops.append(t_s)
            self._skip_check = True
            return _prepend(mv, planned)
        self.empty = True
        return None

    def ends_at(self, mv) -> bool:
        """Whether ``mv`` is the first move after the piece's last cut."""
        if self._hi is None:
            return False
        if self._skip_check:
            self._skip_check = False
            return False
        c = self._hi.check(mv)
        if c is not None:
            self.hi, self.k_hi = c, _first_sample_at(c[0], self.fs)
            return True
        return False

    def window(self, lines):
        """The piece's own source lines: from its first cut's line to before its last cut's line."""
        for ln in lines:
            if self.lo is None and not self.first:
                return  # an empty piece (the lines are pulled only after its first cut is known)
            if self.lo is not None and ln.lineno < self.lo[1]:
                continue
            if self.hi is not None and ln.lineno >= self.hi[1]:
                return
            yield ln

    def before_finish(self, writer) -> None:
        """The writer may hold the next piece's first line (read ahead before the cut was known)."""
        nl = writer.next_line
        if self.hi is not None and nl is not None and nl.lineno >= self.hi[1]:
            writer.next_line = None
            writer.lines = iter(())
        elif self.lo is None and not self.first:
            writer.next_line = None
            writer.lines = iter(())


def _prepend(first, rest):
    yield first
    yield from rest


def _head(blk, n: int):
    """The first ``n`` samples of a block (None if none)."""
    if n <= 0:
        return None
    if n >= len(blk.t_s):
        return blk
    return replace(blk, t_s=blk.t_s[:n], xyz_m=blk.xyz_m[:n], v_m_s=blk.v_m_s[:n], a_m_s2=blk.a_m_s2[:n],
                   e_mm=blk.e_mm[:n], q_m=blk.q_m[:n], move_index=blk.move_index[:n], lineno=blk.lineno[:n])


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
    plan = GcodePlan(src, profile, lenient=opts.lenient, start_position_mm=start.position_mm,
                     unknown_policy=opts.unknown_policy)
    with _open_existing(body_path, "w") as body, _open_existing(qfile, "wb") as qf, \
            _open_existing(segfile, "wb") as sf:
        lines = iter(parse_gcode(src, lenient=True, dialect=plan.firmware,
                                 home_position_mm=(0.0, 0.0, profile.geometry.z_max_mm),
                                 start_position_mm=start.position_mm, unknown_policy=opts.unknown_policy))
        if cuts is not None:  # the piece's own source lines only (known once its cuts are found)
            lines = cuts.window(lines)
        accel = header_accel(profile, opts)
        chain = ChainLimits(profile, accel, opts.corner_velocity_mm_s) if plan.firmware == "klipper" else None
        writer = GcodeWriter(lines, body, dt, opts.tol_um * 1e-3, moves, accel_mm_s2=accel,
                             max_z_accel_mm_s2=profile.limits.max_z_accel_mm_s2,
                             max_z_velocity_mm_s=profile.limits.max_z_velocity_mm_s, segment_table=sf,
                             chain_limits=chain)
        writer.start_travel_mm_s = start.travel_mm_s if cuts is None or cuts.first else None
        pred = Predictor(model, dt) if opts.predict else None
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
            if opts.z_mode in ("hold", "auto"):
                hold = (z_held if opts.z_mode == "hold" else z_moving)(meta["move_index"], moves)
                xyz[hold, 2] = meta["xyz"][hold, 2]
                fix |= hold
            # moves the firmware's own limits bind (max_z_accel, the extruder's, the rim's slow
            # zones) cannot take a command that accelerates harder than the plan: they follow
            # the plan, sample by sample, so the clock holds (counted in the summary)
            dense = shift = None
            if bound is not None:
                # with the pin repair those moves are pinned (the plan, sample by sample): no blend
                w, wz = bound.weights(meta["move_index"], moves, blend_moves=not opts.pin_repair)
                dense = (w > 0) | (wz > 0)
                if dense.any():
                    xyz[dense] += w[dense, None] * (meta["xyz"][dense] - xyz[dense])
                    xyz[dense, 2] += wz[dense] * (meta["xyz"][dense, 2] - xyz[dense, 2])
                    fix |= dense
                    summ.plan_fallback_samples += int(np.sum(np.maximum(w, wz) >= 1.0))
            if zlim is not None:  # moves max_z_accel binds: every sample a segment (see ZLimited)
                zd, snapped, shift = zlim.dense(meta["move_index"], moves, xyz)
                dense = zd if dense is None else (dense | zd)
                fix |= snapped
            # the firmware refuses positions outside its limits: a correction that pokes past
            # them (at z_max after homing, at the rim) is clamped to the boundary
            cl = _clamp_to_workspace(xyz, geom)
            if cl.any():
                summ.clamped += int(cl.sum())
                fix |= cl
            if fix.any():
                qc = qc.copy()
                qc[fix] = inverse(geom, xyz[fix])
            summ.max_correction_um = max(summ.max_correction_um,
                                         float(np.max(np.abs(qc - meta["q"]))) * 1e6)
            qf.write(qc.astype(np.float32).tobytes())
            new_stream = k_written and np.max(np.abs(qc[0] - last_qc)) > JUMP_M
            if new_stream or not k_written:  # the machine stands where the plan starts the stream
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

            def pinned(mv) -> bool:
                if mv.kind != "move":  # extruder-only move or dwell
                    return True
                return bound is not None and (bound.bound(mv) or (
                    opts.repair.pin_z_after_hold and z_hop(mv) and bound.z_after_hold(mv, moves))
                    or (opts.repair.pin_z_before_hold and z_hop(mv) and bound.z_before_hold(mv, moves)
                        and zlim is not None and zlim.limited(mv)))

            def pins(meta):
                return moves_where(meta["move_index"], moves, pinned)

            steep = (lambda meta: moves_where(meta["move_index"], moves, zlim.limited)) if zlim is not None else None
            stream = pin_repaired(stream, pins, model, dt, opts.repair, pin_stats, jump_m=JUMP_M, steep_fn=steep)
        for qc, meta in stream:
            emit(qc, meta)
        if cuts is not None:
            cuts.before_finish(writer)
        writer.finish()
    if pred is not None:
        pred.flush()
    summ.pin_windows, summ.pinned_samples = pin_stats.windows, pin_stats.pinned_samples
    summ.pin_max_change_um = pin_stats.max_change_m * 1e6
    parser = plan.parser
    return BodyResult(stats=writer.stats, accel=accel, firmware=plan.firmware,
                      parser_warnings=parser.warnings if hasattr(parser, "warnings") else 0,
                      counts=dict(parser.counts), warning_messages=list(parser.warning_messages[:20]),
                      pred_sq=[float(x) for x in pred.sq] if pred is not None else [0.0, 0.0],
                      pred_n=pred.n if pred is not None else 0,
                      pred_mx=[float(x) for x in pred.mx] if pred is not None else [0.0, 0.0],
                      k_written=k_written, streams=writer.stream + 1,
                      n_xyz=cuts.n_xyz if cuts is not None else 0,
                      cut_lo=cuts.lo if cuts is not None else None, cut_hi=cuts.hi if cuts is not None else None,
                      lines_read=parser.lines_read, start_mm=ends[0],
                      end_mm=writer.last_pt.tolist() if writer.last_pt is not None else None)


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


def _count_commands(summ: CompensationSummary, counts: dict) -> None:
    """The parser's per-class command counts into the summary (see :mod:`ffcomp.gcode.commands`)."""
    summ.commands_passed = counts.get("pass", 0)
    summ.commands_baked = counts.get("state", 0)
    summ.commands_stopped = counts.get("stop", 0)
    summ.commands_unknown = counts.get("unknown", 0)
    summ.lines_skipped = counts.get("skipped", 0)


def compensated_stream(plan: GcodePlan, moves: dict, profile, model: LpvModel, icfg: InverseConfig, opts,
                       summ: CompensationSummary, src: str, pstate: _PieceState | None = None):
    """Compensated carriage commands of a planned file, in order, with each sample's reference.

    Yields ``(q_cmd (n, 3), meta)``; ``meta`` holds the reference ``q``, ``xyz`` (m), ``e`` (mm),
    ``move_index`` and ``lineno`` of the same samples.  Planned moves are recorded in ``moves``
    (index -> PlannedMove) as they go by.  A homing (a jump of the carriages) ends one compensation
    stream and starts the next; each stream begins with ``pre_s`` and ends with ``post_s`` of rest,
    which the output keeps (so the command can pre-actuate the first move and settle after the last).
    A stop command (M600, PAUSE, T1, G29, M109, an unknown macro...: the planner brings the toolhead to
    rest there) or a sync (M400, M84) ends a stream the same way, so the command stands still at the
    plan's rest position when the firmware runs it, and the next stream starts from rest after it.  A
    file without XYZ motion is an error (nothing to compensate).

    ``pstate`` (``--jobs``): only the samples of one :class:`Piece` are compensated: the plan runs from
    the file's start (modal state, positions, limits and E stay right) but its moves before the
    piece's first cut are not sampled, and the last stream ends at the next cut as at a stop.
    """
    geom = model.geometry
    dt = 1.0 / profile.limits.sample_rate_hz
    fifo = _Fifo()
    inv = None
    last_q = None
    last_meta = None
    stops: list[float] = []  # print times of stops not yet applied to the stream
    plan.planner.on_stop = lambda t_s, lineno: stops.append(t_s)
    n_xyz = 0
    planned = iter(plan)
    k_start = 0
    if pstate is not None:
        planned = pstate.begin(plan, planned, stops, profile.limits.sample_rate_hz)
        if planned is None:  # an empty piece: its first cut is also its last
            return
        k_start = pstate.k_lo

    def tee():
        nonlocal n_xyz
        for mv in planned:
            if pstate is not None and pstate.ends_at(mv):
                return
            moves[mv.index] = mv
            if mv.kind == "move":
                n_xyz += 1
            yield mv

    def out(qc):
        if len(qc):
            yield qc, fifo.pop(len(qc))

    def push_post(meta):
        n_post = int(round(icfg.post_s / dt))
        qq, xx, ee, mi, ln = meta
        fifo.push(q=np.repeat(qq[None], n_post, 0), xyz=np.repeat(xx[None], n_post, 0),
                  e=np.repeat(ee, n_post), move_index=np.full(n_post, REST_MOVE), lineno=np.repeat(ln, n_post),
                  k=np.full(n_post, -1, np.int64))

    for blk in sample_blocks(tee(), geom, fs_hz=profile.limits.sample_rate_hz, block_len=opts.block_len,
                             overlap=0, path=src, k_start=k_start):
        if pstate is not None and pstate.hi is not None and blk.k0 + len(blk.t_s) > pstate.k_hi:
            blk = _head(blk, pstate.k_hi - blk.k0)  # the next piece starts at the cut
            if blk is None:
                break
        q = blk.q_m
        # homing (or any jump) restarts the compensation stream
        jumps = np.nonzero(max_abs3(np.diff(q, axis=0)) > JUMP_M)[0] + 1
        if last_q is not None and np.max(np.abs(q[0] - last_q)) > JUMP_M:
            jumps = np.concatenate([[0], jumps])
        # stops: the stream ends where the plan comes to rest (the first sample at or after the stop)
        t_end = blk.t_s[-1]
        here = [t for t in stops if t <= t_end]
        stops[:] = [t for t in stops if t > t_end]
        at_stop = np.unique(np.searchsorted(blk.t_s, np.asarray(here, float) - 1e-9)) if here else np.zeros(0, int)
        cuts = np.union1d(jumps, at_stop).astype(int)
        for pc in np.split(np.arange(len(q)), cuts):
            if len(pc) == 0:
                continue
            if inv is not None and pc[0] in cuts:
                push_post(last_meta)
                yield from out(inv.finish())
                inv = None
                if pc[0] in jumps:
                    summ.restarts += 1
            sl = slice(pc[0], pc[-1] + 1)
            if inv is None:
                inv = StreamingInverse(model, dt, icfg, keep_padding=True)
                k = pc[0]
                n_pre = inv_pre_samples(icfg, dt)
                fifo.push(q=np.repeat(q[k:k + 1], n_pre, 0), xyz=np.repeat(blk.xyz_m[k:k + 1], n_pre, 0),
                          e=np.repeat(blk.e_mm[k:k + 1], n_pre), move_index=np.full(n_pre, REST_MOVE),
                          lineno=np.repeat(blk.lineno[k:k + 1], n_pre), k=np.full(n_pre, -1, np.int64))
            last_meta = (q[pc[-1]], blk.xyz_m[pc[-1]], blk.e_mm[pc[-1]], blk.move_index[pc[-1]], blk.lineno[pc[-1]])
            fifo.push(q=q[sl], xyz=blk.xyz_m[sl], e=blk.e_mm[sl], move_index=blk.move_index[sl],
                      lineno=blk.lineno[sl], k=blk.k0 + np.arange(sl.start, sl.stop, dtype=np.int64))
            # the planner's exact rates only where the inverse uses them (by default it takes the
            # derivatives of the samples themselves)
            qd, qdd = (carriage_rates(geom, blk.xyz_m[sl], blk.v_m_s[sl], blk.a_m_s2[sl])
                       if icfg.derivatives == "given" else (None, None))
            hold = holds(blk.move_index[sl], moves) if opts.pin_holds else None
            yield from out(inv.push(q[sl], blk.xyz_m[sl], qd, qdd, hold))
        last_q = q[-1].copy()
        summ.print_time_s = float(blk.t_s[-1])
    if inv is not None:
        push_post(last_meta)
        yield from out(inv.finish())
    if pstate is not None:
        pstate.n_xyz = n_xyz
        return
    if n_xyz == 0:
        raise GcodeError(src, plan.parser.lines_read, "the file has no XYZ motion (empty, comments only, or no "
                         "moves): nothing to compensate")


def inverse_config(profile, opts: CompensateOptions) -> InverseConfig:
    """The inverse settings of a run: the options' plus the command bounds from the profile (and,
    for Klipper, its ``max_z_accel``: the firmware caps the z acceleration of every segment there)."""
    lim = profile.limits
    bounds = opts.inverse.bounds or (lim.max_correction_mm * 1e-3, lim.max_carriage_velocity_mm_s * 1e-3,
                                     lim.max_carriage_accel_mm_s2 * 1e-3)
    zb = opts.inverse.z_accel_bound
    if zb is None and lim.planner == "klipper":
        zb = lim.max_z_accel_mm_s2 * 1e-3
    return InverseConfig(**{**asdict(opts.inverse), "method": opts.method, "bounds": bounds, "z_accel_bound": zb})


def inv_pre_samples(icfg: InverseConfig, dt: float) -> int:
    """Rest samples the streaming inverse puts before a stream."""
    from ..compensate.inverse import _round_to

    return _round_to(int(round(icfg.pre_s / dt)), icfg.knot_samples)


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


class _Fifo:
    """Per-sample metadata waiting for its compensated command."""

    def __init__(self):
        self.parts: dict[str, list[np.ndarray]] = {}

    def push(self, **cols):
        for k, v in cols.items():
            self.parts.setdefault(k, []).append(np.asarray(v))

    def pop(self, n: int) -> dict[str, np.ndarray]:
        out = {}
        for k, lst in self.parts.items():
            arr = np.concatenate(lst) if len(lst) > 1 else lst[0]
            out[k], rest = arr[:n], arr[n:]
            self.parts[k] = [rest]
        return out
