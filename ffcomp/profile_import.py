"""Import printer geometry and limits from firmware configuration.

* Klipper ``printer.cfg`` (``[printer] kinematics: delta``, ``[stepper_a|b|c]``), including the
  ``#*#`` SAVE_CONFIG block that overrides the sections above it;
* a Marlin or RepRapFirmware ``M665`` line (``L`` diagonal rod, per tower as ``L250:251:250`` on
  RRF, ``R`` delta radius, ``B`` radius, ``H`` height, ``X/Y/Z`` tower angle corrections).

Klipper, Marlin and RRF all place towers A/X at 210, B/Y at 330 and C/Z at 90 degrees, the paper at
0/120/240.  ffcomp keeps the firmware's own tower angles, so positions in the G-code frame mean the
same thing to ffcomp as to the firmware.  The dynamics are taken from ``base`` (the default profile
unless given): identify yours with ``ffcomp identify``.
"""

from __future__ import annotations

import configparser
import math
import re
from dataclasses import replace
from pathlib import Path

from .errors import ProfileError
from .profile import PrinterProfile, default_profile, profile_from_dict

__all__ = ["from_klipper_cfg", "from_m665", "klipper_max_xy", "FIRMWARE_TOWER_ANGLES_DEG"]

#: Tower angles (A, B, C) used by Klipper, Marlin and RepRapFirmware, degrees counter-clockwise from +x.
FIRMWARE_TOWER_ANGLES_DEG = (210.0, 330.0, 90.0)

#: Klipper (kinematics/delta.py) slows moves where the tower moves more than SLOW_RATIO times the
#: nozzle's XY motion, and refuses XY beyond the point where that ratio reaches 4 * SLOW_RATIO
KLIPPER_SLOW_RATIO = 3.0


def klipper_max_xy(print_radius_mm: float, delta_radius_mm: float, arm_lengths_mm, step_dist_mm: float
                   ) -> tuple[float, str]:
    """The build radius Klipper's delta kinematics allows, and which of its three limits set it.

    Klipper does not refuse a ``print_radius`` the arms cannot reach: it takes the smallest of the
    configured ``print_radius`` (default ``delta_radius``), ``min(arm_length) - delta_radius``, and the
    radius where a tower moves ``4 * SLOW_RATIO`` times as fast as the nozzle,
    ``r sqrt(L^2 / (r^2 + 1) - h^2) + h - delta_radius`` with ``r = 12`` and ``h`` half the smallest
    step distance.

    Returns
    -------
    max_xy_mm : float
    limit : str
        ``"print_radius"``, ``"arm_length - delta_radius"`` or ``"tower speed ratio 12"``.
    """
    L = float(min(arm_lengths_mm))
    h = 0.5 * float(step_dist_mm)
    ratio = 4.0 * KLIPPER_SLOW_RATIO
    by_ratio = ratio * math.sqrt(L * L / (ratio * ratio + 1.0) - h * h) + h - delta_radius_mm
    cands = [(print_radius_mm, "print_radius"), (L - delta_radius_mm, "arm_length - delta_radius"),
             (by_ratio, f"tower speed ratio {ratio:g}")]
    return min(cands, key=lambda c: c[0])


def _merge(profile: PrinterProfile, geometry: dict, limits: dict, name: str, source: str,
           sections: dict | None = None) -> PrinterProfile:
    """``profile`` with ``geometry`` and ``limits`` values replaced and whole optional ``sections`` set
    (or removed, where a section's value is None)."""
    d = profile.to_dict()
    d["name"] = name
    d["geometry"].update(geometry)
    d["limits"].update(limits)
    for key, sec in (sections or {}).items():
        if sec is None:  # the firmware has no such section
            d.pop(key, None)
        else:
            d[key] = sec
    return profile_from_dict(d, source)


def _read_klipper(text: str) -> configparser.ConfigParser:
    main, saved = [], []
    for line in text.splitlines():
        if line.startswith("#*#"):
            body = line[3:].strip()
            if not body.startswith("<"):  # skip the "<--- SAVE_CONFIG --->" banner
                saved.append(body)
        else:
            main.append(line)
    cp = configparser.ConfigParser(inline_comment_prefixes=("#", ";"), strict=False, interpolation=None)
    cp.read_string("\n".join(main))
    if saved:
        sv = configparser.ConfigParser(inline_comment_prefixes=("#", ";"), strict=False, interpolation=None)
        sv.read_string("\n".join(saved))
        for sec in sv.sections():
            if not cp.has_section(sec):
                cp.add_section(sec)
            for k, v in sv.items(sec):
                cp.set(sec, k, v)
    return cp


def from_klipper_cfg(path: str | Path, base: PrinterProfile | None = None, notes: list | None = None
                     ) -> PrinterProfile:
    """Profile from a Klipper ``printer.cfg`` (delta kinematics).

    The print radius is the build radius Klipper itself allows (:func:`klipper_max_xy`): Klipper caps
    a ``print_radius`` the arms cannot serve instead of refusing it, and so does the import.  Where
    that radius puts the arms flatter than the base profile's ``min_arm_angle_deg``, the angle is
    lowered to what Klipper accepts there.  What was capped is appended to ``notes``.
    """
    path = str(path)
    base = base or default_profile()
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as e:
        raise ProfileError("<file>", path, f"cannot read: {e.strerror or e}", path) from e
    except UnicodeDecodeError as e:
        raise ProfileError("<file>", path, f"not a text file: byte 0x{e.object[e.start]:02x} at offset "
                           f"{e.start} is not UTF-8", path) from e
    try:
        cp = _read_klipper(text)
    except configparser.Error as e:
        raise ProfileError("<cfg>", path, f"not a valid Klipper config: {e}", path) from e

    def get(sec, key, default=None, conv=float):
        if cp.has_option(sec, key):
            raw = cp.get(sec, key)
            try:
                return conv(raw)
            except ValueError:
                raise ProfileError(f"[{sec}] {key}", raw, "not a number", path) from None
        if default is None:
            raise ProfileError(f"[{sec}] {key}", None, "missing (required for a delta printer)", path)
        return default

    if not cp.has_section("printer"):
        raise ProfileError("[printer]", None, "section missing", path)
    kin = cp.get("printer", "kinematics", fallback="").strip()
    if kin != "delta":
        raise ProfileError("[printer] kinematics", kin, "only 'delta' kinematics can be imported", path)
    radius = get("printer", "delta_radius")
    arm_a = get("stepper_a", "arm_length")
    arms, angles, radii = [], [], []
    for i, tower in enumerate("abc"):
        sec = f"stepper_{tower}"
        arms.append(get(sec, "arm_length", arm_a) if cp.has_section(sec) else arm_a)
        angles.append(get(sec, "angle", FIRMWARE_TOWER_ANGLES_DEG[i]) if cp.has_section(sec)
                      else FIRMWARE_TOWER_ANGLES_DEG[i])
        radii.append(radius)
    max_v = get("printer", "max_velocity")
    max_a = get("printer", "max_accel")
    for i, arm in enumerate(arms):
        if arm <= radius:  # Klipper: arm_length must be above delta_radius
            raise ProfileError(f"[stepper_{'abc'[i]}] arm_length", arm, f"must exceed delta_radius = {radius}",
                               path)
    step_dists = []
    for t in "abc":
        sec = f"stepper_{t}" if cp.has_option(f"stepper_{t}", "rotation_distance") else "stepper_a"
        if cp.has_option(sec, "rotation_distance"):
            step_dists.append(get(sec, "rotation_distance") / (get(sec, "full_steps_per_rotation", 200.0)
                                                                * get(sec, "microsteps", 16.0)))
    cfg_pr = get("printer", "print_radius", radius)
    print_radius, limit = klipper_max_xy(cfg_pr, radius, arms, min(step_dists) if step_dists else 0.0)
    min_arm_angle = base.geometry.min_arm_angle_deg
    if print_radius < cfg_pr:
        # the flattest arm at the capped radius: the nozzle opposite a tower
        flat = min(math.degrees(math.asin(math.sqrt(max(a * a - (radius + print_radius) ** 2, 0.0)) / a))
                   for a in arms)
        min_arm_angle = min(min_arm_angle, math.floor(flat * 100.0) / 100.0 - 0.01)
        if notes is not None:
            notes.append(f"print radius capped as Klipper does: {cfg_pr:g} mm configured, {print_radius:.3f} mm "
                         f"allowed (limit: {limit}); min_arm_angle_deg {min_arm_angle:g}")
    geom = {
        "arm_length_mm": arms,
        "delta_radius_mm": radii,
        "tower_angles_deg": angles,
        "print_radius_mm": print_radius,
        "min_arm_angle_deg": min_arm_angle,
        "z_min_mm": get("printer", "minimum_z_position", 0.0),
        "z_max_mm": min(get(f"stepper_{t}", "position_endstop", get("stepper_a", "position_endstop"))
                        for t in "abc" if cp.has_section(f"stepper_{t}")),
    }
    limits = {
        "max_velocity_mm_s": max_v,
        "max_accel_mm_s2": max_a,
        "max_z_velocity_mm_s": get("printer", "max_z_velocity", max_v),
        "max_z_accel_mm_s2": get("printer", "max_z_accel", max_a),
        "square_corner_velocity_mm_s": get("printer", "square_corner_velocity", 5.0),
        "planner": "klipper",
    }
    if cp.has_option("printer", "minimum_cruise_ratio"):
        limits["minimum_cruise_ratio"] = get("printer", "minimum_cruise_ratio")
    elif cp.has_option("printer", "max_accel_to_decel"):
        limits["minimum_cruise_ratio"] = max(0.0, 1.0 - get("printer", "max_accel_to_decel") / max_a)
    if cp.has_option("stepper_a", "rotation_distance"):
        rd = get("stepper_a", "rotation_distance")
        micro = int(get("stepper_a", "microsteps", 16.0))
        full = get("stepper_a", "full_steps_per_rotation", 200.0)
        limits["steps_per_mm"] = full * micro / rd
        limits["microsteps"] = micro
    if cp.has_section("extruder"):
        limits["instantaneous_corner_velocity_mm_s"] = get("extruder", "instantaneous_corner_velocity", 1.0)
        # the extruder-only limits time every retraction; Klipper's defaults scale the toolhead's by the
        # default cross-section ratio 4 nozzle^2 / filament area (klippy/kinematics/extruder.py)
        ratio = None
        if cp.has_option("extruder", "nozzle_diameter") and cp.has_option("extruder", "filament_diameter"):
            ratio = 4.0 * get("extruder", "nozzle_diameter") ** 2 / (
                math.pi * (0.5 * get("extruder", "filament_diameter")) ** 2)
        for key, toolhead in (("max_extrude_only_velocity", max_v), ("max_extrude_only_accel", max_a)):
            unit = "_mm_s" if key.endswith("velocity") else "_mm_s2"
            if cp.has_option("extruder", key):
                limits[key + unit] = get("extruder", key)
            elif ratio is not None:
                limits[key + unit] = toolhead * ratio
    # the chords Klipper makes of G2/G3 (without the section Klipper refuses them; its default then)
    limits["arc_resolution_mm"] = get("gcode_arcs", "resolution", 1.0)
    sections: dict = {"firmware_retraction": None}  # without the section Klipper has no G10/G11
    if cp.has_section("firmware_retraction"):  # G10/G11 then run as Klipper makes them (its defaults)
        sections["firmware_retraction"] = {
            f"{k}_mm" if "length" in k else f"{k}_mm_s": get("firmware_retraction", k, dflt)
            for k, dflt in (("retract_length", 0.0), ("retract_speed", 20.0), ("unretract_extra_length", 0.0),
                            ("unretract_speed", 10.0))}
    sections["input_shaper"] = None  # without the section Klipper does not shape
    if cp.has_section("input_shaper"):  # the compensated file switches it off and back on to these
        both = cp.get("input_shaper", "shaper_type", fallback="mzv").strip().lower()
        sections["input_shaper"] = {}
        for a in "xyz":  # (z: recent Klipper's optional z shaper)
            sections["input_shaper"].update({
                f"shaper_type_{a}": cp.get("input_shaper", f"shaper_type_{a}", fallback=both).strip().lower(),
                f"shaper_freq_{a}_hz": get("input_shaper", f"shaper_freq_{a}", 0.0),
                f"damping_ratio_{a}": get("input_shaper", f"damping_ratio_{a}", 0.1)})
    return _merge(base, geom, limits, f"Klipper delta from {Path(path).name}", path, sections)


#: a parameter letter and its value: everything up to white space or the next letter that starts a
#: number (``L250R130``), so that ``L abc`` reads as L = "abc" (not a number) rather than as missing
_M665_WORD = re.compile(r"([A-Za-z])\s*(\S*?)(?=\s|[A-Za-z][-+.\d]|$)")


def from_m665(line: str, base: PrinterProfile | None = None, *, print_radius_mm: float | None = None,
              firmware: str = "marlin") -> PrinterProfile:
    """Profile from a Marlin / RepRapFirmware ``M665`` line.

    ``X``, ``Y``, ``Z`` are tower angle corrections in degrees added to 210/330/90; ``R`` the
    delta radius, ``L`` the diagonal rod (``L250:251:249`` per tower on RRF), ``B`` the printable
    (RRF) or calibration (Marlin) radius, used as print radius unless ``print_radius_mm`` is given,
    ``H`` the homed height (taken as ``z_max_mm``).  Without ``B`` the print radius must be given
    (``print_radius_mm``): a default would be another printer's.
    """
    base = base or default_profile()
    text = line.split(";")[0].strip()
    if not text.upper().startswith("M665"):
        raise ProfileError("M665", line, "expected a line starting with M665")
    words = {}
    for letter, val in _M665_WORD.findall(text[4:]):
        if letter.upper() in words:
            raise ProfileError(f"M665 {letter.upper()}", val, "given twice")
        words[letter.upper()] = val
    def num(letter, default=None):
        if letter not in words:
            if default is None:
                raise ProfileError(f"M665 {letter}", None, "missing", None)
            return default
        try:
            v = float(words[letter])
        except ValueError:
            raise ProfileError(f"M665 {letter}", words[letter], "not a number") from None
        if not math.isfinite(v):
            raise ProfileError(f"M665 {letter}", words[letter], "not a finite number")
        return v
    if "L" in words and ":" in words["L"]:
        try:
            arms = [float(v) for v in words["L"].split(":")]
        except ValueError:
            raise ProfileError("M665 L", words["L"], "not a number list") from None
        if len(arms) != 3:
            raise ProfileError("M665 L", words["L"], "expected one or three diagonal rod lengths")
    else:
        arms = [num("L")] * 3
    radius = num("R")
    corr = [num("X", 0.0), num("Y", 0.0), num("Z", 0.0)]
    angles = [a + c for a, c in zip(FIRMWARE_TOWER_ANGLES_DEG, corr)]
    geom = {"arm_length_mm": arms, "delta_radius_mm": radius, "tower_angles_deg": angles}
    if print_radius_mm is not None:
        geom["print_radius_mm"] = print_radius_mm
    elif "B" in words:
        geom["print_radius_mm"] = num("B")
    else:
        raise ProfileError("M665 B", None, "missing: the print radius is unknown (give B in the M665 line, "
                           "or --print-radius)")
    if "H" in words:
        geom["z_max_mm"] = num("H")
    prof = _merge(base, geom, {"planner": "marlin"} if firmware == "marlin" else {},
                  f"{firmware} delta from M665", "M665")
    return replace(prof, source=None)
