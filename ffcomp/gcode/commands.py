"""What ffcomp does with every G-code command that is not plain motion: one table, four classes.

The compensated file keeps every source line in place, but a line can only sit between two
compensated segments if the printer may run it *while the compensated command is moving*.  Each
command word therefore belongs to one class (:data:`TABLE`):

``motion``
    Executed by the planner itself (G0-G3, G4, G28, M400, M18/M84): its timing is the plan's.
``state``
    Modal state the compensation bakes into the output (G90/G91, M82/M83, G92, M220/M221, units,
    planes, G-code offsets and motion limits); the line is kept as a ``; ffcomp (baked in):`` comment.
``pass``
    Runs in the background without stopping or moving the toolhead (temperatures, fans, messages,
    progress, object labels, pressure/linear advance, firmware-retraction *settings*): copied verbatim.
``stop``
    Stops, moves or re-references the machine at an unknown time (filament change, pause, tool change,
    heater waits, probing and bed levelling, nozzle cleaning, parking, firmware retraction G10/G11,
    homing variants):
    the planner brings the toolhead to rest there, the compensation stream ends at rest (as at a
    homing) and starts again from rest after the line, so the command never runs mid-motion.

A command that is not in the table is classified by its form (:func:`classify`): an unknown
Klipper-style macro (``PRINT_START``, ``MY_PURGE``) or unknown ``G`` code may move the toolhead, so
it follows the *unknown-command policy* (:data:`UNKNOWN_POLICIES`: ``stop`` (the default: treated as a
stop, with a warning), ``pass`` (copied verbatim, with a warning) or ``refuse`` (an error naming the
line)); an unknown ``M`` code is passed through (M codes that move the toolhead are all in the table).
``ffcomp/gcode/FIRMWARE.md`` lists the table.
"""

from __future__ import annotations

__all__ = ["MOTION", "STATE", "PASS", "STOP", "UNKNOWN", "TABLE", "UNKNOWN_POLICIES", "BAKED_STOPS", "classify"]

MOTION = "motion"
STATE = "state"
PASS = "pass"
STOP = "stop"
UNKNOWN = "unknown"
#: what to do with an unknown macro or G code
UNKNOWN_POLICIES = ("stop", "pass", "refuse")
#: stops the output keeps as comments: Klipper's ``SET_INPUT_SHAPER`` flushes the lookahead (a stop),
#: but a compensated file runs with input shaping off (its header switches it off), and a shaper
#: switched on in the middle of it would smear the compensation
BAKED_STOPS = frozenset({"SET_INPUT_SHAPER"})


def _words(cls: str, text: str) -> dict[str, str]:
    return {w: cls for w in text.split()}


#: command word (as :func:`ffcomp.gcode.words.lex` returns it) -> class
TABLE: dict[str, str] = {
    **_words(MOTION, "G0 G1 G2 G3 G4 G28 M400 M18 M84"),
    **_words(STATE, "G17 G18 G19 G20 G21 G90 G91 G92 M82 M83 M220 M221 M201 M203 M204 M205 "
                    "SET_VELOCITY_LIMIT SET_GCODE_OFFSET"),
    **_words(PASS,
             # temperatures (without waiting), fans, lights, sounds
             "M104 M140 M141 M105 M106 M107 M155 M150 M300 M42 "
             "SET_HEATER_TEMPERATURE SET_FAN_SPEED SET_LED SET_PIN "
             # messages, progress, reports, host protocol
             "M73 M75 M76 M77 M78 M110 M111 M112 M113 M114 M115 M117 M118 M119 M120 M121 M21 M22 M23 "
             "M24 M26 M27 M28 M29 M30 M31 M32 M33 M34 M928 RESPOND M117.1 SET_PRINT_STATS_INFO "
             "SET_DISPLAY_TEXT UPDATE_DELAYED_GCODE "
             # object labels (Klipper's exclude_object, Marlin's M486)
             "M486 EXCLUDE_OBJECT_DEFINE EXCLUDE_OBJECT_START EXCLUDE_OBJECT_END EXCLUDE_OBJECT "
             # extrusion settings that do not move the toolhead
             "M900 SET_PRESSURE_ADVANCE M207 M208 M209 SET_RETRACTION M92 M302 M572 "
             "SET_EXTRUDER_ROTATION_DISTANCE "
             # motor current, steppers on, settings storage, slicer/printer checks
             "M17 M80 M81 M85 M500 M501 M502 M503 M504 M906 M907 M913 M914 M862.1 M862.2 M862.3 M862.4 "
             "M862.5 M862.6 M115.1 SAVE_GCODE_STATE SAVE_VARIABLE"),
    **_words(STOP,
             # heater waits: the firmware stops the toolhead while the heater is away from its target
             # (Klipper flushes the lookahead then), so the command must not be mid-motion there
             "M109 M190 M191 M116 TEMPERATURE_WAIT "
             # pauses and user interaction
             "M0 M1 M25 M125 M226 M600 M601 M602 M603 M701 M702 M876 PAUSE RESUME CANCEL_PRINT "
             # input shaping (Klipper flushes the lookahead; the output keeps it as a comment: BAKED_STOPS)
             "SET_INPUT_SHAPER "
             # tool changes are added by classify(): T0, T1, ...
             # firmware retraction (the firmware moves the extruder, and Marlin may lift z)
             "G10 G11 "
             # probing, bed levelling, calibration, nozzle cleaning and parking
             "G12 G27 G29 G29.1 G29.2 G30 G31 G32 G33 G34 G35 G38.2 G38.3 G38.4 G38.5 G42 G76 G80 G81 "
             "M48 M401 M402 M420 M851 BED_MESH_CALIBRATE BED_MESH_PROFILE BED_MESH_CLEAR PROBE "
             "PROBE_CALIBRATE PROBE_ACCURACY DELTA_CALIBRATE DELTA_ANALYZE Z_TILT_ADJUST QUAD_GANTRY_LEVEL "
             "SCREWS_TILT_CALCULATE BED_TILT_CALIBRATE "
             # homing variants and position overrides (the firmware's position changes under the plan)
             "G28.1 G28.2 G28.3 G161 G162 SET_KINEMATIC_POSITION RESTORE_GCODE_STATE FORCE_MOVE "
             "MANUAL_STEPPER SET_STEPPER_ENABLE M410 M999 "
             # macros every Klipper user has (start and end of print)
             "PRINT_START START_PRINT PRINT_END END_PRINT"),
}


def classify(command: str) -> str:
    """The class of a command word (``""`` for blank and comment-only lines is ``pass``).

    Words not in :data:`TABLE`: ``T<n>`` (tool change) is a stop; an unknown ``M`` code passes; any other
    unknown word (a Klipper macro, an unknown ``G`` code) is ``unknown``.
    """
    cls = TABLE.get(command)
    if cls is not None:
        return cls
    if not command:
        return PASS
    c0 = command[0]
    if c0 == "T" and command[1:].isdigit():
        return STOP
    if c0 == "M" and len(command) > 1 and command[1].isdigit():
        return PASS
    return UNKNOWN
