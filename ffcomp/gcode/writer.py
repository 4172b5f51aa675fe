"""Compensated G-code writer.

Input: the source file's lines (re-parsed, so every line keeps its number and meaning) and, in
time order, compensated samples with the reference's extruder position and the planned move each
sample belongs to.  Output: the source with every XYZ motion line replaced by G1 segments through
the compensated nozzle positions, and every other line kept in place.

* Points are placed adaptively: a segment ends where linear interpolation *in time* (the firmware
  moves a segment at constant speed) would stray from the compensated samples by more than
  ``tol_mm``.  The points chosen between forced ones (run ends, catch-ups, samples written one by
  one) then take the values of the least-squares time-linear fit of the samples
  (:mod:`ffcomp.gcode.knot_fit`): the same lines, a command about 2.5 times closer in RMS.
* Timing on the absolute clock: with Klipper, the feed rates come from a closed-loop solve
  (:mod:`ffcomp.gcode.feed_solve`) against Klipper's own plan of the written chain (junction
  speeds, ramps, ``max_z_accel * d/|dz|``, the extruder's limits), so every segment ends when its
  sample is due, and lateness a limit forces (a catch-up after a hold) is taken back by the
  segments after it instead of adding up over the file.  Extruder-only moves and dwells count
  with their exact durations; a hold (a segment under a micrometre) leaves the nozzle where it
  was and a ``G4`` gives back lateness.  (Marlin: a per-segment feed solve.)
* Extrusion follows the reference timing: each segment extrudes ``e_ref(t_end) - e_ref(t_start)``
  (relative extrusion, rounding carried over), so material is laid when the original lays it.
* Lines whose meaning the compensation has baked in are commented out with ``; ffcomp:``:
  coordinate and extrusion modes (the output is G90 + M83 throughout), G92 and gcode offsets (the
  output is in machine coordinates), speed and flow factors, and motion-limit commands (the header
  sets the limits the compensated file needs).
* Extruder-only moves become ``G1 E.. F..`` with the planned speed; dwells, homing, temperatures,
  fans, comments and object labels pass through verbatim (byte for byte: the caller opens ``out``
  with ``errors="surrogateescape"``, as the parser reads).  Lines a lenient parse skipped are kept as
  ``; ffcomp (skipped):`` comments.
* The body carries :data:`~ffcomp.gcode.signature.SIGNATURE_LINE` before its first segment and then
  at the first run of segments after every :data:`~ffcomp.gcode.signature.SIGNATURE_EVERY_LINES`
  lines, so a compensated file is recognised even without its header.
* ``start_travel_mm_s`` set: the first motion is an ordinary travel to the first compensated point at
  that speed (the toolhead's position before an un-homed file is not known to the firmware's plan).
"""

from __future__ import annotations

from typing import IO, Iterator, NamedTuple

import numpy as np

from ..linalg3 import max_abs3
from .breakpoints import breakpoints_runs
from .chain_plan import ChainLimits, corner_v2, segment_limits
from .extrusion import EDGE_SHARE, by_length, extruder_capped, flow_groups, place_ratio_steps  # noqa: F401 (EDGE_SHARE: re-exported)
from .feed_solve import TimingState, extrude_only_feed, extrude_only_time, solve_feeds
from .holds import (
    merged_ramp_holds,
    merged_rest_holds,
    merged_start_holds,
    merged_wet_holds,
    settle_holds,
    unrunnable_rests,
)
from .knot_fit import fit_knots
from .moves import EXTRUDE, FIRMWARE, MOVE, PlannedMove
from .passthrough import passthrough_lines
from .plan_clock import (
    CORNER_LEAD_MAX_SAMPLES,
    FREE_CORNER_STRAIGHT_COS,
    REST_POINT_NEAR_MM,
    corner_lead,
    corner_lead_free,
    corner_tail,
    free_corner,
    plan_speeds,
    rest_end,
    rest_start,
    sampled_corners_ok,
)
from .records import FirmwareMove, GcodeLine
from .segment_lines import SEG_COLS, format_segments
from .signature import SIGNATURE_EVERY_LINES, SIGNATURE_LINE
from .writer_stats import WriterStats, add_segments

__all__ = ["GcodeWriter"]

#: an extruder-only move is written up to this much faster than planned (s), for the catch-up after it
EXTRUDE_SPARE_S = 3e-3

def _plan_corner_v(moves: list, srun: np.ndarray, first_seg: np.ndarray, start_pt: np.ndarray) -> np.ndarray:
    """The plan's speed (mm/s) at the start of each written segment that starts a run on its plan
    move's start point (the plan's corner, as the writer placed it: printed to 0.1 um) and follows
    the plan from there (``first_seg``: those segments' end on the plan), NaN elsewhere (see
    :func:`~ffcomp.gcode.extrusion.by_length`'s ``plan_v_mm_s``).  A free command may pass the
    corner faster than the plan (a correction's velocity of 10 mm/s at a retracting lift's end):
    there the ramp of ratios lets it through."""
    out = np.full(len(srun), np.nan)
    qs = np.nonzero(first_seg)[0]
    ok = [(q, moves[int(srun[q])]) for q in qs.tolist()]
    ok = [(q, mv) for q, mv in ok if mv is not None and mv.kind == MOVE]
    if not ok:
        return out
    q = np.array([q for q, _ in ok])
    st = np.round(np.array([mv.start_mm[:3] for _, mv in ok], float), 4)
    near = np.linalg.norm(start_pt[q] - st, axis=1) < 1e-3
    out[q[near]] = [mv.start_v_mm_s for (_, mv), n in zip(ok, near.tolist()) if n]
    return out


class GcodeWriter:
    """Streams the compensated body of a G-code file.

    Parameters
    ----------
    lines : iterator of GcodeLine
        The source, parsed (every line, in order).
    out : text file
        Where the body goes.
    dt_s : float
        Sample time of the compensated samples.
    tol_mm : float
        Point placement tolerance.
    moves : dict
        ``move index -> PlannedMove`` (filled by the planner as it goes; entries are dropped here).
    """

    def __init__(self, lines: Iterator[GcodeLine], out: IO[str], dt_s: float, tol_mm: float,
                 moves: dict[int, PlannedMove], accel_mm_s2: float = float("inf"),
                 max_z_accel_mm_s2: float = float("inf"), max_z_velocity_mm_s: float = float("inf"),
                 segment_table: IO[bytes] | None = None, chain_limits: ChainLimits | None = None,
                 fit_points: bool = True):
        self.lines, self.out, self.dt, self.tol = lines, out, dt_s, tol_mm
        self.accel, self.max_z_accel, self.max_z_v = accel_mm_s2, max_z_accel_mm_s2, max_z_velocity_mm_s
        self.f_last = 0.0  # feed rate (mm/s) of the last segment written: the next junction speed
        #: keep the extruder limits of the source's limit commands in force (Marlin's M204 R, M201 E,
        #: M203 E: the plan was timed with them) while the rest is baked in
        self.extruder_limits = False
        self.moves = moves
        self.stats = WriterStats()
        self.next_line: GcodeLine | None = None
        self.emitted_upto = 0  # source lines with lineno <= this are written
        self.last_pt: np.ndarray | None = None  # last emitted nozzle point (mm)
        self.last_k = None  # sample index of it
        self.e_emitted = 0.0  # extrusion written so far (relative sum), mm
        self.e_ref_cum = 0.0  # reference extrusion accounted for so far, mm
        self.e_last_ref = None  # reference extruder position at the last emitted point
        self.replaced: set[int] = set()  # source line numbers written as motion (not yet flushed past)
        self.n_replaced = 0  # source line numbers written as motion and forgotten
        self.done_moves: set[int] = set()  # planned move indices written
        #: (velocity mm/s, vector mm, duration s) of the last moving segment written (its statistics)
        self.prev_seg: tuple | None = None
        self.after_hold = False
        self.at_rest_end = False  # the last motion run ended on the plan's rest point (rest_end)
        #: (extrusion ratio, length mm, intended speed mm/s) of the last segment written where the
        #: firmware goes on from it at speed into the next chunk's first; None where it stops there
        self.ratio_prev: tuple[float, float, float] | None = None
        #: write extruder-only moves up to EXTRUDE_SPARE_S faster (the command moved on during them)
        self.fast_extrude = True
        self.nlines = 0  # body lines written
        #: (body line number, first sample, last sample, catch-up flag) of every XYZ segment, for the
        #: self-check: int64 rows written to ``segment_table`` (a binary file, so memory stays
        #: bounded); not recorded without one
        self.segment_table = segment_table
        self.stream = -1  # compensation stream of the samples being written (a homing starts one)
        #: where the firmware stands when the next stream starts (the plan's point: after a homing,
        #: the home position), mm; None: the stream's first sample
        self.stream_start_mm: np.ndarray | None = None
        #: the point the current stream's first segment starts from (mm)
        self.stream_lead_mm: np.ndarray | None = None
        #: Klipper's limits for the closed-loop feed solve (None: the per-segment solve, for Marlin)
        self.chain = chain_limits
        self.timing = TimingState()
        self.pend_late_s = 0.0  # lateness of extruder-only moves and dwells not yet absorbed
        #: the samples of a chunk's last run held back for the next chunk (see :meth:`feed`)
        self._carry: tuple | None = None
        self._write = out.write
        self._next_sig = 0  # body line at or after which the next signature line is due
        #: speed of the travel to the first point (None: no travel; see the module docstring), mm/s
        self.start_travel_mm_s: float | None = None
        #: the points placed between forced ones take the least-squares values of the samples they
        #: stand for (:mod:`ffcomp.gcode.knot_fit`) instead of the samples' own
        self.fit_points = fit_points
        self.free_corners = True  # end runs on free corners of the plan (plan_clock.free_corner)
        #: each change of extrusion ratio written on the junction where the firmware loses least
        #: (:func:`~ffcomp.gcode.extrusion.place_ratio_steps`; Klipper's feed solve only)
        self.place_steps = True

    def _w(self, text: str) -> None:
        self._write(text)
        self.nlines += 1

    # ------------------------------------------------------------------ source lines
    def _line_iter_next(self) -> GcodeLine | None:
        if self.next_line is None:
            self.next_line = next(self.lines, None)
        return self.next_line

    def flush_lines(self, upto: int) -> None:
        """Write the source lines numbered < ``upto`` that are not motion lines."""
        w = self._w
        while True:
            ln = self._line_iter_next()
            if ln is None or ln.lineno >= upto:
                return
            self.next_line = None
            for text in passthrough_lines(ln, self.replaced, self.extruder_limits, self.stats):
                w(text)

    # ------------------------------------------------------------------ samples
    def feed(self, k0: int, xyz_mm: np.ndarray, e_mm: np.ndarray, move_index: np.ndarray,
             lineno: np.ndarray, dense: np.ndarray | None = None, k_plan: np.ndarray | None = None,
             plan_mm: np.ndarray | None = None, t_shift: np.ndarray | None = None) -> None:
        """Compensated nozzle positions of samples ``k0 ..`` with their reference extrusion and move.

        ``dense`` marks samples that each end a segment of their own (no point placement).
        ``k_plan``: each sample's index on the plan's grid (print time ``k_plan dt``; -1 for the rest
        samples a stream adds) and ``plan_mm`` the plan's nozzle positions (n, 3): with them, where the
        command follows the plan, a run whose move comes to rest between samples ends on the plan's
        rest point at the plan's time and one that leaves rest starts on time
        (:mod:`ffcomp.gcode.plan_clock`).
        ``t_shift``: where a point is due off its sample's time (a turning point), samples.

        The chunk is cut into runs of one planned move.  The numbers of every motion run (point
        placement, extrusion, feed rates) are computed for the whole chunk at once
        (:meth:`_plan_chunk`); the lines are then written run by run, in place among the source's
        other lines.
        """
        args = (k0, xyz_mm, e_mm, move_index, lineno, dense, k_plan, plan_mm, t_shift)
        if self._carry is not None:
            args, self._carry = _joined(self._carry, args), None
        cut = self._carry_from(args)
        if cut < len(args[3]):
            self._carry = (args[0] + cut,) + tuple(None if x is None else x[cut:] for x in args[1:])
            args = (args[0],) + tuple(None if x is None else x[:cut] for x in args[1:])
        self._feed(*args)

    def _carry_from(self, args: tuple) -> int:
        """Index of the first sample of a chunk (``args``: :meth:`feed`'s) held back for the next
        one; the chunk's length when none is.

        * A run that starts within the chunk's last :data:`CARRY_SAMPLES` samples waits, with the
          run before's last sample: how it leaves a corner (``plan_clock.corner_lead``) depends on
          the samples after it (a layer change's lift that began 2 samples before a chunk's end
          kept a 1.4 um first segment: 0.42 ms late), and how the run before ends
          (``plan_clock.rest_end``) on the first sample after that.
        * Where none does but the move of the chunk's last sample turns into the next move within
          :data:`CARRY_SAMPLES` samples after it, the last :data:`CARRY_SAMPLES` samples wait (the
          rule above again at the new cut): the corner is written in one chunk (a user's tower
          on other_delta, cut right at a layer change's lift: -0.28 ms, now on time).
        * Where the last run starts within :data:`CARRY_FREE_SAMPLES` samples of the cut on a turn
          of the plan at speed that the command does not follow (``plan_clock.free_corner``'s
          kind) or on a change of extrusion ratio at speed (:meth:`_turn_ahead`), that run and the
          last :data:`CARRY_TAIL_SAMPLES` samples of the run before wait: the free corner drops up
          to ``CORNER_LEAD_MAX_SAMPLES`` samples either side of it (with one sample of the run
          before it had none to drop: +1.0 ms on a random file on other_delta), and the ratio's
          ramp (``extrusion.limit_ratio_steps``) is written in one chunk (cut 11 samples into a
          retraction's ramp, the first chunk ended on a feed the lift never made up: +0.56 ms).
        * Where the cut so far falls within :data:`CARRY_TAIL_SAMPLES` samples before a corner of the
          plan that the command follows (a pinned lift into its travel), or before a turn it does
          not follow or a change of ratio, that many more samples wait, so that
          ``plan_clock.corner_tail`` or ``plan_clock.free_corner`` sees the move's end whole (the
          first rule again at the new cut, and this rule again up to :data:`CARRY_TAIL_PASSES`
          times in all).
        * Where the plan then comes to rest within :data:`CARRY_REST_SAMPLES` samples after the last
          sample written, that many more samples wait, so that the segments before the stop are
          timed knowing it (and the rule above holds at the new cut).
        """
        mi = args[3]
        n = len(mi)
        cut = _run_start_cut(mi, n)
        first = _last_run_start(mi, cut)
        if 0 < first < cut and cut - first < CARRY_FREE_SAMPLES and self._turn_ahead(args, first - 1, 1):
            cut = _run_start_cut(mi, max(first - CARRY_TAIL_SAMPLES, 0))
        if cut == n and n > CARRY_SAMPLES and self._corner_ahead(args, n - 1):
            cut = _run_start_cut(mi, n - CARRY_SAMPLES)
        for _ in range(CARRY_TAIL_PASSES):  # (the new cut may fall before the corner before)
            if not (0 < cut and self._tail_ahead(args, cut - 1)):
                break
            cut = _run_start_cut(mi, max(cut - CARRY_TAIL_SAMPLES, 0))
        if cut > 0 and self._rest_ahead(args, cut - 1):
            cut = max(cut - CARRY_REST_SAMPLES, 0)
            if cut > 0 and mi[cut] != mi[cut - 1]:
                cut -= 1  # (not right after a run's last sample: see rest_end above)
            cut = _run_start_cut(mi, cut)
        return cut

    def _planned_at(self, args: tuple, i: int) -> tuple:
        """``(move, k)``: the planned move of sample ``i`` of a chunk (``args``: :meth:`feed`'s) and
        the sample's index on the plan's grid; ``(None, -1)`` for a sample the plan does not have
        (a stream's added rest) or a move no longer held."""
        k_plan = args[6]
        if k_plan is None or k_plan[i] < 0:
            return None, -1
        return self.moves.get(int(args[3][i])), int(k_plan[i])

    def _corner_ahead(self, args: tuple, i: int, samples: int | None = None) -> bool:
        """Whether sample ``i`` of a chunk (``args``: :meth:`feed`'s) is in a planned move that ends in
        motion, into another move, within ``samples`` (default :data:`CARRY_SAMPLES`) samples after it."""
        samples = CARRY_SAMPLES if samples is None else samples
        mv, k = self._planned_at(args, i)
        if mv is None or mv.kind != MOVE or mv.end_v_mm_s <= REST_V_MM_S:
            return False
        nxt = self.moves.get(mv.index + 1)
        return nxt is not None and nxt.kind == MOVE and mv.t_end_s < (k + samples) * self.dt

    def _tail_ahead(self, args: tuple, i: int) -> bool:
        """Whether sample ``i`` of a chunk (``args``: :meth:`feed`'s) follows the plan (within
        :data:`ON_PLAN_MM`) in a planned move that ends in motion, into another move, within
        :data:`CARRY_TAIL_SAMPLES` samples after it: a cut there would leave
        :func:`~ffcomp.gcode.plan_clock.corner_tail` too few of the move's last samples to lengthen
        the segment into the corner.  Off the plan, whether such a corner is one
        :meth:`_turn_ahead` names (a turn for ``plan_clock.free_corner``, or a change of ratio)."""
        if args[7] is None:
            return False
        if _on_plan(args, i):
            return self._corner_ahead(args, i, CARRY_TAIL_SAMPLES + 1)
        return self._turn_ahead(args, i, CARRY_TAIL_SAMPLES + 1)

    def _turn_ahead(self, args: tuple, i: int, samples: int) -> bool:
        """Whether sample ``i`` of a chunk (``args``: :meth:`feed`'s) is in a planned move that ends in
        motion, into another move, within ``samples`` samples after it, with a change of
        extrusion ratio there, or with a turn while the sample is off the plan (by
        :data:`ON_PLAN_MM` or more): a corner :func:`~ffcomp.gcode.plan_clock.free_corner` may
        take."""
        if args[7] is None or not self._corner_ahead(args, i, samples):
            return False
        mv, _ = self._planned_at(args, i)
        nxt = self.moves[mv.index + 1]
        if abs(mv.unit[3] - nxt.unit[3]) > 1e-9:
            return True
        if _on_plan(args, i):
            return False
        return sum(a * b for a, b in zip(mv.unit[:3], nxt.unit[:3])) <= FREE_CORNER_STRAIGHT_COS

    def _rest_ahead(self, args: tuple, i: int) -> bool:
        """Whether the plan comes to rest within :data:`CARRY_REST_SAMPLES` samples after sample
        ``i`` of a chunk (``args``: :meth:`feed`'s), while that sample's move moves."""
        mv, k = self._planned_at(args, i)
        horizon_s = (k + CARRY_REST_SAMPLES) * self.dt
        while mv is not None and mv.kind == MOVE and mv.t_start_s < horizon_s:
            if mv.end_v_mm_s <= REST_V_MM_S:
                return mv.t_end_s < horizon_s
            mv = self.moves.get(mv.index + 1)
        return False

    def flush_samples(self) -> None:
        """Write the samples :meth:`feed` holds back (before a new stream starts, and at the end)."""
        if self._carry is not None:
            args, self._carry = self._carry, None
            self._feed(*args)

    def _feed(self, k0: int, xyz_mm: np.ndarray, e_mm: np.ndarray, move_index: np.ndarray,
              lineno: np.ndarray, dense: np.ndarray | None = None, k_plan: np.ndarray | None = None,
              plan_mm: np.ndarray | None = None, t_shift: np.ndarray | None = None) -> None:
        n = len(xyz_mm)
        if n == 0:
            return
        if self.last_pt is None:  # a new stream (the start, or after a homing)
            start = self.stream_start_mm if self.stream_start_mm is not None else xyz_mm[0]
            self.last_pt, self.last_k, self.e_last_ref = np.array(start, float), k0, float(e_mm[0])
            self.stream_lead_mm = self.last_pt.copy()
            self.stream_start_mm = None
            self.stream += 1
            self.at_rest_end = False
            self.ratio_prev = None
        cut = np.nonzero(np.diff(move_index))[0] + 1
        starts = np.concatenate([[0], cut]).tolist()
        ends = np.concatenate([cut, [n]]).tolist()
        mis = move_index[starts].tolist()
        lns = lineno[starts].tolist()
        runs = []
        for a, b, mi, ln in zip(starts, ends, mis, lns):
            mv = self.moves.get(mi)
            runs.append(_Run(a, b, mi, mv, mv.kind if mv is not None else MOVE, ln))
        on_plan = None
        if k_plan is not None and plan_mm is not None:
            on_plan = max_abs3(xyz_mm - plan_mm) < ON_PLAN_MM
        chunk = self._plan_chunk(k0, xyz_mm, e_mm, runs, dense, k_plan, on_plan, t_shift)
        seg_base = []
        for r, run in enumerate(runs):
            mv, kind, ln = run.move, run.kind, run.lineno
            if self.nlines >= self._next_sig:
                self._w(SIGNATURE_LINE)
                self._next_sig = self.nlines + SIGNATURE_EVERY_LINES
            self.flush_lines(ln)
            if self.start_travel_mm_s is not None:
                # (to the point the stream's first segment starts from: the command's first sample
                # may lie 0.1 um off it, which made a z-only first segment an XY move to Klipper, rid
                # of the extruder's acceleration cap the feed solve counted on: 0.2 ms early)
                self._start_travel(self.stream_lead_mm)
            if kind == MOVE:
                s0, s1 = chunk.run_lines[r]
                # the firmware stands still (the plan leaves rest later), or stops on the rest point
                if chunk.run_wait[r] > 0 or chunk.run_stop[r]:
                    self._w(f"G4 P{chunk.run_wait[r] * 1000:.3f}\n")
                if s1 > s0:
                    seg_base.append((r, self.nlines))
                    self._write("".join(chunk.lines[s0:s1]))
                    self.nlines += s1 - s0
            elif mv.index not in self.done_moves:
                if kind == EXTRUDE:
                    speed = chunk.extrude_v[r] or max(mv.cruise_v_mm_s, 1e-3)
                    self._w(f"G1 E{chunk.extrude_de[r]:.5f} F{speed * 60:.3f}\n")
                    self.stats.extrude_moves += 1
                elif kind == FIRMWARE:  # G10/G11: the firmware makes the move of its own line
                    self._firmware_line(ln)
                else:
                    self._dwell(mv, ln)
            if mv is not None:
                self.done_moves.add(mv.index)
            self.replaced.add(ln)
        self.n_replaced += len(self.replaced)
        self.stats.motion_lines_replaced = self.n_replaced
        # lines before the next source line to write are settled: forget them (bounded memory)
        nxt = self.next_line.lineno if self.next_line is not None else runs[-1].lineno
        keep = {k for k in self.replaced if k >= nxt}
        self.n_replaced -= len(keep)
        self.replaced = keep
        last_mi = runs[-1].move_index
        for old in [k for k in self.moves if k < last_mi - 2]:
            del self.moves[old]
        if len(self.done_moves) > 64:
            self.done_moves = {k for k in self.done_moves if k >= last_mi - 2}
        # the self-check's table: body line, first and last sample, catch-up flag of every segment
        if self.segment_table is not None and seg_base and len(chunk.seg_rows):
            base = np.zeros(len(runs), np.int64)
            for r, n0 in seg_base:
                base[r] = n0
            rows = chunk.seg_rows.copy()
            rows[:, 0] += base[chunk.seg_run]
            self.segment_table.write(rows.tobytes())

    def _plan_chunk(self, k0: int, X: np.ndarray, E: np.ndarray, runs: list,
                    dense: np.ndarray | None = None, k_plan: np.ndarray | None = None,
                    on_plan: np.ndarray | None = None, t_shift: np.ndarray | None = None) -> "_Chunk":
        """Points, extrusion and feed rates of every motion run of a chunk, vectorised over runs.

        Each motion run's path starts at the last emitted point; after an extruder-only move or a
        dwell (the planned nozzle stood still while the command moved on) the run's first segment
        catches up in one sample's time instead of stretching the next segment.  Updates the
        writer's running state (last point, extrusion totals, feed rate, statistics) as if the runs
        had been written one after the other.
        """
        R = len(runs)
        ch = _Chunk(R)
        lead_pt, lead_k, lead_e, catch, run_ids, a_s, n_s = [], [], [], [], [], [], []
        leads = []  # per motion run: its first point moved out of the plan's corner (plan_clock.corner_lead)
        tails = []  # per motion run: its last samples dropped before the plan's corner (plan_clock.corner_tail)
        run_ends = []  # per motion run: (point mm, time / dt, e mm, appended) or None (plan_clock.rest_end)
        went = []  # per motion run: it leaves rest on the plan's time (see plan_clock.rest_start)
        rest_go = []  # per motion run: it leaves at once from the plan's rest point the run before ended on
        at_rest_end = self.at_rest_end  # the last run ended on the plan's rest point (plan_clock.rest_end)
        last_pt, last_k, e_last, after_hold = self.last_pt, self.last_k, self.e_last_ref, self.after_hold
        ext_de = np.zeros(R)  # reference extrusion of the extruder-only moves written in this chunk
        ext_runs = []
        follows_hold = np.zeros(R, bool)
        free_lead = 0  # the next run's first samples a free corner drops (plan_clock.free_corner)
        look = self._corners_to_look_at(X, runs)
        # an extruder-only move or dwell lasts its planned time, which starts and ends between
        # samples: the difference from the samples it spans is lateness the next segment must absorb
        pend, run_pre = self.pend_late_s, np.zeros(R)
        end_pts = np.round(X[[run.end - 1 for run in runs]], 4)  # each run's last sample, as written
        for r, (a, b, _, mv, kind, _) in enumerate(runs):
            if kind != MOVE and mv is not None:
                first = mv.index not in self.done_moves
                dur = mv.duration_s
                if first and kind == EXTRUDE and self.chain is not None and self.fast_extrude:
                    dur = self._fast_extrude(ch, r, mv)
                pend += (dur if first else 0.0) - (k0 + b - 1 - last_k) * self.dt
            if kind == MOVE:
                # a move that starts from rest between two samples starts on the plan's time
                k_go = rest_start(self.dt, k0, a, mv, k_plan, on_plan, last_pt, last_k)
                went.append(k_go != last_k)
                rest_go.append(k_go == last_k and at_rest_end and (mv is None or mv.start_v_mm_s <= 1e-9))
                run_pre[r], pend = pend - (k_go - last_k) * self.dt, 0.0
                if free_lead:  # the previous run ended on a free corner (plan_clock.free_corner)
                    leads.append((free_lead, None, None))
                else:
                    leads.append(self._corner_lead(k0, a, b, X, mv, k_plan, on_plan, last_pt)
                                 if self.chain is not None and mv is not None else None)
                free_lead = 0
                run_ids.append(r)
                a_s.append(a)
                n_s.append(b - a + 1)
                lead_pt.append(last_pt)
                lead_k.append(k_go)
                lead_e.append(e_last)
                catch.append(after_hold and b - a + 1 > 2)
                follows_hold[r] = after_hold
                last_pt, after_hold = end_pts[r], False
                end = rest_end(self.dt, k0, b, X, mv, k_plan, on_plan,
                               self.moves.get(mv.index + 1) if mv is not None else None)
                free = None
                if end is None and r in look:
                    free = self._free_corner(k0, a, b, runs[r + 1], X, mv, k_plan, on_plan)
                if free is not None:
                    end, n_tail, free_lead = free
                    run_ends.append(end)
                    tails.append((n_tail, None, None) if n_tail else None)
                else:
                    run_ends.append(end)
                    tails.append(self._corner_tail(k0, a, b, X, mv, on_plan, end) if self.chain is not None else None)
                at_rest_end = end is not None
                if end is not None:  # the run ends where and when the plan comes to rest
                    last_pt = np.round(end[0], 4)
                    n_s[-1] += end[3]
            else:
                at_rest_end = False
                if (kind == EXTRUDE or kind == FIRMWARE) and mv.index not in self.done_moves:
                    ext_de[r] = mv.end_mm[3] - mv.start_mm[3]
                    ext_runs.append(r)
                after_hold = True
            last_k, e_last = k0 + b - 1 + (float(t_shift[b - 1]) if t_shift is not None else 0.0), float(E[b - 1])
            if kind == MOVE and run_ends[-1] is not None:
                last_k, e_last = run_ends[-1][1], run_ends[-1][2]
            elif kind != MOVE and mv is not None:
                # written whole (its planned extrusion): the next segment extrudes from its end, not
                # from the last sample's (which a retraction ending between samples has not reached)
                e_last = float(mv.end_mm[3])
        self.after_hold = after_hold
        self.at_rest_end = at_rest_end
        self.pend_late_s = pend
        self.last_k, self.e_last_ref = last_k, e_last
        ratio_prev, self.ratio_prev = self.ratio_prev, None
        if not run_ids:
            self._extrusion(ch, np.zeros(0), np.zeros(0, np.int64), ext_de, ext_runs)
            self.f_last = 0.0  # the firmware stops for extruder-only moves and dwells
            return ch
        run_ids, n_s, a_s, catch = np.array(run_ids), np.array(n_s), np.array(a_s), np.array(catch)
        offs = np.cumsum(n_s) - n_s
        total = int(n_s.sum())
        src = np.repeat(a_s - 1 - offs, n_s) + np.arange(total)  # sample of each path point
        src = np.clip(src, 0, len(X) - 1)
        P = X[src]
        P[offs] = np.array(lead_pt)
        Ef = E[src]
        Ef[offs] = lead_e
        K = (k0 + src).astype(float)  # time of each point / dt (a rest end falls between samples)
        if t_shift is not None:
            K += t_shift[src]
        K[offs] = lead_k
        last = offs + n_s - 1
        ends = [(m_, e) for m_, e in enumerate(run_ends) if e is not None]
        if ends:  # (appended after the run's last sample, or in its place)
            at = last[[m_ for m_, _ in ends]]
            P[at] = np.array([e[0] for _, e in ends])
            K[at] = [e[1] for _, e in ends]
            Ef[at] = [e[2] for _, e in ends]
        dropped = []  # points a run's corner lead and tail drop (plan_clock.corner_lead, corner_tail)
        tail_pts = []  # points a run's corner tail moved (written)
        for m_, tail in enumerate(tails):
            if tail is not None:
                n_tail, pt, k_pt = tail
                at_ = last[m_] - 1  # the slot of the run's last sample before the corner point
                lo_ = at_ - n_tail + 1
                if leads[m_] is not None and offs[m_] + 2 + leads[m_][0] >= lo_:
                    continue  # a short run that both leaves and enters a corner: its lead alone
                if pt is not None:  # the first of them moved to the point, the rest dropped
                    P[lo_], K[lo_] = pt, k_pt
                    tail_pts.append(lo_)
                    lo_ += 1
                dropped.extend(range(lo_, at_ + 1))
        for m_, lead in enumerate(leads):
            if lead is not None:
                n_drop, pt, k_pt = lead
                dropped.extend(range(offs[m_] + 1, offs[m_] + 1 + n_drop))
                if pt is not None:
                    P[offs[m_] + 1 + n_drop], K[offs[m_] + 1 + n_drop] = pt, k_pt
        # ---- point placement, all runs at once
        keep = np.zeros(total, bool)
        keep[offs] = keep[last] = True
        keep[offs[catch] + 1] = True
        if ends:  # the point before a rest end keeps its own value and time
            keep[at - 1] = True
        keep[tail_pts] = True
        if dense is not None:  # samples written one by one (the plan where limits bind: on its clock)
            keep |= dense[src]
        forced = keep.copy()
        keep = breakpoints_runs(P, np.where(catch, offs + 1, offs), last, self.tol, keep)
        # a first sample within a micrometre of the run's lead point (leaving rest on time, or
        # just past a corner the previous run ended on) would be a hold: a stop of the firmware,
        # and the segment after it would start from rest a sample late: it is not a point
        w_ = np.nonzero(n_s > 2)[0]
        if w_.size:
            o = offs[w_]
            near = np.linalg.norm(np.round(P[o + 1], 4) - np.round(P[o], 4), axis=1) < 1e-3
            keep[o[near] + 1] = False
        if dropped:
            keep[dropped] = False
        kidx = np.nonzero(keep)[0]
        if self.fit_points:  # the chosen points' values: the best time-linear fit of the samples
            # (not on moves with z travel, where max_z_accel * d/|dz| binds the firmware: there the
            # fit's shifted points moved the re-planned timing, by up to 0.75 ms on cube_prusa with
            # max_z_accel = 3000, for no gain)
            zrun = np.array([r.move is not None and abs(r.move.end_mm[2] - r.move.start_mm[2]) > 1e-9
                             for r in (runs[q] for q in run_ids)])
            fx = forced | np.repeat(zrun, n_s)
            P[kidx] = fit_knots(P, kidx, fx[kidx], max_shift=self.tol)
        run_of = np.repeat(np.arange(len(n_s)), n_s)
        same = run_of[kidx[1:]] == run_of[kidx[:-1]]
        i, j = kidx[:-1][same], kidx[1:][same]
        dt = (K[j] - K[i]) * self.dt
        ok = dt > 0
        i, j, dt = i[ok], j[ok], dt[ok]

        def settled(i, j):
            """Each segment's run, first-of-run flag and the printed points, settled (holds)."""
            srun = run_of[i]  # motion run of each segment
            first_seg = np.concatenate(([True], srun[1:] != srun[:-1]))
            # the firmware sees the printed (rounded) coordinates: durations must come from those
            return (srun, first_seg, *settle_holds(np.round(P, 4), i, j, first_seg, offs, last))

        srun, first_seg, Pr, d, dist, hold = settled(i, j)
        # sub-micrometre holds where a run leaves or comes to rest on the plan's time, and a leaving
        # run's first point within REST_POINT_NEAR_MM of its lead (see holds.merged_rest_holds):
        # those points go, the segments next to them span their time
        went_a, rest_go_a = np.asarray(went, bool), np.asarray(rest_go, bool)
        merged = merged_rest_holds(i, j, srun, first_seg, hold, (went_a | rest_go_a)[srun],
                                   np.array([e is not None for e in run_ends], bool)[srun],
                                   near=dist < REST_POINT_NEAR_MM, span=K[j] - K[i])
        if merged is not None:
            i, j = merged
            dt = (K[j] - K[i]) * self.dt
            srun, first_seg, Pr, d, dist, hold = settled(i, j)
        # holds that extrude would be extruder-only lines, a stop of the firmware where the plan
        # moves: the moving segment after them takes them over (holds.merged_wet_holds)
        merged = merged_wet_holds(i, j, srun, hold, Ef[j] != Ef[i])
        if merged is not None:
            i, j = merged
            dt = (K[j] - K[i]) * self.dt
            srun, first_seg, Pr, d, dist, hold = settled(i, j)
        # the slow ends of a quiet z move's ramps: not holds (holds.merged_ramp_holds)
        quiet = np.array([r.move is not None and r.move.kind == MOVE and r.move.quiet
                          for r in (runs[q] for q in run_ids)], bool)
        if quiet.any():
            merged = merged_ramp_holds(i, j, srun, hold, quiet[srun])
            if merged is not None:
                i, j = merged
                dt = (K[j] - K[i]) * self.dt
                srun, first_seg, Pr, d, dist, hold = settled(i, j)
        if self.chain is not None:
            # a move that leaves rest after holds the firmware cannot start in its time takes the last
            # of them over (holds.merged_start_holds)
            merged = merged_start_holds(self.chain, i, j, Pr, srun, hold, Ef[j] == Ef[i], dt)
            if merged is not None:
                i, j = merged
                dt = (K[j] - K[i]) * self.dt
                srun, first_seg, Pr, d, dist, hold = settled(i, j)
        if self.chain is not None:  # (a hold moves the next segment's start: a few passes)
            micro = np.zeros(len(i), bool)
            for _ in range(3):
                new = unrunnable_rests(self.chain, Pr[i], Pr[j], dist, dt, hold, Ef[j] == Ef[i], self.tol)
                if not new.any():
                    break
                micro |= new
                Pr, d, dist, hold = settle_holds(Pr, i, j, first_seg, offs, last, force=micro)
            self.stats.micro_holds += int(micro.sum())
        groups = flow_groups([runs[q].move for q in run_ids])[srun]
        capped = np.array([self._caps_bind(runs[q].move) for q in run_ids])[srun]
        ratio_changes = bool(np.any(groups[1:] != groups[:-1]))
        # the last chunk's last segment, where the firmware runs on from it into this chunk's first
        if ratio_prev is not None and (run_ids[0] != 0 or follows_hold[0] or went[0] or rest_go[0]):
            ratio_prev = None
        de = by_length(Ef[j] - Ef[i], dist, groups, hold, speed_mm_s=dist / dt, prev=ratio_prev,
                       icv_mm_s=self.chain.instant_corner_v if self.chain is not None else None, capped=capped,
                       e_limits=None if self.chain is None else (self.chain.max_e_velocity, self.chain.max_e_accel),
                       corner_v_mm_s=(self._corner_v(Pr[i], Pr[j], dist, Ef[j] - Ef[i])
                                      if self.chain is not None and ratio_changes else None),
                       plan_v_mm_s=(_plan_corner_v([runs[q].move for q in run_ids], srun,
                                                   first_seg & on_plan[src[j]], Pr[i])
                                    if ratio_changes and on_plan is not None else None))
        if self.chain is not None and self.place_steps and ratio_changes:
            # each change of ratio on its cheapest junction (a chunk without one has nothing to place)
            de = place_ratio_steps(de, dist, dist / dt, segment_limits(self.chain, Pr[i], Pr[j], de)[1], groups,
                                   hold, self.chain.instant_corner_v, capped=capped)
        de = self._extrusion(ch, de, run_ids[srun], ext_de, ext_runs)
        stop_first = first_seg & follows_hold[run_ids[srun]]
        if self.chain is not None:
            # a run that leaves rest on the plan's time a sample or more after the writer's last point
            # (the stream's pre-roll ends a sample before the plan's first move): the firmware would
            # go on at once, a sample early for the rest of the file where the plan leaves no slack
            # (a move at max_z_accel); it waits there (a G4, feed_solve's wait_out) from rest
            ahead = first_seg & went_a[srun] & (run_pre[run_ids[srun]] < -0.5 * self.dt)
            stop_first = stop_first | ahead
            # a run that leaves rest at once where the run before it ended on the plan's rest point:
            # the firmware stops there as the plan does (a G4 P0 flushes its look-ahead) rather than
            # carry a micrometre's turn through at speed and brake the plan's ramp for it
            go = first_seg & rest_go_a[srun] & ~stop_first
            for q in np.nonzero(go)[0].tolist():
                ch.run_stop[int(run_ids[srun[q]])] = True
            stop_first = stop_first | go
        fixed_v = None
        if self.chain is not None and on_plan is not None and k_plan is not None:
            fixed_v, plan_acc = plan_speeds(self.dt, k0, [runs[q].move for q in run_ids.tolist()], a_s, offs,
                                            src, K, i, j, srun, went, on_plan, k_plan)
            # only where the firmware ramps as the plan did (its limit binds there: max_z_accel, the
            # extruder's); elsewhere the output's acceleration (the header's) differs from the plan's
            fixed_v[hold] = np.nan
            c_ = np.nonzero(np.isfinite(fixed_v))[0]  # (the firmware's caps only where they matter)
            if c_.size:
                acc = segment_limits(self.chain, Pr[i[c_]], Pr[j[c_]], de[c_])[1]
                fixed_v[c_[np.abs(acc - plan_acc[c_]) > 1e-3 * np.maximum(plan_acc[c_], 1.0)]] = np.nan
            if not np.isfinite(fixed_v).any():
                fixed_v = None
        if self.chain is not None:
            pre = np.where(first_seg, run_pre[run_ids[srun]], 0.0)
            wait = np.zeros(len(dt))
            v = solve_feeds(self.chain, self.timing, Pr[i], Pr[j], dt, de, hold, stop_first,
                            open_end=runs[-1].kind == MOVE, pre_late=pre, wait_out=wait, fixed_v=fixed_v)
            for q in np.nonzero(wait > 0)[0].tolist():  # (only ever a run's first segment)
                ch.run_wait[int(run_ids[srun[q]])] = float(wait[q])
        else:
            v = self._firmware_feeds(d, dist, dt, hold, stop_first)
            v = np.where(hold, np.where(np.abs(de) > 1e-9, np.maximum(np.abs(de) / dt, 1e-3), dt), v)
        if runs[-1].kind != MOVE:
            self.f_last = 0.0
        elif not at_rest_end and not hold[-1] and dist[-1] > 1e-9:
            self.ratio_prev = (float(de[-1] / dist[-1]), float(dist[-1]), float(dist[-1] / dt[-1]))
        # ---- statistics
        self.prev_seg = add_segments(self.stats, Pr[i], Pr[j], d, dt, v, de, hold, self.prev_seg, self.chain,
                                     self.max_z_accel, self.dt)
        # ---- the lines (one per segment) and the self-check's table
        lines = format_segments(Pr[j], de, v, hold, fractional_dwell=self.chain is not None)
        ch.lines = lines
        cnt = np.bincount(srun, minlength=len(n_s))
        ends = np.cumsum(cnt)
        for m_, r in enumerate(run_ids.tolist()):
            ch.run_lines[r] = (int(ends[m_] - cnt[m_]), int(ends[m_]))
        local = np.arange(len(i)) - (ends - cnt)[srun] + 1  # line of the segment within its run
        cu = catch[srun] & (i == offs[srun])
        ka, kb = np.floor(K[i] + 1e-9), np.floor(K[j] + 1e-9)
        rows = ~hold & (kb > ka)  # a segment to a rest end between two samples stands for none
        fa, fb = np.round((K[i] - ka) * self.dt * 1e9), np.round((K[j] - kb) * self.dt * 1e9)
        ch.seg_rows = np.stack([local, ka, kb, cu.astype(np.int64), np.full(len(i), self.stream), fa, fb],
                               1)[rows].astype(np.int64)
        ch.seg_run = run_ids[srun][rows]
        self.last_pt = Pr[last[-1]].copy()
        return ch

    def _corners_to_look_at(self, X: np.ndarray, runs: list) -> set:
        """The motion runs of a chunk that end on a corner into another motion run where the sampled
        chords do not let the command through (:func:`~ffcomp.gcode.plan_clock.sampled_corners_ok`):
        the only ones :meth:`_free_corner` is asked about."""
        if not self.free_corners or self.chain is None:
            return set()
        rs = [r for r in range(len(runs) - 1) if runs[r].kind == MOVE and runs[r + 1].kind == MOVE
              and 2 <= runs[r].end < len(X) - 1]
        if not rs:
            return set()
        ok = sampled_corners_ok(self.chain, X, np.array([runs[r].end for r in rs]), self.dt)
        return {r for r, o in zip(rs, ok.tolist()) if not o}

    def _free_corner(self, k0: int, a: int, b: int, nxt, X: np.ndarray, mv, k_plan, on_plan):
        """:func:`~ffcomp.gcode.plan_clock.free_corner` into the next run ``nxt`` (a motion run of
        the next move that starts at ``b``) with the firmware's limits; None where either side of the
        corner follows the plan (pinned: :func:`~ffcomp.gcode.plan_clock.corner_lead` and
        :func:`~ffcomp.gcode.plan_clock.corner_tail` take those; a free side into a pinned lift,
        merged the same way, ran its chord late: up to +0.41 ms on random files; the pin repair's
        lead-in pins the free side where it comes into such a lift: ``RepairConfig.lead_in_wet``)."""
        a2, b2, _, mv2, kind2, _ = nxt
        if mv is None or kind2 != MOVE or mv2 is None or a2 != b or mv2.index != mv.index + 1:
            return None
        if on_plan is not None and on_plan[b - 1:b + 2].any():  # a pinned side: corner_lead / corner_tail
            return None
        return free_corner(self.dt, k0, a, b, b2, X, mv, mv2, k_plan, self.chain, self.tol)

    def _caps_bind(self, mv) -> bool:
        """Whether the extruder's own caps may bind the written segments of ``mv``
        (:func:`~ffcomp.gcode.extrusion.extruder_capped`: it retracts, or extrudes without XY travel),
        judged against the firmware's own limits on Klipper: ``max_extrude_only_velocity / |r|`` and
        ``max_extrude_only_accel / |r|`` (``r`` the move's ratio, mm of filament per mm) below the
        header's velocity or acceleration.  A travel that retracts 0.06 mm over 38 mm (caps of 73,000
        mm/s and 1.8 million mm/s^2) is not capped: its change of ratio into the print move after it
        may be placed (:func:`~ffcomp.gcode.extrusion.place_ratio_steps`)."""
        if not extruder_capped(mv):
            return False
        if self.chain is None or not CAPS_AGAINST_LIMITS:
            return True
        s_, e_ = mv.start_mm, mv.end_mm
        d = float(np.linalg.norm(np.subtract(e_[:3], s_[:3])))
        r = abs(e_[3] - s_[3]) / max(d, 1e-12)
        return bool(self.chain.max_e_velocity < r * self.chain.max_velocity
                    or self.chain.max_e_accel < r * self.chain.accel)

    def _corner_lead(self, k0: int, a: int, b: int, X: np.ndarray, mv, k_plan, on_plan, lead_pt):
        """:func:`~ffcomp.gcode.plan_clock.corner_lead`, or for a free run that leaves the plan's
        corner :func:`~ffcomp.gcode.plan_clock.corner_lead_free` (with the firmware's acceleration
        along the move)."""
        prev = self.moves.get(mv.index - 1)
        lead = corner_lead(self.dt, k0, a, b, X, mv, k_plan, on_plan, lead_pt, prev)
        if (lead is not None or not FREE_CORNER_LEAD or on_plan is None or mv.start_v_mm_s <= 1e-9
                or lead_pt is None or abs(round(mv.start_mm[2], 4) - lead_pt[2]) >= 1e-3):
            return lead  # (the cheap part of corner_lead_free's own conditions first)
        st, en = np.array(mv.start_mm[:3], float)[None], np.array(mv.end_mm[:3], float)[None]
        acc = float(segment_limits(self.chain, st, en, np.zeros(1))[1][0])
        return corner_lead_free(a, b, X, mv, on_plan, lead_pt, prev, acc, self.tol)

    def _corner_tail(self, k0: int, a: int, b: int, X: np.ndarray, mv, on_plan, end):
        """:func:`~ffcomp.gcode.plan_clock.corner_tail` with the firmware's acceleration along the move."""
        if end is None or mv is None or mv.end_v_mm_s <= 1e-9:
            return None
        st, en = np.array(mv.start_mm[:3], float)[None], np.array(mv.end_mm[:3], float)[None]
        acc = float(segment_limits(self.chain, st, en, np.zeros(1))[1][0])
        return corner_tail(self.dt, k0, a, b, X, mv, on_plan, self.moves.get(mv.index + 1), end, acc)

    def _corner_v(self, P0: np.ndarray, P1: np.ndarray, dist: np.ndarray, de: np.ndarray) -> np.ndarray:
        """The firmware's corner limit (mm/s) at the start of each written segment (``inf`` at the
        first, on a straight line and next to a hold), from the printed points."""
        out = np.full(len(dist), np.inf)
        ok = dist > 1e-9
        if len(dist) < 2 or not ok.any():
            return out
        unit = np.where(ok[:, None], (P1 - P0) / np.where(ok, dist, 1.0)[:, None], 0.0)
        acc = segment_limits(self.chain, P0, P1, de)[1]
        v2 = corner_v2(self.chain, unit, acc, 2.0 * dist * acc)
        both = ok[1:] & ok[:-1]
        out[1:][both] = np.sqrt(v2[both])
        return out

    def _extrusion(self, ch, de_ref, seg_run, ext_de, ext_runs) -> np.ndarray:
        """Relative extrusion of every segment and extruder-only move of a chunk, in written order.

        Extrusion follows the reference timing; the emitted total is the reference total rounded to
        0.01 um, so rounding never accumulates (each line gets the difference of consecutive
        rounded totals).  Returns the segments' values; the extruder-only moves' go to ``ch``.
        """
        ext_runs = np.asarray(ext_runs, np.int64)
        ev_run = np.concatenate([seg_run, ext_runs])
        ev_val = np.concatenate([de_ref, ext_de[ext_runs]])
        order = np.argsort(ev_run, kind="stable")
        cum = self.e_ref_cum + np.cumsum(ev_val[order])
        tot = np.round(cum, 5)
        out = np.empty(len(order))
        out[order] = np.diff(np.concatenate([[self.e_emitted], tot]))
        if len(order):
            self.e_ref_cum = float(cum[-1])
            self.e_emitted = float(tot[-1])
        for m_, r in enumerate(ext_runs.tolist()):
            ch.extrude_de[r] = float(out[len(seg_run) + m_])
        return out[: len(seg_run)]

    def _start_travel(self, p_mm: np.ndarray) -> None:
        """The ordinary travel to the first compensated point (before the compensated motion)."""
        x, y, z = np.round(p_mm, 4).tolist()
        self._w(f"G1 X{x:.4f} Y{y:.4f} Z{z:.4f} F{self.start_travel_mm_s * 60:.1f} ; ffcomp: travel to the start\n")
        self.start_travel_mm_s = None

    def _fast_extrude(self, ch, r: int, mv: PlannedMove) -> float:
        """Write an extruder-only move up to ``EXTRUDE_SPARE_S`` faster than planned (within the
        extruder's limits): the command moved on while the nozzle had to stand, and the segment
        after the move catches up in the time saved.  Returns the written move's duration."""
        de = np.array([mv.end_mm[3] - mv.start_mm[3]])
        lim = self.chain
        want = np.array([max(mv.duration_s - EXTRUDE_SPARE_S, 1e-4)])
        v = extrude_only_feed(de, want, lim.max_e_accel, lim.max_e_velocity)
        v = np.maximum(v, mv.cruise_v_mm_s)
        ch.extrude_v[r] = float(np.round(v[0] * 60, 3) / 60)
        return float(extrude_only_time(de, np.array([ch.extrude_v[r]]), lim.max_e_accel)[0])

    def _firmware_line(self, lineno: int) -> None:
        """Write source line ``lineno`` (a ``G10``/``G11``), under the source's M220/M221 factors: the
        output bakes those into its own moves and runs at 100 %, the firmware applies them to its
        retraction as it would in the source."""
        src = self._line_iter_next()
        if src is None or src.lineno != lineno or not isinstance(src.op, FirmwareMove):
            raise AssertionError(f"the firmware's extruder move of line {lineno} is not next to write")
        op = src.op
        wrap = [(f"M220 S{op.speed_percent:g}", "M220 S100") if op.speed_percent != 100.0 else None,
                (f"M221 S{op.extrude_percent:g}", "M221 S100") if op.extrude_percent != 100.0 else None]
        wrap = [w for w in wrap if w is not None]
        for on, _ in wrap:
            self._w(on + " ; ffcomp: the source's factor, for the firmware's retraction\n")
        self._w(src.raw if src.raw.endswith("\n") else src.raw + "\n")
        for _, off in wrap:
            self._w(off + " ; ffcomp: the output's moves carry the factors\n")
        self.stats.extrude_moves += 1

    def _dwell(self, mv: PlannedMove, lineno: int) -> None:
        self._w(f"G4 P{mv.cruise_t_s * 1000:{'.0f' if self.chain is None else '.3f'}}\n")

    def _firmware_feeds(self, d, dist, dt, hold, stop_before) -> np.ndarray:
        """Feed rates that make the firmware's trapezoids last the intended durations.

        A segment cruises at its F, but the firmware enters it at the junction speed
        ``min(F_prev, F)`` and leaves at ``min(F, F_next)``, ramping at its acceleration limit
        (the header's ACCEL, or Klipper's delta limit ``max_z_accel * d / |dz|`` on segments with z
        travel).  Solving ``d = F T - (F - v_in)^2 / 2a - (F - v_out)^2 / 2a`` for F, a few sweeps
        over the chunk, removes the time those ramps would add (a slow drift otherwise).  The
        firmware starts from rest after a held segment and where ``stop_before`` is set (an
        extruder-only move or a dwell stands between two runs).
        """
        v = dist / dt
        if len(v) == 0:
            return v
        dz = np.abs(d[:, 2])
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(dz > 0, dist / np.maximum(dz, 1e-12), np.inf)
        a = np.minimum(self.accel, self.max_z_accel * ratio)
        if not np.all(np.isfinite(a)):
            return v
        stop = np.concatenate([[False], hold[:-1]]) | stop_before
        F = v.copy()
        for _ in range(4):
            prev = np.concatenate([[self.f_last], F[:-1]])
            prev[stop] = 0.0
            nxt = np.concatenate([F[1:], [F[-1]]])
            nxt[:-1][stop[1:]] = 0.0
            vin = np.minimum(prev, F)
            vout = np.minimum(nxt, F)
            b = vin + vout + a * dt
            disc = b * b - 2.0 * (vin * vin + vout * vout + 2.0 * a * dist)
            Fn = np.where(disc > 0, 0.5 * (b - np.sqrt(np.maximum(disc, 0.0))), v)
            F = np.where(hold, v, np.maximum(Fn, v))
        self.f_last = 0.0 if hold[-1] else float(F[-1])
        return F

    def finish(self) -> None:
        self.flush_samples()
        self.flush_lines(1 << 62)


#: a sample within this distance of the plan's nozzle position (every axis) follows the plan, mm
ON_PLAN_MM = 1e-3

#: :meth:`GcodeWriter.feed` holds back a chunk's last run when it starts within this many samples of
#: the chunk's end (:func:`~ffcomp.gcode.plan_clock.corner_lead` needs at least 4 of a run's samples;
#: on other_delta's sample files, 16 moved other runs' ends across the cut and made new 0.3 ms errors);
#: and this many of its last samples when the last one's move turns into the next within as many after
CARRY_SAMPLES = 5

#: :meth:`GcodeWriter.feed` holds back this many more samples where a cut would fall within as many
#: samples before a corner of the plan that the command follows (a pinned lift into its travel): the
#: corner's tail (``plan_clock.corner_tail`` looks at up to ``CORNER_LEAD_MAX_SAMPLES`` samples) is
#: written in one chunk (a 0.1 mm gyroid on other_delta, whose chunk ended just after a pinned lift's
#: travel began: the travel waited with the lift's last sample alone, the lift ended on a 3 um
#: segment, +0.32 ms)
CARRY_TAIL_SAMPLES = CORNER_LEAD_MAX_SAMPLES + 2

#: the rule of :data:`CARRY_TAIL_SAMPLES` applies again at the cut it moved to, up to this many times
#: in all: a cut held back from a travel's turn into a printed line fell within the tail of the
#: pinned lift before the travel (a user's tower on other_delta: +0.58 ms)
CARRY_TAIL_PASSES = 3

#: a move :func:`~ffcomp.gcode.extrusion.extruder_capped` calls capped counts as capped for the
#: extrusion's ramps and steps only where its caps fall below the firmware's own limits
#: (:meth:`GcodeWriter._caps_bind`; a switch for the tests)
CAPS_AGAINST_LIMITS = True

#: a free run that leaves the plan's corner drops its first samples within the corner's reach
#: (:func:`~ffcomp.gcode.plan_clock.corner_lead_free`; a switch for the tests)
FREE_CORNER_LEAD = True

#: :meth:`GcodeWriter.feed` holds back a chunk's last run where it starts within this many samples of
#: the cut on a free corner or a change of extrusion ratio (``plan_clock.free_corner``'s lead reaches
#: ``CORNER_LEAD_MAX_SAMPLES`` samples into the run and needs 4 more after them)
CARRY_FREE_SAMPLES = CORNER_LEAD_MAX_SAMPLES + 4

#: :meth:`GcodeWriter.feed` holds back a chunk's last this-many samples when the plan comes to rest
#: within as many samples after them: the segments written before a chunk's end are timed as if the
#: chain went on, and a stop just after the cut left them no segments to take their braking back
#: (the plate's z-hop descent: a 6 ms segment 0.22 ms late, one 5 um segment left to the rest point)
CARRY_REST_SAMPLES = 16
#: a planned move that ends slower than this comes to rest, mm/s
REST_V_MM_S = 1e-6


def _run_start_cut(mi: np.ndarray, cut: int) -> int:
    """``cut`` (the first sample held back), or earlier where the last run before it starts within
    :data:`CARRY_SAMPLES` samples of it: then that run waits too, with the run before's last
    sample (:meth:`GcodeWriter._carry_from`)."""
    first = _last_run_start(mi, cut)
    if 1 < first and cut - first < CARRY_SAMPLES:
        return first - 1
    return cut


def _on_plan(args: tuple, i: int) -> bool:
    """Whether sample ``i`` of a chunk (``args``: :meth:`GcodeWriter.feed`'s, with ``plan_mm``) lies
    within :data:`ON_PLAN_MM` of the plan on every axis."""
    return float(np.max(np.abs(args[1][i] - args[7][i]))) < ON_PLAN_MM


def _last_run_start(mi: np.ndarray, cut: int) -> int:
    """The first sample of the run that holds sample ``cut - 1`` (0 where it starts the chunk)."""
    head = mi[:cut]
    if not len(head) or not np.any(head != head[-1]):
        return 0
    return cut - int(np.argmax(head[::-1] != head[-1]))


def _joined(a: tuple, b: tuple) -> tuple:
    """Two :meth:`GcodeWriter.feed` argument tuples as one (the first's ``k0``; an optional array
    missing on one side is filled: ``dense`` False, ``k_plan`` -1, ``plan_mm`` the samples' own
    positions, ``t_shift`` 0)."""
    n_a, n_b = len(a[1]), len(b[1])
    fill = {5: lambda n, x: np.zeros(n, bool), 6: lambda n, x: np.full(n, -1, np.int64),
            7: lambda n, x: x[1], 8: lambda n, x: np.zeros(n)}
    out = [a[0]]
    for i in range(1, 9):
        x, y = a[i], b[i]
        if x is None and y is None:
            out.append(None)
            continue
        x = x if x is not None else fill[i](n_a, a)
        y = y if y is not None else fill[i](n_b, b)
        out.append(np.concatenate([x, y]))
    return tuple(out)


class _Run(NamedTuple):
    """Samples ``[start, end)`` of a chunk that belong to one planned move."""

    start: int
    end: int
    move_index: int
    move: PlannedMove | None
    kind: str
    lineno: int


class _Chunk:
    """The writer's numbers for one chunk (see :meth:`GcodeWriter._plan_chunk`)."""

    __slots__ = ("lines", "run_lines", "extrude_de", "extrude_v", "seg_rows", "seg_run", "run_wait", "run_stop")

    def __init__(self, n_runs: int):
        self.lines: list[str] = []
        self.run_lines = [(0, 0)] * n_runs
        self.extrude_de = [0.0] * n_runs
        self.extrude_v = [0.0] * n_runs  # feed of an extruder-only move written faster (0: as planned)
        self.run_wait = [0.0] * n_runs  # a G4 before a motion run that leaves rest ahead of the clock, s
        self.run_stop = [False] * n_runs  # a G4 (at least P0) before a motion run: it leaves from a stop
        self.seg_rows = np.zeros((0, SEG_COLS), np.int64)
        self.seg_run = np.zeros(0, np.int64)
