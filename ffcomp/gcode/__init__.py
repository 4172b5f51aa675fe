"""G-code in, firmware-exact motion out: streaming parser, planner variants, sampler, summary.

Flow: :func:`parse_gcode` (one :class:`GcodeLine` per input line) -> :func:`plan_moves` /
:func:`plan_gcode` (:class:`PlannedMove` trapezoids with print times, Klipper or Marlin rules) ->
:func:`sample_blocks` / :func:`sample_all` (uniform-time samples, SI, with carriage positions).
"""

from .moves import PlannedMove
from .parser import DIALECTS, GcodeParser, parse_gcode, parse_text
from .planner import PLANNERS, GcodePlan, make_planner, plan_gcode, plan_moves
from .records import ArcMove, Dwell, FirmwareMove, GcodeLine, Home, LimitsChange, LinearMove, ModeChange, Stop, Sync
from .sampler import SampleBlock, concat_blocks, sample_all, sample_blocks, sample_gcode
from .summary import PlanSummary, PlanTrace, summarize_gcode

__all__ = [
    "PlannedMove",
    "DIALECTS",
    "GcodeParser",
    "parse_gcode",
    "parse_text",
    "PLANNERS",
    "GcodePlan",
    "make_planner",
    "plan_gcode",
    "plan_moves",
    "ArcMove",
    "Dwell",
    "GcodeLine",
    "Home",
    "LimitsChange",
    "LinearMove",
    "FirmwareMove",
    "ModeChange",
    "Stop",
    "Sync",
    "SampleBlock",
    "concat_blocks",
    "sample_all",
    "sample_blocks",
    "sample_gcode",
    "PlanSummary",
    "PlanTrace",
    "summarize_gcode",
]
