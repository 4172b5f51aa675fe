"""The header and footer of a compensated G-code file: the firmware settings it must run with."""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass

from .. import __version__

__all__ = ["header_accel", "header_lines", "shaper_lines", "shaper_summary", "SHAPER_OFF", "FirmwareNeeds",
           "firmware_needs", "klipper_snippet", "read_firmware_needs", "limit_warnings", "NEEDS_TAG",
           "quiet_z_period_s", "settings_hold_margin_s", "settings_quiet_z_period_s"]

#: the header line that carries the firmware values, machine-readable (``key=value`` words)
NEEDS_TAG = "; ffcomp firmware:"


@dataclass(frozen=True)
class FirmwareNeeds:
    """What a compensated file needs from Klipper (mm, s).

    ``max_accel``, ``max_z_accel``, ``max_velocity``, ``max_z_velocity``: the ``[printer]``
    (printer.cfg) values the file is **timed for**, the profile's.  The writer solved its feeds
    against them, and Klipper's delta kinematics reads them from printer.cfg only
    (``SET_VELOCITY_LIMIT`` cannot change them): the z ramps run at ``max_z_accel * d/|dz|`` and the
    rim's slow zone at a fraction of ``max_accel`` and ``max_velocity``.  So ``max_z_accel`` and
    ``max_accel`` must be these values: a higher max_z_accel runs the file's z ramps early and its
    clock drifts (``cube_prusa.gcode`` compensated for the default profile and re-planned at the
    43,600 mm/s^2 its segments would need to pass every corner unslowed: 165 ms early by its end;
    at 1.1x the profile's value on other_delta, 85 ms).  ``max_velocity`` and ``max_z_velocity``
    may be higher where the written segments stay below them (``peak_velocity``,
    ``peak_z_velocity``: the largest speeds of the written segments, overall and along z).
    ``accel``, ``square_corner_velocity``, ``minimum_cruise_ratio``: the run-time values the file
    sets itself with ``SET_VELOCITY_LIMIT``.
    ``instantaneous_corner_velocity``, ``max_extrude_only_velocity``, ``max_extrude_only_accel``: the
    ``[extruder]`` values the file is timed for, the profile's, all three exactly (the retractions
    and the junctions where the extrusion ratio steps run at them: cube_prusa on other_delta
    re-planned at max_extrude_only_accel 5000 instead of 3000 runs 1.34 s early by its end).
    ``z_accel_unslowed``: the max_z_accel at which Klipper's rules let :data:`Z_NEED_SHARE` of the
    junctions that move in z through at the command's speed (rounded up to 100 mm/s^2; information:
    it takes a profile with that value, and compensating again, to use it).
    """

    max_accel: float
    max_z_accel: float
    max_velocity: float
    max_z_velocity: float
    accel: float
    square_corner_velocity: float
    minimum_cruise_ratio: float = 0.0
    peak_velocity: float = 0.0
    peak_z_velocity: float = 0.0
    z_accel_unslowed: float = 0.0
    rim_segments: float = 0.0
    instantaneous_corner_velocity: float = 1.0
    max_extrude_only_velocity: float = 0.0
    max_extrude_only_accel: float = 0.0

    def may_be_higher(self, name: str) -> bool:
        """Whether printer.cfg's ``name`` (``max_velocity`` or ``max_z_velocity``) may exceed the
        stated value without moving the file's clock: no written segment reaches it (nor, for
        max_velocity, the rim's slow zone, whose cap is a fraction of it)."""
        peak = {"max_velocity": self.peak_velocity, "max_z_velocity": self.peak_z_velocity}.get(name)
        if name == "max_velocity" and self.rim_segments:
            return False
        return peak is not None and peak < getattr(self, name) * (1 - 1e-9)


def _up(x: float, step: float) -> float:
    return float(math.ceil(max(x, 0.0) / step - 1e-9) * step)


#: the share of a file's junctions (those with a z need) whose max_z_accel the header states as what
#: the file's segments would need to pass unslowed: one chord of a micrometre or two at a corner asks
#: any amount (253,200 mm/s^2 on a printed circle's layer change, where the self-check measured
#: +0.06 ms for the nine such junctions)
Z_NEED_SHARE = 0.999
#: a max_z_accel need within this factor of the profile's is no warning (the need's bins are 1 %
#: wide, and the plan's own z ramps run at the profile's value)
Z_NEED_SLACK = 1.02
#: no limit warning where the self-check measured at most this drift (ms): the timing goal
QUIET_DRIFT_MS = 0.2


def firmware_needs(profile, opts, accel: float, stats) -> FirmwareNeeds:
    """The firmware values a written body is timed for (the profile's ``[printer]`` limits) and what
    its segments reach, from the writer's statistics (peak speeds between its segments, overall and
    along z; the max_z_accel its junctions ask)."""
    lim = profile.limits
    return FirmwareNeeds(
        max_accel=float(lim.max_accel_mm_s2), max_z_accel=float(lim.max_z_accel_mm_s2),
        max_velocity=float(lim.max_velocity_mm_s), max_z_velocity=float(lim.max_z_velocity_mm_s),
        accel=float(accel), square_corner_velocity=float(opts.corner_velocity_mm_s), minimum_cruise_ratio=0.0,
        peak_velocity=_up(stats.peak_speed_mm_s, 1.0), peak_z_velocity=_up(stats.peak_z_velocity_mm_s, 1.0),
        z_accel_unslowed=_up(stats.z_accel_quantile(Z_NEED_SHARE), 100.0), rim_segments=float(stats.rim_segments),
        instantaneous_corner_velocity=float(lim.instantaneous_corner_velocity_mm_s),
        max_extrude_only_velocity=float(lim.max_extrude_only_velocity_mm_s),
        max_extrude_only_accel=float(lim.max_extrude_only_accel_mm_s2))


def limit_warnings(profile, needs: FirmwareNeeds, stats=None, drift_ms: float | None = None,
                   clock_um: float | None = None) -> list[str]:
    """Warnings for profile limits below what the file's segments would need to run unslowed, each
    saying which, by how much, where (``stats``, the writer's :class:`~ffcomp.gcode.writer_stats.WriterStats`:
    how many junctions need more max_z_accel) and what it cost: the self-check's largest drift on the
    absolute clock (ms) and distance from the intended command at the same instant (um), when it ran.
    None where the self-check measured a drift within :data:`QUIET_DRIFT_MS`: the firmware slows at
    those junctions, and the writer's feeds keep the clock anyway."""
    lim = profile.limits
    if drift_ms is not None and abs(drift_ms) <= QUIET_DRIFT_MS:
        return []  # measured: the writer keeps the clock despite the limits
    if drift_ms is not None and clock_um is not None:
        cost = (f"the self-check measured what it costs: largest drift on the absolute clock {drift_ms:+.3f} ms, "
                f"largest distance from the intended command {clock_um:.1f} um")
    else:
        cost = "those segments run late (the self-check, when on, says by how much)"
    out = []
    for name, have, need in (("max_z_accel", lim.max_z_accel_mm_s2, needs.z_accel_unslowed),
                             ("max_z_velocity", lim.max_z_velocity_mm_s, needs.peak_z_velocity),
                             ("max_velocity", lim.max_velocity_mm_s, needs.peak_velocity)):
        if need > have * (Z_NEED_SLACK if name == "max_z_accel" else 1 + 1e-9):
            what = f"the {need:g} this file's compensated segments need ({need / have:.1f}x)"
            if name == "max_z_accel" and stats is not None and stats.junctions:
                what = (f"what this file's compensated segments need at {stats.z_accel_short:,} of "
                        f"{stats.junctions:,} junctions ({need:g} at {Z_NEED_SHARE:.1%} of those that move in z, "
                        f"{need / have:.1f}x; up to {_up(stats.peak_z_accel_mm_s2, 100.0):g})")
            out.append(f"firmware: the profile's {name} = {have:g} is below {what}: the firmware slows there; "
                       f"{cost}; raising {name} in printer.cfg and in the profile, then compensating again, "
                       "removes the cost (the file is timed for the profile's value: raising it in printer.cfg "
                       "alone moves the file's clock)")
    return out


def read_firmware_needs(path: str, max_lines: int = 40) -> FirmwareNeeds | None:
    """The :class:`FirmwareNeeds` stated in a compensated file's header (None if it has none).

    Raises
    ------
    ValueError
        For a header written before the values were the ones the file is timed for (no
        ``z_accel_unslowed`` word): its max_z_accel was what the segments would need to pass every
        corner unslowed, which moves the file's clock if printer.cfg is set to it.
    """
    with open(path, encoding="utf-8", errors="replace") as f:
        for i, line in enumerate(f):
            if line.startswith(NEEDS_TAG):
                kv = dict(w.split("=", 1) for w in line[len(NEEDS_TAG):].split() if "=" in w)
                if "z_accel_unslowed" not in kv:
                    raise ValueError(
                        f"{path}: its header comes from an older ffcomp, which stated the max_z_accel its "
                        "segments would need to pass every corner unslowed, not the value the file is timed "
                        "for (setting printer.cfg to it moves the file's clock): compensate the source again")
                return FirmwareNeeds(**{k: float(kv[k]) for k in asdict(FirmwareNeeds(0, 0, 0, 0, 0, 0)) if k in kv})
            if i >= max_lines:
                break
    return None


def klipper_snippet(needs: FirmwareNeeds, profile=None) -> str:
    """The ``[printer]`` values a Klipper printer.cfg must have to run the file on time (those it is
    timed for), with what the file sets itself as comments; ``profile`` (optional) adds its
    ``[firmware_retraction]`` and says where its limits differ from the file's."""
    def bound(name: str) -> str:
        v = getattr(needs, name)
        if needs.may_be_higher(name):
            peak = needs.peak_velocity if name == "max_velocity" else needs.peak_z_velocity
            return f"{name}: {v:g}  # or higher (its segments reach {peak:g} mm/s)"
        return f"{name}: {v:g}  # exactly: the file is timed for it"

    lines = [
        "# Klipper printer.cfg values this compensated file is timed for (ffcomp " + __version__ + ")",
        "# The file itself sets the run-time limits (and its footer restores the profile's):",
        f"#   SET_VELOCITY_LIMIT ACCEL={needs.accel:.0f} SQUARE_CORNER_VELOCITY={needs.square_corner_velocity:g} "
        f"MINIMUM_CRUISE_RATIO={needs.minimum_cruise_ratio:g}",
        f"# and switches input shaping off while it runs ({SHAPER_OFF}): the compensation is the shaping;",
        "# " + (f"it switches it back on at its end ({profile.input_shaper.klipper_command()})."
                if profile is not None and profile.input_shaper is not None else
                "the profile has no [input_shaper] section, so the file cannot switch it back on "
                "(ffcomp profile import --klipper printer.cfg reads it)."),
        "# Klipper's delta kinematics reads these four from printer.cfg only: it ramps z at max_z_accel",
        "# and slows the rim at a fraction of max_accel, and the file's feeds were solved against them.",
    ]
    if needs.z_accel_unslowed > needs.max_z_accel * Z_NEED_SLACK:
        lines.append(f"# (Its segments would pass every corner unslowed at max_z_accel {needs.z_accel_unslowed:g}: "
                     "that takes a profile with that value and compensating again.)")
    lim = profile.limits if profile is not None else None
    if lim is not None:
        for name, have in (("max_velocity", lim.max_velocity_mm_s), ("max_accel", lim.max_accel_mm_s2),
                           ("max_z_velocity", lim.max_z_velocity_mm_s), ("max_z_accel", lim.max_z_accel_mm_s2),
                           ("instantaneous_corner_velocity", lim.instantaneous_corner_velocity_mm_s),
                           ("max_extrude_only_velocity", lim.max_extrude_only_velocity_mm_s),
                           ("max_extrude_only_accel", lim.max_extrude_only_accel_mm_s2)):
            if abs(have - getattr(needs, name)) > 1e-9 * max(have, 1.0):
                lines.append(f"# note: this profile's {name} = {have:g}, but the file was timed for "
                             f"{getattr(needs, name):g} (compensated with another profile?)")
    lines += ["[printer]", *(bound(n) for n in ("max_velocity", "max_accel", "max_z_velocity", "max_z_accel"))]
    lines += ["# these three go into your [extruder] section: the retractions and extrusion steps are timed with them",
              "[extruder]",
              *(f"{n}: {getattr(needs, n):g}  # exactly: the file is timed for it"
                for n in ("instantaneous_corner_velocity", "max_extrude_only_velocity", "max_extrude_only_accel"))]
    fr = profile.firmware_retraction if profile is not None else None
    if fr is not None:  # G10/G11 are timed with these: the printer must retract the same way
        lines += ["[firmware_retraction]", f"retract_length: {fr.retract_length_mm:g}",
                  f"retract_speed: {fr.retract_speed_mm_s:g}",
                  f"unretract_extra_length: {fr.unretract_extra_length_mm:g}",
                  f"unretract_speed: {fr.unretract_speed_mm_s:g}"]
    return "\n".join(lines) + "\n"


#: the line that switches Klipper's input shaping off (harmless without ``[input_shaper]``: Klipper
#: answers an unknown command with a message and goes on; a Klipper without the optional z shaper
#: ignores SHAPER_FREQ_Z)
SHAPER_OFF = "SET_INPUT_SHAPER SHAPER_FREQ_X=0 SHAPER_FREQ_Y=0 SHAPER_FREQ_Z=0"


def shaper_lines(profile) -> tuple[list[str], list[str]]:
    """The header and footer lines that switch Klipper's input shaping off for the compensated motion
    and, where the profile knows the printer's ``[input_shaper]``, back on after it.

    A shaper convolves the toolhead's X and Y with its impulses: on top of the compensation's
    command it smears the feedforward (on the simulator the 100 mm square's residual rose from
    2.4 um to 22-43 um with ZV/MZV/EI at the printer's 62 Hz, more than the shaper alone leaves).
    """
    head = [f"{SHAPER_OFF} ; ffcomp: the compensation is the shaping (input shaping off while this file runs)"]
    sh = profile.input_shaper
    if sh is not None:
        foot = [f"{sh.klipper_command()} ; ffcomp: restore the profile's input shaper"]
    else:
        foot = ["; ffcomp: input shaping stays off (the profile has no [input_shaper] section to restore): "
                "SET_INPUT_SHAPER with your printer.cfg values, or FIRMWARE_RESTART, switches it back on"]
    return head, foot


def shaper_summary(profile) -> str:
    """One line for the run's summary: what the output does to Klipper's input shaping."""
    sh = profile.input_shaper
    if sh is None:
        return ("off while the file runs, and left off (the profile has no [input_shaper]: "
                "ffcomp profile import --klipper printer.cfg reads it)")
    z = f" / z {sh.shaper_type_z} {sh.shaper_freq_z_hz:g} Hz" if sh.shaper_freq_z_hz > 0 else ""
    return (f"off while the file runs, back on at its end ({sh.shaper_type_x} {sh.shaper_freq_x_hz:g} Hz / "
            f"{sh.shaper_type_y} {sh.shaper_freq_y_hz:g} Hz{z})")


def header_accel(profile, opts) -> float:
    """The ACCEL the output sets (and the writer's timing assumes), mm/s^2."""
    return float(max(1e5, opts.accel_factor * profile.limits.max_accel_mm_s2))


def header_lines(profile, opts, src: str, accel: float, needs: FirmwareNeeds | None = None,
                 firmware_retractions: int = 0) -> tuple[list[str], list[str]]:
    """The output's header and footer lines; ``firmware_retractions``: how many G10/G11 of the file
    are timed with the profile's ``[firmware_retraction]`` (the header then states those values)."""
    lim = profile.limits
    settings = (f"method={opts.method} tol_um={opts.tol_um:g} z_mode={opts.z_mode} "
                f"knots={opts.inverse.knot_samples / lim.sample_rate_hz * 1e3:g}ms "
                f"degree={opts.inverse.degree} sample_rate={lim.sample_rate_hz:g}Hz")
    if opts.hold_margin_s:
        settings += f" hold_margin={opts.hold_margin_s * 1e3:g}ms"
    qp = quiet_z_period_s(profile, opts)
    if qp is not None:
        settings += f" quiet_z={qp * 1e3:.4f}ms"
    head = [
        f"; ffcomp {__version__}: model-based feedforward vibration compensation (delta)",
        f"; source: {os.path.basename(src)}",
        f"; profile: {profile.name}",
        f"; settings: {settings}",
        "; The timing of every move below is baked in: run it with the firmware settings that follow",
        "; (limit and mode commands of the source are kept as '; ffcomp (baked in):' comments).",
    ]
    if lim.planner == "klipper":
        if needs is not None:
            head += [
                f"; timed for printer.cfg [printer] max_accel = {needs.max_accel:g}, "
                f"max_z_accel = {needs.max_z_accel:g}, "
                f"max_velocity = {needs.max_velocity:g}, max_z_velocity = {needs.max_z_velocity:g} (the profile's); "
                "keep max_accel and max_z_accel exactly: Klipper runs the z ramps at max_z_accel and the feeds "
                "were solved against it (another value moves this file's clock)",
                f"; and [extruder] instantaneous_corner_velocity = {needs.instantaneous_corner_velocity:g}, "
                f"max_extrude_only_velocity = {needs.max_extrude_only_velocity:g}, max_extrude_only_accel = "
                f"{needs.max_extrude_only_accel:g} exactly (the retractions are timed with them)",
                f"; its segments reach {needs.peak_velocity:g} mm/s ({needs.peak_z_velocity:g} mm/s along z) "
                "(print the snippet: ffcomp firmware-config FILE)",
                NEEDS_TAG + " " + " ".join(f"{k}={v:g}" for k, v in asdict(needs).items()),
            ]
        else:
            head += [
                f"; timed for [printer] max_z_accel = {profile.limits.max_z_accel_mm_s2:g} mm/s^2 and "
                f"max_z_velocity = {profile.limits.max_z_velocity_mm_s:g} mm/s as in the profile",
            ]
        fr = profile.firmware_retraction
        if firmware_retractions and fr is not None:
            head += [f"; G10/G11 timed for [firmware_retraction] retract_length = {fr.retract_length_mm:g}, "
                     f"retract_speed = {fr.retract_speed_mm_s:g}, unretract_extra_length = "
                     f"{fr.unretract_extra_length_mm:g}, unretract_speed = {fr.unretract_speed_mm_s:g} as in the "
                     "profile (and the file's SET_RETRACTION lines)"]
        shaper_head, shaper_foot = shaper_lines(profile)
        head += [
            f"SET_VELOCITY_LIMIT ACCEL={accel:.0f} MINIMUM_CRUISE_RATIO=0 "
            f"SQUARE_CORNER_VELOCITY={opts.corner_velocity_mm_s:g}",
            *shaper_head,
        ]
        foot = [f"SET_VELOCITY_LIMIT ACCEL={lim.max_accel_mm_s2:g} MINIMUM_CRUISE_RATIO={lim.minimum_cruise_ratio:g} "
                f"SQUARE_CORNER_VELOCITY={lim.square_corner_velocity_mm_s:g} ; ffcomp: restore the profile's limits",
                *shaper_foot]
    else:
        # the limits the body is timed with: the run-time accelerations raised (the segments carry the
        # timing), the rest at the profile's values, set here so that the printer's EEPROM cannot
        # differ.  Not the E axis's (M201 E): it also bounds the extruder's velocity jump where Marlin
        # joins a retraction to a printing move at a junction speed (about 12 mm/s at 3000 mm/s^2;
        # 35 mm/s, the whole retraction speed, with it raised to the header's acceleration)
        e_acc, v, vz, ve = (lim.max_extrude_only_accel_mm_s2, lim.max_velocity_mm_s, lim.max_z_velocity_mm_s,
                            lim.max_extrude_only_velocity_mm_s)
        head += [f"M204 P{accel:.0f} T{accel:.0f} R{e_acc:g}",
                 f"M201 X{accel:.0f} Y{accel:.0f} Z{accel:.0f} E{e_acc:g}",
                 f"M203 X{v:g} Y{v:g} Z{vz:g} E{ve:g} ; ffcomp: the profile's, which the file is timed for",
                 f"M205 J{lim.junction_deviation_mm:g} S0 T0 ; ffcomp: the profile's junction deviation, no minimum "
                 "feed rates (a junction-deviation Marlin build)"]
        # restore every limit the header raised: M204 and M201 (Z: the profile's max_z_accel)
        foot = [f"M204 P{lim.max_accel_mm_s2:g} T{lim.max_accel_mm_s2:g} R{e_acc:g} "
                "; ffcomp: restore the profile's limits",
                f"M201 X{lim.max_accel_mm_s2:g} Y{lim.max_accel_mm_s2:g} Z{lim.max_z_accel_mm_s2:g} E{e_acc:g} "
                "; ffcomp: restore the profile's limits",
                f"M203 X{v:g} Y{v:g} Z{vz:g} E{ve:g} ; ffcomp: restore the profile's limits (the source's E may "
                "have changed it)"]
    head += ["G90 ; ffcomp: absolute positions (machine coordinates)", "M83 ; ffcomp: relative extrusion"]
    return head, foot


def _setting_ms(path, key: bytes, max_lines: int = 40) -> float | None:
    """``key=..ms`` of an ffcomp output's ``; settings:`` header line, in s (None: absent)."""
    import re

    with open(path, "rb") as f:
        for _ in range(max_lines):
            line = f.readline()
            if not line:
                break
            if line.startswith(b"; settings:"):
                m = re.search(rb"\b" + key + rb"=([0-9.]+)ms", line)
                return float(m.group(1)) * 1e-3 if m else None
    return None


def settings_hold_margin_s(path, max_lines: int = 40) -> float:
    """The rest margin (s) an ffcomp output was written with (its ``; settings:`` header line's
    ``hold_margin=..ms``); 0 for any other file."""
    return _setting_ms(path, b"hold_margin", max_lines) or 0.0


def settings_quiet_z_period_s(path, max_lines: int = 40) -> float | None:
    """The period (s) an ffcomp output's quiet z moves were planned with (``quiet_z=..ms`` in its
    ``; settings:`` line, :attr:`CompensateOptions.quiet_z`); None for any other file."""
    return _setting_ms(path, b"quiet_z", max_lines)


def quiet_z_period_s(profile, opts) -> float | None:
    """The period (s) of the printer's z resonance that ``opts.quiet_z`` times the z moves next to
    holds with (:func:`ffcomp.model.modes.z_resonance_hz` at the bed centre); None when off or the
    profile's planner is not Klipper's (off by default)."""
    if not getattr(opts, "quiet_z", False) or profile.limits.planner != "klipper":
        return None
    from ..model.lpv import LpvModel
    from ..model.modes import z_resonance_hz

    return 1.0 / z_resonance_hz(LpvModel.from_profile(profile))
