"""Rest margins around retractions: where a compensation stream adds them, and the same rest in a
sampled reference (``CompensateOptions.hold_margin_s``, ``--hold-margin-ms``).

A G-code file cannot move the nozzle during an extruder-only move, so the compensated command can
neither settle a stop's ringing during a retraction nor pre-actuate the next move during an
unretraction.  With margins the stream gets a few ms of rest before every retraction that follows an
XYZ move and after every unretraction that an XYZ move follows, and the command moves freely there.
"""

from __future__ import annotations

import numpy as np

from .moves import EXTRUDE, FIRMWARE, MOVE

_E_ONLY = (EXTRUDE, FIRMWARE)  # extruder-only moves, the file's own or the firmware's (G10/G11)

__all__ = ["hold_margins", "with_margins"]


def hold_margins(move_index: np.ndarray, moves: dict, prev_mi: int | None) -> list[tuple[int, str]]:
    """Where a stream of samples gets a rest margin.

    Parameters
    ----------
    move_index : (n,) planned move (``PlannedMove.index``) of each sample
    moves : planned moves by index (those of the samples and their neighbours)
    prev_mi : the move of the sample before the first (None: the stream starts here)

    Returns
    -------
    list of (i, where): insert the margin before sample ``i``; ``where`` is ``"before"`` (a
    retraction, an extruder-only move that lowers E right after an XYZ move, starts at sample ``i``)
    or ``"after"`` (an unretraction, one that raises E right before an XYZ move, ended at sample
    ``i - 1``).
    """
    mi = np.asarray(move_index)
    if prev_mi is not None:
        mi = np.concatenate([[prev_mi], mi])
    edges = np.nonzero(mi[1:] != mi[:-1])[0]
    out = []
    for j in edges.tolist():
        a, b = moves.get(int(mi[j])), moves.get(int(mi[j + 1]))
        if a is None or b is None or int(b.index) != int(a.index) + 1:
            continue
        i = j + 1 - (prev_mi is not None)
        if a.kind == MOVE and b.kind in _E_ONLY and b.end_mm[3] < b.start_mm[3]:
            out.append((i, "before"))
        elif a.kind in _E_ONLY and b.kind == MOVE and a.end_mm[3] > a.start_mm[3]:
            out.append((i, "after"))
    return out


def with_margins(columns: tuple, move_index: np.ndarray, moves: dict, n: int) -> tuple:
    """``columns`` (arrays with one row per sample of a whole planned file) with ``n`` rest rows
    added where :func:`hold_margins` puts them: copies of the row where the plan stands still (the
    retraction's first sample, or the unretraction's last)."""
    parts, a = [[] for _ in columns], 0
    for i, where in hold_margins(move_index, moves, None):
        r = i if where == "before" else i - 1
        for p, c in zip(parts, columns):
            p += [c[a:i], np.repeat(c[r:r + 1], n, 0)]
        a = i
    return tuple(np.concatenate(p + [c[a:]]) for p, c in zip(parts, columns))
