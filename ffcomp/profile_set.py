"""Edit profile values from the command line: ``ffcomp profile set P.toml KEY=VALUE ...``.

Keys are ``section.key`` (``geometry.delta_radius_mm=155``, ``dynamics.k=81000``), per-tower
values as three comma-separated numbers (``geometry.tower_angles_deg=0,120,240``), ``name=TEXT``,
or an effect parameter ``effects.NAME.PARAM=VALUE``.  The edited profile goes through the same
validation as a loaded one (:func:`ffcomp.profile.profile_from_dict`), so a bad value is refused
with the key, the value and the reason, and nothing is written.

Frames: firmware (Klipper, Marlin, RRF) puts towers A/B/C at 210/330/90 deg; the paper and the FRF
file format at 0/120/240 (tower A on +x).  :func:`to_frame` rotates a profile between them.
"""

from __future__ import annotations

import copy

from .errors import ProfileError
from .profile import PrinterProfile, profile_from_dict

__all__ = ["parse_value", "set_values", "to_frame", "FRAMES"]

FRAMES = {"paper": (0.0, 120.0, 240.0), "firmware": (210.0, 330.0, 90.0)}


def parse_value(text: str):
    """``"155"`` -> 155.0, ``"0,120,240"`` -> [0.0, 120.0, 240.0]; anything else stays a string."""
    parts = [p.strip() for p in text.split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        return text
    return vals if len(vals) > 1 else vals[0]


def set_values(profile: PrinterProfile, assignments) -> PrinterProfile:
    """A copy of ``profile`` with ``KEY=VALUE`` assignments applied and validated.

    Raises
    ------
    ProfileError
        Unknown key, malformed assignment, or a value the profile rules refuse.
    """
    raw = copy.deepcopy(profile.to_dict())
    for a in assignments:
        key, eq, text = a.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ProfileError(a, None, "expected KEY=VALUE, e.g. geometry.delta_radius_mm=155", profile.source)
        if key == "name":
            raw["name"] = text
            continue
        parts = key.split(".")
        value = parse_value(text.strip())
        if parts[0] == "effects" and len(parts) == 3:
            hits = [e for e in raw.get("effects", []) if e.get("name") == parts[1]]
            if not hits:
                raise ProfileError(key, text, f"the profile has no effect {parts[1]!r}", profile.source)
            hits[0][parts[2]] = value
            continue
        if len(parts) != 2 or parts[0] not in ("geometry", "limits", "dynamics"):
            raise ProfileError(key, text, "expected section.key with section geometry, limits or dynamics, "
                               "name, or effects.NAME.PARAM", profile.source)
        sec, k = parts
        if k not in raw[sec]:
            raise ProfileError(key, text, f"unknown key (known in [{sec}]: {', '.join(sorted(raw[sec]))})",
                               profile.source)
        raw[sec][k] = value
    return profile_from_dict(raw, profile.source)


def to_frame(profile: PrinterProfile, frame: str) -> PrinterProfile:
    """``profile`` with its tower angles in ``frame`` (``paper`` or ``firmware``), corrections kept.

    The angles are rotated by the difference between the frames' tower-A angles, so per-tower
    corrections (e.g. 210.3/330/90) survive: 0.3/120/240 in the paper frame.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    ang = profile.geometry.tower_angles_deg
    cur = min(FRAMES, key=lambda f: sum(abs(((a - b + 180.0) % 360.0) - 180.0) for a, b in zip(ang, FRAMES[f])))
    rot = FRAMES[frame][0] - FRAMES[cur][0]
    new = tuple(float(round((a + rot) % 360.0, 9)) for a in ang)
    from dataclasses import replace

    return profile.with_(geometry=replace(profile.geometry, tower_angles_deg=new))
