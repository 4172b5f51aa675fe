"""What the G-code writer did: counts and peaks for the closing summary and the header's firmware
settings (:class:`WriterStats`), and :func:`add_segments`, which takes a chunk's written segments
into them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .chain_plan import ChainLimits, z_accel_needed

__all__ = ["WriterStats", "Z_NEED_EDGES", "add_segments"]

#: the bins of :attr:`WriterStats.z_need_hist`, mm/s^2 (1 % wide, 1 to 1e8)
Z_NEED_EDGES = np.geomspace(1.0, 1e8, 1853)


@dataclass
class WriterStats:
    """What the writer did (for the closing summary)."""

    segments: int = 0
    motion_lines_replaced: int = 0
    lines_passed: int = 0
    lines_commented: int = 0
    lines_skipped: int = 0
    extrude_moves: int = 0
    holds: int = 0
    #: short rest-to-rest moves the firmware could not run in their time, written as holds
    micro_holds: int = 0
    peak_speed_mm_s: float = 0.0
    peak_accel_mm_s2: float = 0.0
    #: largest max_z_accel a junction between segments needs to run at the intended speeds
    #: (:func:`~ffcomp.gcode.chain_plan.z_accel_needed`)
    peak_z_accel_mm_s2: float = 0.0
    #: junctions between moving segments, and those that need more than the profile's max_z_accel
    junctions: int = 0
    z_accel_short: int = 0
    #: how many junctions need each max_z_accel (counts in the bins of :data:`Z_NEED_EDGES`; those
    #: with no z need are not counted): :meth:`z_accel_quantile`
    z_need_hist: np.ndarray = field(default_factory=lambda: np.zeros(len(Z_NEED_EDGES) - 1, np.int64))
    #: largest speed along a segment with z travel times ``|dz| / d``: the max_z_velocity it needs
    peak_z_velocity_mm_s: float = 0.0
    #: moving segments that reach Klipper's slow zone at the rim (``slow_xy2``), where printer.cfg's
    #: max_velocity and max_accel cap them
    rim_segments: int = 0
    extruded_mm: float = 0.0
    notes: list = field(default_factory=list)

    def z_accel_quantile(self, share: float) -> float:
        """The max_z_accel (mm/s^2; a bin's upper edge, within 1 %) that ``share`` of the junctions
        with a z need need at most; 0 if none."""
        total = int(self.z_need_hist.sum())
        if total == 0:
            return 0.0
        k = int(np.searchsorted(np.cumsum(self.z_need_hist), share * total - 1e-9))
        return float(Z_NEED_EDGES[k + 1])


def add_segments(stats: WriterStats, Pi: np.ndarray, Pj: np.ndarray, d: np.ndarray, dt: np.ndarray,
                 v: np.ndarray, de: np.ndarray, hold: np.ndarray, prev: tuple | None,
                 chain: ChainLimits | None, max_z_accel_mm_s2: float, dt_s: float) -> tuple | None:
    """Count a chunk's written segments into ``stats``.

    ``Pi``, ``Pj`` (n, 3): each segment's printed start and end point, mm; ``d`` (n, 3) its vector,
    mm; ``dt`` its intended duration, s; ``v`` its feed, mm/s; ``de`` its extrusion, mm; ``hold``
    marks holds (no XYZ travel).  ``prev``: the last moving segment of the chunk before, as this
    function returned it (its velocity, vector and duration: the first junction of this chunk), or
    None.  ``chain``: Klipper's limits (None: Marlin's per-segment solve); ``dt_s``: the sample time.
    Returns the ``prev`` of the next chunk.
    """
    moving = ~hold
    stats.holds += int(hold.sum())
    stats.segments += int(moving.sum())
    stats.extruded_mm += float(np.sum(np.maximum(de[moving], 0.0)))
    if not moving.any():
        return prev
    dm, tm = d[moving], dt[moving]
    vv = dm / tm[:, None]
    stats.peak_speed_mm_s = max(stats.peak_speed_mm_s, float(v[moving].max()))
    if chain is not None:
        xy2 = np.maximum(np.einsum("ij,ij->i", Pi[moving, :2], Pi[moving, :2]),
                         np.einsum("ij,ij->i", Pj[moving, :2], Pj[moving, :2]))
        stats.rim_segments += int(np.count_nonzero(xy2 > chain.slow_xy2))
    if prev is not None:
        vv = np.vstack([prev[0][None], vv])
        dm, tm = np.vstack([prev[1][None], dm]), np.r_[prev[2], tm]
    if len(vv) > 1:
        acc = np.linalg.norm(np.diff(vv, axis=0), axis=1) / np.maximum(dt[moving][-len(vv) + 1:], dt_s)
        stats.peak_accel_mm_s2 = max(stats.peak_accel_mm_s2, float(acc.max()))
        sp = np.linalg.norm(vv[1:], axis=1)
        uz = np.abs(vv[1:, 2]) / np.maximum(sp, 1e-12)
        zneed = z_accel_needed(dm, tm, chain.jd if chain is not None else None)
        stats.peak_z_accel_mm_s2 = max(stats.peak_z_accel_mm_s2, float(np.max(zneed)))
        stats.junctions += len(zneed)
        stats.z_accel_short += int(np.count_nonzero(zneed > max_z_accel_mm_s2 * (1 + 1e-9)))
        zn = zneed[zneed > 0]
        if zn.size:
            stats.z_need_hist += np.histogram(np.clip(zn, Z_NEED_EDGES[0], Z_NEED_EDGES[-1] * 0.999),
                                              Z_NEED_EDGES)[0]
        stats.peak_z_velocity_mm_s = max(stats.peak_z_velocity_mm_s, float(np.max(sp * uz)))
    return vv[-1], dm[-1], float(tm[-1])
