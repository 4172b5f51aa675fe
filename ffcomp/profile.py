"""Printer profiles: geometry, motion limits and dynamics, loaded from and saved to TOML.

A profile is the one description of a printer every stage uses.  The TOML file is in user units
(mm, mm/s, mm/s^2, Hz; dynamics in SI: kg, N/m, N s/m); :class:`PrinterProfile` keeps those values as
read and offers SI views (:meth:`PrinterProfile.geometry_si`) for the numeric kernels.

Every value is validated on load, and an error names the dotted key, the value and the reason.
The keys in :data:`REQUIRED` must be given (a default for them would describe another printer);
``ffcomp_profile``, when present, must be the format version this ffcomp reads (1).

Sections
--------
``[geometry]``
    ``arm_length_mm`` (scalar or 3 values), ``delta_radius_mm`` (scalar or 3), ``tower_angles_deg``
    (3 values, counter-clockwise from +x; the paper puts A at 0, Klipper/Marlin at 210/330/90),
    ``effector_offset_z_mm`` (H_ez), ``print_radius_mm``, ``z_min_mm``, ``z_max_mm``,
    ``min_arm_angle_deg``.
``[limits]``
    ``max_velocity_mm_s``, ``max_accel_mm_s2``, ``max_z_velocity_mm_s``, ``max_z_accel_mm_s2``,
    ``square_corner_velocity_mm_s``, ``minimum_cruise_ratio``, ``junction_deviation_mm`` (Marlin),
    ``instantaneous_corner_velocity_mm_s`` (Klipper's extruder junction limit),
    ``max_extrude_only_velocity_mm_s``, ``max_extrude_only_accel_mm_s2``, the compensated command's bounds
    ``max_carriage_velocity_mm_s``, ``max_carriage_accel_mm_s2``, ``max_correction_mm``, ``planner`` (``"klipper"`` or
    ``"marlin"``), ``steps_per_mm`` (microsteps included),
    ``microsteps``, ``sample_rate_hz``, ``arc_resolution_mm`` (the chord length G2/G3 arcs are split
    into: Klipper's ``[gcode_arcs] resolution``, default 1 mm; at least 0.01 mm).
``[dynamics]``
    Carriage sub-model (scalar, or 3 values for per-tower parameters): ``m`` (kg), ``c`` (belt
    damping, N s/m), ``b`` (guide friction, N s/m), ``k`` (belt stiffness, N/m), electrical
    ``d0`` (1/s^2), ``d1`` (1/s), ``d2`` (1/s); effector side: ``m_n`` (kg), ``m_f`` (mass of one
    forearm pair, kg), ``b_nt`` (N s/m).
``[firmware_retraction]``
    Optional: the printer's Klipper ``[firmware_retraction]`` values, ``retract_length_mm``,
    ``retract_speed_mm_s``, ``unretract_extra_length_mm``, ``unretract_speed_mm_s`` (Klipper's defaults
    0, 20, 0, 10 for the keys not given).  With it, ``G10``/``G11`` are timed as the extruder-only moves
    the firmware makes of them; without it they are stops (:mod:`ffcomp.gcode.commands`).
``[input_shaper]``
    Optional: the printer's Klipper ``[input_shaper]`` values, ``shaper_type_x``, ``shaper_type_y``,
    ``shaper_type_z`` (``zv``, ``mzv``, ``zvd``, ``ei``, ``2hump_ei``, ``3hump_ei``; Klipper's default
    ``mzv``), ``shaper_freq_x_hz``, ``shaper_freq_y_hz``, ``shaper_freq_z_hz`` (0: off; z is recent
    Klipper's optional z shaper), ``damping_ratio_x``, ``damping_ratio_y``, ``damping_ratio_z``
    (default 0.1).  A compensated file switches the firmware's input shaping off (the compensation
    is the shaping: a shaper on top smears it); with this section it switches it back on at its end.
``[[effects]]``
    Optional physical effects beyond the paper's model: ``name`` plus that effect's parameters.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import tomllib

from .errors import ProfileError
from .kinematics import DeltaGeometry, arm_heights

__all__ = [
    "Geometry",
    "Limits",
    "Dynamics",
    "FirmwareRetraction",
    "InputShaper",
    "SHAPER_TYPES",
    "PrinterProfile",
    "load_profile",
    "default_profile",
    "save_profile",
    "profile_to_toml",
    "PLANNERS",
]

PLANNERS = ("klipper", "marlin")


def _tri(v) -> tuple[float, float, float]:
    """Scalar or 3-sequence -> 3-tuple of floats."""
    a = np.broadcast_to(np.asarray(v, dtype=float), (3,))
    return (float(a[0]), float(a[1]), float(a[2]))


@dataclass(frozen=True)
class Geometry:
    """Delta geometry in mm and degrees (user units; see :meth:`to_si`)."""

    arm_length_mm: tuple[float, float, float] = (330.0, 330.0, 330.0)
    delta_radius_mm: tuple[float, float, float] = (160.0, 160.0, 160.0)
    tower_angles_deg: tuple[float, float, float] = (0.0, 120.0, 240.0)
    effector_offset_z_mm: float = 25.0
    print_radius_mm: float = 135.0
    z_min_mm: float = 0.0
    z_max_mm: float = 300.0
    min_arm_angle_deg: float = 15.0

    def to_si(self) -> DeltaGeometry:
        return DeltaGeometry.from_radius(
            np.asarray(self.arm_length_mm) * 1e-3,
            np.asarray(self.delta_radius_mm) * 1e-3,
            self.tower_angles_deg,
            effector_offset_z_m=self.effector_offset_z_mm * 1e-3,
            print_radius_m=self.print_radius_mm * 1e-3,
            z_min_m=self.z_min_mm * 1e-3,
            z_max_m=self.z_max_mm * 1e-3,
            min_arm_angle_deg=self.min_arm_angle_deg,
        )


@dataclass(frozen=True)
class Limits:
    """Motion limits and firmware settings (mm, s)."""

    max_velocity_mm_s: float = 300.0
    max_accel_mm_s2: float = 10000.0
    max_z_velocity_mm_s: float = 300.0
    max_z_accel_mm_s2: float = 10000.0
    square_corner_velocity_mm_s: float = 5.0
    minimum_cruise_ratio: float = 0.5
    junction_deviation_mm: float = 0.013
    instantaneous_corner_velocity_mm_s: float = 1.0
    max_extrude_only_velocity_mm_s: float = 120.0
    max_extrude_only_accel_mm_s2: float = 3000.0
    max_carriage_velocity_mm_s: float = 900.0
    max_carriage_accel_mm_s2: float = 60000.0
    max_correction_mm: float = 2.0
    planner: str = "klipper"
    steps_per_mm: float = 80.0
    microsteps: int = 16
    sample_rate_hz: float = 1000.0
    #: the firmware's arc chord length (Klipper ``[gcode_arcs] resolution``): G2/G3 are planned as the
    #: chords the firmware makes of them, and the compensated output keeps that path
    arc_resolution_mm: float = 1.0


@dataclass(frozen=True)
class Dynamics:
    """Parameters of the paper's two sub-models (SI).  Carriage terms are per tower."""

    m: tuple[float, float, float] = (0.177, 0.177, 0.177)
    c: tuple[float, float, float] = (5.87, 5.87, 5.87)
    b: tuple[float, float, float] = (18.0, 18.0, 18.0)
    k: tuple[float, float, float] = (9.44e4, 9.44e4, 9.44e4)
    d0: tuple[float, float, float] = (1.43e5, 1.43e5, 1.43e5)
    d1: tuple[float, float, float] = (-212.1, -212.1, -212.1)
    d2: tuple[float, float, float] = (36.2, 36.2, 36.2)
    m_n: float = 0.156
    m_f: float = 0.032
    b_nt: float = 27.9

    @property
    def m_nt(self) -> float:
        """Effector plus half of each forearm pair, ``m_n + 3 m_f / 2`` (Eq. 28), kg."""
        return self.m_n + 1.5 * self.m_f


@dataclass(frozen=True)
class FirmwareRetraction:
    """Klipper's ``[firmware_retraction]`` (mm, mm/s; its defaults): what ``G10``/``G11`` make the
    extruder do (``SET_RETRACTION`` in a file changes them from there on)."""

    retract_length_mm: float = 0.0
    retract_speed_mm_s: float = 20.0
    unretract_extra_length_mm: float = 0.0
    unretract_speed_mm_s: float = 10.0


#: Klipper's input shaper names (``klippy/extras/shaper_defs.py``)
SHAPER_TYPES = ("zv", "mzv", "zvd", "ei", "2hump_ei", "3hump_ei")


@dataclass(frozen=True)
class InputShaper:
    """Klipper's ``[input_shaper]`` (its defaults): what the printer shapes X and Y with when no
    compensated file is running (a compensated file switches it off and, with these values, back on)."""

    shaper_type_x: str = "mzv"
    shaper_type_y: str = "mzv"
    shaper_freq_x_hz: float = 0.0
    shaper_freq_y_hz: float = 0.0
    damping_ratio_x: float = 0.1
    damping_ratio_y: float = 0.1
    #: Klipper's optional z shaper (recent versions): off unless its frequency is set
    shaper_type_z: str = "mzv"
    shaper_freq_z_hz: float = 0.0
    damping_ratio_z: float = 0.1

    def klipper_command(self) -> str:
        """The ``SET_INPUT_SHAPER`` line that restores these values (z only where it is set)."""
        axes = "xyz" if self.shaper_freq_z_hz > 0 else "xy"
        return "SET_INPUT_SHAPER " + " ".join(
            f"SHAPER_TYPE_{a.upper()}={getattr(self, f'shaper_type_{a}')} "
            f"SHAPER_FREQ_{a.upper()}={getattr(self, f'shaper_freq_{a}_hz'):g} "
            f"DAMPING_RATIO_{a.upper()}={getattr(self, f'damping_ratio_{a}'):g}" for a in axes)


_PER_TOWER = {"arm_length_mm", "delta_radius_mm", "tower_angles_deg", "m", "c", "b", "k", "d0", "d1", "d2"}


@dataclass(frozen=True)
class PrinterProfile:
    """A complete printer description.

    Attributes
    ----------
    name : str
    geometry : Geometry
    limits : Limits
    dynamics : Dynamics
    effects : tuple of dict
        Extra physical effects, each ``{"name": ..., <parameter>: value, ...}``; interpreted by
        :mod:`ffcomp.model.effects`.
    source : str or None
        File the profile was loaded from (for error messages).
    firmware_retraction : FirmwareRetraction or None
        Optional section: the firmware's G10/G11 settings (None: G10/G11 are stops).
    input_shaper : InputShaper or None
        Optional section: the firmware's input shaper, restored at the end of a compensated file
        (None: the file switches shaping off and leaves it off).
    start_position_mm : (x, y, z) or None
        Optional top-level key: where the toolhead stands when a file that moves before any G28
        starts (e.g. where the printer's ``PRINT_START`` macro leaves it); ``--start`` overrides it.
    """

    name: str = "unnamed delta"
    geometry: Geometry = field(default_factory=Geometry)
    limits: Limits = field(default_factory=Limits)
    dynamics: Dynamics = field(default_factory=Dynamics)
    effects: tuple = ()
    source: str | None = None
    start_position_mm: tuple | None = None
    firmware_retraction: FirmwareRetraction | None = None
    input_shaper: InputShaper | None = None

    def geometry_si(self) -> DeltaGeometry:
        return self.geometry.to_si()

    def with_(self, **kw) -> "PrinterProfile":
        return replace(self, **kw)

    def to_dict(self) -> dict[str, Any]:
        d = {
            "name": self.name,
            "geometry": asdict(self.geometry),
            "limits": asdict(self.limits),
            "dynamics": asdict(self.dynamics),
        }
        for sec in ("geometry", "dynamics"):
            for k, v in d[sec].items():
                if isinstance(v, tuple):
                    d[sec][k] = list(v) if len(set(v)) > 1 else v[0]
        if self.effects:
            d["effects"] = [dict(e) for e in self.effects]
        if self.start_position_mm is not None:
            d["start_position_mm"] = list(self.start_position_mm)
        if self.firmware_retraction is not None:
            d["firmware_retraction"] = asdict(self.firmware_retraction)
        if self.input_shaper is not None:
            d["input_shaper"] = asdict(self.input_shaper)
        return d


# --------------------------------------------------------------------------- validation

def _num(sec: str, key: str, v, source, *, positive=False, nonneg=False, lo=None, hi=None):
    name = f"{sec}.{key}"
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ProfileError(name, v, "expected a number", source)
    v = float(v)
    if not math.isfinite(v):
        raise ProfileError(name, v, "must be finite", source)
    if positive and v <= 0:
        raise ProfileError(name, v, "must be > 0", source)
    if nonneg and v < 0:
        raise ProfileError(name, v, "must be >= 0", source)
    if lo is not None and v < lo:
        raise ProfileError(name, v, f"must be >= {lo}", source)
    if hi is not None and v > hi:
        raise ProfileError(name, v, f"must be <= {hi}", source)
    return v


def _value(sec, key, v, source, **kw):
    if key in _PER_TOWER:
        if isinstance(v, (list, tuple)):
            if len(v) != 3:
                raise ProfileError(f"{sec}.{key}", v, "expected a number or a list of 3 numbers", source)
            return tuple(_num(sec, f"{key}[{i}]", x, source, **kw) for i, x in enumerate(v))
        return _tri(_num(sec, key, v, source, **kw))
    return _num(sec, key, v, source, **kw)


_RULES: dict[str, dict[str, dict]] = {
    "geometry": {
        "arm_length_mm": {"positive": True},
        "delta_radius_mm": {"positive": True},
        "tower_angles_deg": {},
        "effector_offset_z_mm": {},
        "print_radius_mm": {"positive": True},
        "z_min_mm": {},
        "z_max_mm": {},
        "min_arm_angle_deg": {"lo": 0.0, "hi": 89.0},
    },
    "limits": {
        "max_velocity_mm_s": {"positive": True},
        "max_accel_mm_s2": {"positive": True},
        "max_z_velocity_mm_s": {"positive": True},
        "max_z_accel_mm_s2": {"positive": True},
        "square_corner_velocity_mm_s": {"nonneg": True},
        "minimum_cruise_ratio": {"lo": 0.0, "hi": 0.99},
        "junction_deviation_mm": {"positive": True},
        "instantaneous_corner_velocity_mm_s": {"nonneg": True},
        "max_extrude_only_velocity_mm_s": {"positive": True},
        "max_extrude_only_accel_mm_s2": {"positive": True},
        "max_carriage_velocity_mm_s": {"positive": True},
        "max_carriage_accel_mm_s2": {"positive": True},
        "max_correction_mm": {"positive": True},
        "steps_per_mm": {"positive": True},
        "microsteps": {"positive": True},
        "sample_rate_hz": {"lo": 100.0, "hi": 100000.0},
        "arc_resolution_mm": {"lo": 0.01},
    },
    "dynamics": {
        "m": {"positive": True},
        "c": {"nonneg": True},
        "b": {"nonneg": True},
        "k": {"positive": True},
        "d0": {"positive": True},
        "d1": {},
        "d2": {"positive": True},
        "m_n": {"positive": True},
        "m_f": {"nonneg": True},
        "b_nt": {"nonneg": True},
    },
    # Klipper's minimums: lengths >= 0, speeds >= 1 mm/s
    "firmware_retraction": {
        "retract_length_mm": {"nonneg": True},
        "retract_speed_mm_s": {"lo": 1.0},
        "unretract_extra_length_mm": {"nonneg": True},
        "unretract_speed_mm_s": {"lo": 1.0},
    },
    # Klipper's: frequencies >= 0 (0: off), damping ratios in [0, 1)
    "input_shaper": {
        "shaper_freq_x_hz": {"nonneg": True},
        "shaper_freq_y_hz": {"nonneg": True},
        "shaper_freq_z_hz": {"nonneg": True},
        "damping_ratio_x": {"nonneg": True, "hi": 0.99},
        "damping_ratio_y": {"nonneg": True, "hi": 0.99},
        "damping_ratio_z": {"nonneg": True, "hi": 0.99},
    },
}
_CLASSES = {"geometry": Geometry, "limits": Limits, "dynamics": Dynamics,
            "firmware_retraction": FirmwareRetraction, "input_shaper": InputShaper}

#: the profile format version this ffcomp reads and writes (top-level ``ffcomp_profile``)
PROFILE_VERSION = 1

#: keys a profile must give: a printer is not described without them, and a default taken silently
#: for one of them (the paper's stiffness, the paper's tower frame) would mis-time every move
REQUIRED: dict[str, tuple[str, ...]] = {
    "geometry": ("arm_length_mm", "delta_radius_mm", "tower_angles_deg", "print_radius_mm", "z_max_mm"),
    "limits": ("max_velocity_mm_s", "max_accel_mm_s2", "planner"),
    "dynamics": ("m", "c", "b", "k", "d0", "d1", "d2", "m_n", "m_f", "b_nt"),
}

#: optional limits whose default is another limit, as in Klipper (``max_z_velocity`` defaults to
#: ``max_velocity``, ``max_z_accel`` to ``max_accel``)
_DEFAULT_FROM = {"max_z_velocity_mm_s": "max_velocity_mm_s", "max_z_accel_mm_s2": "max_accel_mm_s2"}


def _section(raw: dict, sec: str, source) -> Any:
    cls = _CLASSES[sec]
    data = raw.get(sec, {})
    if not isinstance(data, dict):
        raise ProfileError(sec, data, "expected a table", source)
    known = {f.name for f in fields(cls)}
    kw = {}
    for key, v in data.items():
        if key not in known:
            raise ProfileError(f"{sec}.{key}", v, f"unknown key (known: {', '.join(sorted(known))})", source)
        if sec == "limits" and key == "planner":
            if v not in PLANNERS:
                raise ProfileError("limits.planner", v, f"must be one of {PLANNERS}", source)
            kw[key] = v
        elif sec == "input_shaper" and key.startswith("shaper_type_"):
            if not isinstance(v, str) or v.lower() not in SHAPER_TYPES:
                raise ProfileError(f"input_shaper.{key}", v, f"must be one of {', '.join(SHAPER_TYPES)}", source)
            kw[key] = v.lower()
        elif sec == "limits" and key == "microsteps":
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ProfileError("limits.microsteps", v, "must be a positive integer", source)
            kw[key] = v
        else:
            kw[key] = _value(sec, key, v, source, **_RULES[sec][key])
    if any(k not in kw for k in REQUIRED.get(sec, ())):
        return None  # the values given are checked first; :func:`_require` names what is missing
    if sec == "limits":
        for key, other in _DEFAULT_FROM.items():
            kw.setdefault(key, kw[other])
    return cls(**kw)


def _require(raw: dict, source) -> None:
    """Name the first required key (or section) the profile lacks: no silent defaults for them."""
    for sec, keys in REQUIRED.items():
        if sec not in raw:
            raise ProfileError(sec, None, f"section [{sec}] missing (required keys: {', '.join(keys)})", source)
        missing = [k for k in keys if k not in raw[sec]]
        if missing:
            also = f" (also missing: {', '.join(missing[1:])})" if missing[1:] else ""
            raise ProfileError(f"{sec}.{missing[0]}", None, f"required key missing{also}", source)


def _check_geometry(g: Geometry, source) -> None:
    if g.z_max_mm <= g.z_min_mm:
        raise ProfileError("geometry.z_max_mm", g.z_max_mm, f"must exceed z_min_mm = {g.z_min_mm}", source)
    ang = np.asarray(g.tower_angles_deg)
    for i in range(3):
        for j in range(i + 1, 3):
            sep = abs((ang[i] - ang[j] + 180.0) % 360.0 - 180.0)
            if sep < 30.0:
                raise ProfileError("geometry.tower_angles_deg", list(g.tower_angles_deg),
                                   f"towers {i} and {j} are only {sep:.1f} deg apart", source)
    R = np.asarray(g.delta_radius_mm)
    L = np.asarray(g.arm_length_mm)
    worst = R + g.print_radius_mm  # the farthest a nozzle gets from a tower's joint line
    for i in range(3):
        if L[i] <= worst[i]:
            raise ProfileError(
                f"geometry.arm_length_mm[{i}]", float(L[i]),
                f"arm shorter than needed: must exceed delta_radius + print_radius = {worst[i]:.3f} mm "
                "to reach the far edge of the print radius", source)
    # every pose on the rim must keep the arms above min_arm_angle_deg
    geo = g.to_si()
    th = np.linspace(0.0, 2.0 * np.pi, 361)
    rim = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1) * g.print_radius_mm * 1e-3
    h = arm_heights(geo, rim)
    min_h = geo.arm_length_m * math.sin(math.radians(g.min_arm_angle_deg))
    bad = np.argwhere(~(h >= min_h[None, :]))
    if bad.size:
        k, i = bad[0]
        ang_deg = math.degrees(math.asin(min(1.0, float(h[k, i]) / geo.arm_length_m[i]))) if np.isfinite(
            h[k, i]) else float("nan")
        raise ProfileError(
            "geometry.print_radius_mm", g.print_radius_mm,
            f"unreachable workspace: at ({rim[k, 0] * 1e3:.1f}, {rim[k, 1] * 1e3:.1f}) mm arm {i} stands at "
            f"{ang_deg:.1f} deg, below min_arm_angle_deg = {g.min_arm_angle_deg}", source)


def _check_limits(lim: Limits, source) -> None:
    if lim.max_z_velocity_mm_s > lim.max_velocity_mm_s:
        raise ProfileError("limits.max_z_velocity_mm_s", lim.max_z_velocity_mm_s,
                           f"exceeds max_velocity_mm_s = {lim.max_velocity_mm_s}", source)
    if lim.max_z_accel_mm_s2 > lim.max_accel_mm_s2:
        raise ProfileError("limits.max_z_accel_mm_s2", lim.max_z_accel_mm_s2,
                           f"exceeds max_accel_mm_s2 = {lim.max_accel_mm_s2}", source)


def _start_position(v, g: Geometry, source) -> tuple | None:
    """The optional ``start_position_mm = [x, y, z]``: three numbers inside the print volume."""
    if v is None:
        return None
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise ProfileError("start_position_mm", v, "expected a list of 3 numbers [x, y, z] in mm", source)
    for i, c in enumerate(v):
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not math.isfinite(c):
            raise ProfileError(f"start_position_mm[{i}]", c, "expected a finite number", source)
    x, y, z = (float(c) for c in v)
    if math.hypot(x, y) > g.print_radius_mm or not g.z_min_mm <= z <= g.z_max_mm:
        raise ProfileError("start_position_mm", v, f"outside the print volume (radius {g.print_radius_mm:g} mm, "
                           f"z {g.z_min_mm:g}..{g.z_max_mm:g} mm)", source)
    return (x, y, z)


def profile_from_dict(raw: dict, source: str | None = None) -> PrinterProfile:
    """Validate a parsed TOML document and build a :class:`PrinterProfile`."""
    if not isinstance(raw, dict):
        raise ProfileError("<root>", raw, "expected a table", source)
    allowed = {"name", "geometry", "limits", "dynamics", "effects", "ffcomp_profile", "start_position_mm",
               "firmware_retraction", "input_shaper"}
    for key in raw:
        if key not in allowed:
            raise ProfileError(key, raw[key], f"unknown top-level key (known: {', '.join(sorted(allowed))})",
                               source)
    version = raw.get("ffcomp_profile", PROFILE_VERSION)
    if isinstance(version, bool) or not isinstance(version, int) or version != PROFILE_VERSION:
        raise ProfileError("ffcomp_profile", version, f"unsupported profile format version: this ffcomp "
                           f"reads version {PROFILE_VERSION}", source)
    name = raw.get("name", Path(source).stem if source else "unnamed delta")
    if not isinstance(name, str):
        raise ProfileError("name", name, "expected a string", source)
    geometry = _section(raw, "geometry", source)
    limits = _section(raw, "limits", source)
    dynamics = _section(raw, "dynamics", source)
    _require(raw, source)
    _check_geometry(geometry, source)
    _check_limits(limits, source)
    effects = raw.get("effects", [])
    if not isinstance(effects, list) or not all(isinstance(e, dict) for e in effects):
        raise ProfileError("effects", effects, "expected an array of tables ([[effects]])", source)
    for i, e in enumerate(effects):
        if not isinstance(e.get("name"), str):
            raise ProfileError(f"effects[{i}].name", e.get("name"), "each effect needs a string name", source)
    start = _start_position(raw.get("start_position_mm"), geometry, source)
    retraction = _section(raw, "firmware_retraction", source) if "firmware_retraction" in raw else None
    shaper = _section(raw, "input_shaper", source) if "input_shaper" in raw else None
    prof = PrinterProfile(name=name, geometry=geometry, limits=limits, dynamics=dynamics,
                          effects=tuple(dict(e) for e in effects), source=source, start_position_mm=start,
                          firmware_retraction=retraction, input_shaper=shaper)
    if effects:
        from .model.effects import validate_effects  # effects know their own parameters

        validate_effects(prof)
    return prof


def load_profile(path: str | Path | None = None) -> PrinterProfile:
    """Load and validate a TOML profile; ``None`` gives the embedded default (the paper's printer)."""
    if path is None:
        return default_profile()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ProfileError("<file>", str(path), f"cannot read profile: {e.strerror or e}", str(path)) from e
    except UnicodeDecodeError as e:
        raise ProfileError("<file>", str(path), f"not a text (UTF-8 TOML) file: byte 0x{e.object[e.start]:02x} "
                           f"at offset {e.start} is not UTF-8", str(path)) from e
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ProfileError("<toml>", str(path), f"not valid TOML: {e}", str(path)) from e
    return profile_from_dict(raw, str(path))


def default_profile() -> PrinterProfile:
    """The embedded default: the paper's Monoprice Delta Pro (Table I, assumed geometry)."""
    text = resources.files("ffcomp").joinpath("data/monoprice_delta_pro.toml").read_text(encoding="utf-8")
    return profile_from_dict(tomllib.loads(text), "<embedded monoprice_delta_pro.toml>")


def profile_to_toml(profile: PrinterProfile) -> str:
    import tomli_w

    d = {"ffcomp_profile": 1, **profile.to_dict()}
    return tomli_w.dumps(d)


def save_profile(profile: PrinterProfile, path: str | Path) -> None:
    """Write a profile atomically (temporary file, then rename)."""
    from .io_atomic import atomic_write_text

    atomic_write_text(path, profile_to_toml(profile))
