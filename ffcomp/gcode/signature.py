"""The mark a compensated file carries in its body, and the scan that finds it anywhere in a file.

Compensating a file twice would invert the printer model twice.  The header says the file is
compensated, but a header is easy to lose (a user trims it, a slicer or uploader rewrites the start
of the file), so the body carries the mark too, in two independent ways:

* **explicit**: the writer emits :data:`SIGNATURE_LINE` before its first segment and then again at
  the first run of segments after every :data:`SIGNATURE_EVERY_LINES` body lines;
* **intrinsic**: the writer's segments have a fixed form (``G1 X.4f Y.4f Z.4f [E.5f] F.3f``: every
  axis, four decimals, a feed rate with three decimals) that slicers do not write.  A file in which
  at least :data:`INTRINSIC_MIN_LINES` lines, and at least half of its ``G1`` lines, have that form is
  compensated even when every comment was stripped.

:func:`scan_gcode` reads the file once in binary chunks (C-speed counting; memory bounded by the
chunk), and also counts its lines.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["SIGNATURE", "SIGNATURE_LINE", "SIGNATURE_EVERY_LINES", "INTRINSIC_MIN_LINES", "ScanResult",
           "scan_gcode"]

#: the explicit mark (a comment, so the firmware ignores it)
SIGNATURE = "; ffcomp:sig"
SIGNATURE_LINE = SIGNATURE + " compensated by ffcomp: do not compensate this file again\n"
#: the writer repeats the mark at least this often (body lines)
SIGNATURE_EVERY_LINES = 1000
#: fewest writer-form segment lines that mark a file as compensated (with >= half of its G1 lines)
INTRINSIC_MIN_LINES = 100

_HEADER_START = b"; ffcomp "
_HEADER_TEXT = b"feedforward vibration compensation"
# the writer's segment lines; the leading newline (instead of ^ with re.M) lets the regex engine skip
# ahead to each "\nG1 X" literal, several times faster on slicer files
_SEGMENT = re.compile(rb"\nG1 X-?\d+\.\d{4} Y-?\d+\.\d{4} Z-?\d+\.\d{4}(?: E-?\d+\.\d{5})? F\d+\.\d{3}\r?(?=\n)")
_CHUNK = 1 << 22


@dataclass
class ScanResult:
    """What :func:`scan_gcode` found.

    lines : number of lines (newline characters)
    mark_line : 1-based line of the first explicit mark or ffcomp header, or None
    mark_text : that line's text
    segment_lines, g1_lines : lines of the writer's segment form, and all ``G1`` lines
    """

    lines: int = 0
    mark_line: int | None = None
    mark_text: str = ""
    segment_lines: int = 0
    g1_lines: int = 0

    @property
    def intrinsic(self) -> bool:
        """The body has the writer's segment form throughout (see the module docstring)."""
        return self.segment_lines >= INTRINSIC_MIN_LINES and 2 * self.segment_lines >= self.g1_lines

    @property
    def compensated(self) -> bool:
        return self.mark_line is not None or self.intrinsic


def scan_gcode(path: str) -> ScanResult:
    """Count the lines of ``path`` and look for the marks of a compensated file anywhere in it.

    Stops at the first explicit mark (the line count is then partial)."""
    res = ScanResult()
    carry = b"\n"  # every chunk starts with the newline that ends the previous line (not counted again)
    with open(path, "rb") as f:
        while res.mark_line is None:
            block = f.read(_CHUNK)
            if not block:
                break
            data = carry + block
            cut = data.rfind(b"\n") + 1
            if cut <= 1 and len(data) < 4 * _CHUNK:  # no complete line yet: read on
                carry = data
                continue
            if cut <= 1:
                cut = len(data)
            _scan(data, cut, res)
            carry = data[cut - 1:] if data[cut - 1:cut] == b"\n" else b"\n" + data[cut:]
    if res.mark_line is None and len(carry) > 1:
        _scan(carry + b"\n", len(carry) + 1, res)
        res.lines -= 1
    return res


def _scan(data: bytes, cut: int, res: ScanResult) -> None:
    """Scan ``data[:cut]`` (whole lines; ``data[0]`` is the newline ending the line before)."""
    region = data[:cut]
    sig = region.find(SIGNATURE.encode())
    head = region.find(_HEADER_START)
    while head >= 0:
        eol = region.find(b"\n", head)
        if region.find(_HEADER_TEXT, head, eol if eol >= 0 else cut) >= 0 and region[head - 1:head] == b"\n":
            break
        head = region.find(_HEADER_START, head + 1)
    hits = [h for h in (sig, head) if h >= 0]
    if hits:
        pos = min(hits)
        res.mark_line = res.lines + region.count(b"\n", 1, pos) + 1
        eol = region.find(b"\n", pos)
        res.mark_text = region[pos:eol if eol >= 0 else cut].decode("utf-8", "replace")
    res.segment_lines += len(_SEGMENT.findall(region))
    res.g1_lines += region.count(b"\nG1 ")
    res.lines += region.count(b"\n", 1)
