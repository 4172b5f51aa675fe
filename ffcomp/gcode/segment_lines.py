"""The G-code lines of the writer's segments, and the layout of its segment table.

One line per written segment: ``G1 X Y Z [E] F`` through the printed point, or for a hold (no XYZ
travel) the extruder's own move (``G1 E F``) or a dwell of the segment's duration (``G4 P``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SEG_COLS", "format_segments"]

#: columns of the writer's segment table: body line, first and last sample, catch-up flag, stream,
#: and where the segment starts and ends past those samples (a rest start or end between samples), ns
SEG_COLS = 7

#: a segment line, with and without extrusion; below F100 the feed gets six decimals (a slow
#: segment's duration needs them)
_SEG_E, _SEG_E_SLOW = "G1 X%.4f Y%.4f Z%.4f E%.5f F%.3f\n", "G1 X%.4f Y%.4f Z%.4f E%.5f F%.6f\n"
_SEG, _SEG_SLOW = "G1 X%.4f Y%.4f Z%.4f F%.3f\n", "G1 X%.4f Y%.4f Z%.4f F%.6f\n"


def format_segments(P_mm: np.ndarray, de_mm: np.ndarray, v_mm_s: np.ndarray, hold: np.ndarray,
                    fractional_dwell: bool) -> list[str]:
    """The lines of segments ending at ``P_mm`` (n, 3, printed to 0.1 um), extruding ``de_mm`` at
    feed ``v_mm_s``; a hold's ``v_mm_s`` is the extruder's feed, or without extrusion the dwell's
    duration, s.  ``fractional_dwell``: ``G4 P`` in fractions of a ms (Klipper takes them)."""
    xs, ys, zs = (P_mm + 0.0).T.tolist()  # (+ 0.0: a coordinate rounded to -0.0 prints as 0.0000)
    pfmt = ".3f" if fractional_dwell else ".0f"
    lines = []
    app = lines.append
    for x, y, z, e, f, h, t in zip(xs, ys, zs, de_mm.tolist(), (v_mm_s * 60).tolist(), hold.tolist(),
                                   v_mm_s.tolist()):
        if h:  # a hold's value: the extruder's feed, or the dwell's duration
            if abs(e) > 1e-9:
                app(f"G1 E{e:.5f} F{f:.3f}\n")
            else:
                app(f"G4 P{t * 1000:{pfmt}}\n")
        elif abs(e) > 1e-9:
            app((_SEG_E if f >= 100 else _SEG_E_SLOW) % (x, y, z, e, f))
        else:
            app((_SEG if f >= 100 else _SEG_SLOW) % (x, y, z, f))
    return lines
