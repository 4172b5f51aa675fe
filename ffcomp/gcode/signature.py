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

_HEADER = re.compile(rb"^; ffcomp [^\n]*feedforward vibration compensation", re.M)
_SIG = re.compile(re.escape(SIGNATURE.encode()) + rb"\b", re.M)
_SEGMENT = re.compile(rb"^G1 X-?\d+\.\d{4} Y-?\d+\.\d{4} Z-?\d+\.\d{4}(?: E-?\d+\.\d{5})? F\d+\.\d{3}\r?$", re.M)
_G1 = re.compile(rb"^G1 ", re.M)
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
    """Count the lines of ``path`` and look for the marks of a compensated file anywhere in it."""
    res = ScanResult()
    carry = b""
    with open(path, "rb") as f:
        while True:
            block = f.read(_CHUNK)
            if not block:
                break
            # scan whole lines only: the tail after the last newline waits for the next block
            data = carry + block
            cut = data.rfind(b"\n") + 1
            if cut == 0 and len(data) < 4 * _CHUNK:
                carry = data
                continue
            if cut == 0:
                cut = len(data)
            _scan(data[:cut], res)
            res.lines += data.count(b"\n", 0, cut)
            carry = data[cut:]
    if carry:
        _scan(carry, res)
    return res


def _scan(data: bytes, res: ScanResult) -> None:
    if res.mark_line is None:
        hits = [m.start() for m in (_SIG.search(data), _HEADER.search(data)) if m is not None]
        if hits:
            pos = min(hits)
            res.mark_line = res.lines + data.count(b"\n", 0, pos) + 1
            end = data.find(b"\n", pos)
            res.mark_text = data[pos:end if end >= 0 else len(data)].decode("utf-8", "replace")
    res.segment_lines += len(_SEGMENT.findall(data))
    res.g1_lines += len(_G1.findall(data))
