"""What a compensation run is asked (:class:`CompensateOptions`) and what it reports
(:class:`CompensationSummary`), with the constants every stage of the run shares."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from ..compensate.inverse import InverseConfig
from ..compensate.pin_repair import RepairConfig

__all__ = ["CompensateOptions", "CompensationSummary", "Z_MODES", "REST_MOVE", "REST_PRE", "JUMP_M",
           "PIECE_START_FEED_MM_MIN"]

#: the z modes (see :class:`CompensateOptions`)
Z_MODES = ("keep", "hold", "auto")

#: move index of the rest samples before and after a compensation stream (no planned move: the
#: machine stands while the command pre-actuates the first move or settles after the last, so these
#: samples are motion of their own, never part of an extruder-only move or dwell)
REST_MOVE = -1
#: move index of the rest samples before a stream (its pre-roll): a run of their own, apart from the
#: rest after the stream before, so a stop's line (G10 planned as a stop, M600, M109, an unknown
#: macro...) is written between the two rests, where the command stands still, not into the
#: pre-roll's motion (there the firmware's flush slowed the segment before it: 0.13 ms each time,
#: a lateness the writer never saw and kept for the rest of the file)
REST_PRE = -2

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
    #: rest added before every retraction that follows motion and after every unretraction that
    #: precedes motion, s (0: none).  A G-code file cannot move the nozzle during an extruder-only
    #: move, so the command cannot settle a stop's ringing during the retraction nor pre-actuate
    #: the next move during the unretraction; in this added rest it can (the print takes that much
    #: longer per margin: counted in the summary).  See :mod:`ffcomp.gcode.margins`.
    hold_margin_s: float = 0.0
    #: plan the z moves next to extruder-only moves (a layer change's z move between retraction and
    #: unretraction, a z-hop's lift and its move down) with quiet ramps: each ramp from rest lasts one
    #: period of the printer's z resonance (:func:`ffcomp.model.modes.z_resonance_hz`), so the move
    #: itself leaves (almost) no ringing.  A G-code file cannot compensate these moves (the nozzle
    #: stands still in the holds around them, so the command there is the plan); their ringing was
    #: most of what the written file loses against the exact commands at layer changes.  The print
    #: takes longer by the slower ramps (counted in the summary).  Klipper only (its planner plans
    #: the source); see :class:`ffcomp.gcode.klipper.KlipperPlanner`'s ``quiet_z_period_s``.
    #: Off by default: the slower moves put the output off the source's own clock (about 20 ms later
    #: at every such move), and a judge that compares the output with the source's plan sees that as
    #: drift.  True: on where the profile's planner is Klipper's, a warning where it is another.
    quiet_z: bool = False
    #: passes of the feed re-timing on the firmware's own plan for planners the writer has no exact
    #: chain model of (Marlin; :mod:`ffcomp.pipeline.retime`); 0: none.  Klipper's writer solves its
    #: feeds against an exact copy of Klipper's lookahead and needs none.
    retime_passes: int = 6


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
    #: M400 and M18/M84 lines: the firmware drains its queue there (a stop of the toolhead), so the
    #: compensation settles and starts again at each (the inverse's settle and pre-roll, 0.35 s by default)
    commands_synced: int = 0
    #: G10/G11 timed as the extruder moves Klipper's firmware_retraction makes of them (the profile's
    #: [firmware_retraction]); without that section they are stops (among commands_stopped)
    firmware_retractions: int = 0
    #: what the output does to Klipper's input shaping (off while it runs; back on at its end with the
    #: profile's [input_shaper]); empty for Marlin
    input_shaper: str = ""
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
    #: stretches whose command was brought within Klipper's delta cap ``max_z_accel * d/|dz|``
    #: (:mod:`ffcomp.compensate.delta_cap`), and the largest change of the command there (um)
    cap_windows: int = 0
    cap_max_change_um: float = 0.0
    #: worker processes (``--jobs``) and, with more than one, each piece: its first source line, how
    #: it ends (the cut's kind: ``stop``, ``hold`` or None at the end of the file), its samples' print
    #: time, and its worker's wall and CPU time (s)
    jobs: int = 1
    pieces: list | None = None
    #: rest margins added around retractions (``hold_margin_s``): how many, and the time they add, s
    hold_margins: int = 0
    hold_margin_time_s: float = 0.0
    #: z moves planned with quiet ramps (``quiet_z``), the time their slower ramps add (s, rest to
    #: rest) and the period they are timed to (s; None: off)
    quiet_z_moves: int = 0
    quiet_z_time_s: float = 0.0
    quiet_z_period_s: float | None = None
    #: what the checks cost: the prediction's and the self-check's time, s (wall time in one
    #: process; with ``--jobs``, summed over the workers)
    predict_time_s: float | None = None
    self_check_time_s: float | None = None
    #: short moves from rest to rest the firmware could not run in their time, written as holds
    #: (the nozzle stays within ``tol_um``; :func:`ffcomp.gcode.holds.unrunnable_rests`)
    micro_holds: int = 0
    #: the feed re-timing (Marlin, ``retime_passes``): passes run, the largest lateness on the
    #: absolute clock before and after (ms), and its time (s)
    retime_passes: int = 0
    retime_before_ms: float | None = None
    retime_after_ms: float | None = None
    retime_time_s: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)
