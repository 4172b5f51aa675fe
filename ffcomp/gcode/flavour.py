"""Which firmware a G-code file was sliced for, from what the slicer wrote into it.

PrusaSlicer, SuperSlicer, OrcaSlicer and Slic3r write ``; gcode_flavor = marlin2`` into the config
block at the end of the file; Cura writes ``;FLAVOR:Marlin`` in the first lines.  Only the head and
tail of the file are read.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["Flavour", "detect_flavour", "flavour_mismatch"]

_HEAD_BYTES = 64 * 1024
_TAIL_BYTES = 512 * 1024
_SLIC3R = re.compile(rb"^;\s*gcode_flavor\s*=\s*([A-Za-z0-9_\-]+)", re.M)
_CURA = re.compile(rb"^;\s*FLAVOR:\s*([^\r\n]+)", re.M)

#: slicer flavour name (lower case) -> firmware family
_FAMILY = {
    "klipper": "klipper",
    "marlin": "marlin", "marlin2": "marlin", "marlinlegacy": "marlin", "marlinfirmware": "marlin",
    "reprap (marlin/sprinter)": "marlin", "marlin (volumetric)": "marlin",
    "reprap": "reprap", "reprapfirmware": "reprap", "reprap (reprap)": "reprap", "reprap (volumetric)": "reprap",
}


@dataclass(frozen=True)
class Flavour:
    """A flavour declaration found in a file.

    Attributes
    ----------
    name : str
        As the slicer wrote it (``marlin2``, ``Marlin``, ``klipper``).
    family : str
        ``klipper``, ``marlin``, ``reprap``, or the lower-cased name for any other firmware.
    line : int
        1-based line number of the declaration (counted in the part of the file read; for the tail,
        the number is counted from the end and given as a negative offset if the file is large).
    text : str
        The declaring line.
    """

    name: str
    family: str
    line: int
    text: str


def _find(buf: bytes, base_line: int | None) -> Flavour | None:
    for rx in (_CURA, _SLIC3R):
        m = rx.search(buf)
        if m:
            name = m.group(1).decode("utf-8", "replace").strip()
            family = _FAMILY.get(name.lower(), name.lower())
            end = buf.find(b"\n", m.start())
            text = buf[m.start():end if end >= 0 else len(buf)].decode("utf-8", "replace").strip()
            line = (base_line or 0) + buf.count(b"\n", 0, m.start()) + 1
            return Flavour(name, family, line, text)
    return None


def detect_flavour(path: str) -> Flavour | None:
    """The flavour a slicer declared in ``path`` (``None`` if it declares none)."""
    with open(path, "rb") as f:
        head = f.read(_HEAD_BYTES)
        found = _find(head, 0)
        if found:
            return found
        f.seek(0, 2)
        size = f.tell()
        if size <= _HEAD_BYTES:
            return None
        start = max(_HEAD_BYTES, size - _TAIL_BYTES)
        # count the lines before the tail so the line number is exact
        f.seek(0)
        n_before = 0
        left = start
        while left > 0:
            b = f.read(min(1 << 20, left))
            if not b:
                break
            n_before += b.count(b"\n")
            left -= len(b)
        tail = f.read()
    return _find(tail, n_before)


def flavour_mismatch(flavour: Flavour | None, planner: str, path: str, profile_name: str) -> str | None:
    """A warning when the file was sliced for a different firmware than the profile drives."""
    if flavour is None or flavour.family == planner:
        return None
    head = ("SET_VELOCITY_LIMIT (a Klipper command)" if planner == "klipper" else "M204/M201 (Marlin commands)")
    if flavour.family == "marlin" and planner == "klipper":
        advice = ("Klipper runs Marlin-flavoured G-code, so nothing is wrong if this printer runs Klipper; if it "
                  "runs Marlin, use a profile with planner = \"marlin\".")
    elif flavour.family in ("klipper", "marlin"):
        advice = (f"Use a profile with planner = \"{flavour.family}\" if the printer runs {flavour.family}, "
                  f"or re-slice for {planner}.")
    else:
        advice = "ffcomp times files for klipper or marlin only: re-slice for the printer's firmware."
    return (f"{path}:{flavour.line}: the file was sliced for {flavour.name} ({flavour.text!r}) but the "
            f"profile '{profile_name}' is for {planner}: ffcomp times the moves with {planner}'s planner and a "
            f"compensated output's header sets {head}. {advice}")
