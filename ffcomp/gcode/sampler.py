"""Uniform-time samples of a planned trajectory, streamed in overlapping blocks.

Samples sit on the global grid ``t_k = k / fs`` (``k = 0, 1, ..., K`` with ``K = ceil(T_end fs)``; after
the last move the machine rests at the final position, so the last sample is the last G-code position).
Each sample is evaluated exactly from the trapezoid pieces of the move active at ``t_k`` (the later
move at a boundary): position, velocity and acceleration of the nozzle (a straight move has no
centripetal term), the extruder position, and the carriage positions by inverse kinematics.

:func:`sample_blocks` streams :class:`SampleBlock` objects of ``block_len`` samples; consecutive blocks
share ``overlap`` samples (block ``b`` starts at ``k = b (block_len - overlap)``), so windowed processing
runs in bounded memory on files of any length.  Dropping the first ``overlap`` rows of every block but
the first reproduces :func:`sample_all` exactly.

Units: SI for the kernels (``t_s``, ``xyz_m``, ``v_m_s``, ``a_m_s2``, ``q_m``); extruder ``e_mm`` in mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Iterator

import numpy as np

from ..errors import KinematicsError
from ..kinematics import DeltaGeometry, inverse
from .moves import PlannedMove

__all__ = ["SampleBlock", "sample_blocks", "sample_all", "sample_gcode", "concat_blocks"]

_EPS_T = 1e-9  # s: grid points this close past T_end do not add a sample


@dataclass(frozen=True, slots=True)
class SampleBlock:
    """Samples ``k0 .. k0 + n - 1`` of the global grid.

    Attributes
    ----------
    k0 : int
        Global index of the first row (``t_s[0] == k0 / fs_hz``).
    overlap : int
        Leading rows that repeat the previous block's last rows (0 for the first block).
    fs_hz : float
    t_s : ndarray, shape (n,)
        Sample times, s.
    xyz_m, v_m_s, a_m_s2 : ndarray, shape (n, 3)
        Nozzle position (m), velocity (m/s), acceleration (m/s^2).
    e_mm : ndarray, shape (n,)
        Extruder position, mm.
    q_m : ndarray, shape (n, 3)
        Carriage heights (A, B, C), m.
    move_index : ndarray of int64, shape (n,)
        Index of the planned move (``PlannedMove.index``) each sample belongs to.
    lineno : ndarray of int64, shape (n,)
        Source G-code line of that move.
    last : bool
        True for the final block.
    """

    k0: int
    overlap: int
    fs_hz: float
    t_s: np.ndarray
    xyz_m: np.ndarray
    v_m_s: np.ndarray
    a_m_s2: np.ndarray
    e_mm: np.ndarray
    q_m: np.ndarray
    move_index: np.ndarray
    lineno: np.ndarray
    last: bool

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def new_rows(self) -> slice:
        """Rows not already delivered by the previous block."""
        return slice(self.overlap, None)


# columns of the per-move parameter table
_C_T0, _C_TA, _C_TC, _C_TD, _C_V0, _C_VC, _C_A = range(7)
_C_P = 7  # start x, y, z, e
_C_U = 11  # unit x, y, z, e
_NCOL = 15


def _row(m: PlannedMove) -> tuple:
    s, u = m.start_mm, m.unit
    return (m.t_start_s, m.accel_t_s, m.cruise_t_s, m.decel_t_s, m.start_v_mm_s, m.cruise_v_mm_s,
            m.accel_mm_s2, s[0], s[1], s[2], s[3], u[0], u[1], u[2], u[3])


def _evaluate(rows: list[tuple], ids: list[tuple], t: np.ndarray):
    """Exact trapezoid evaluation of the moves in ``rows`` at times ``t``."""
    P = np.asarray(rows, dtype=float).reshape(-1, _NCOL)
    t0 = P[:, _C_T0]
    j = np.searchsorted(t0, t, side="right") - 1
    np.clip(j, 0, len(rows) - 1, out=j)
    Pj = P[j]
    ta, tc, td = Pj[:, _C_TA], Pj[:, _C_TC], Pj[:, _C_TD]
    v0, vc, a = Pj[:, _C_V0], Pj[:, _C_VC], Pj[:, _C_A]
    tau = t - Pj[:, _C_T0]
    np.clip(tau, 0.0, ta + tc + td, out=tau)
    in_acc = tau < ta
    in_cru = ~in_acc & (tau < ta + tc)
    in_dec = ~(in_acc | in_cru)
    s = np.empty_like(tau)
    v = np.empty_like(tau)
    acc = np.zeros_like(tau)
    # acceleration phase
    tt = tau[in_acc]
    s[in_acc] = v0[in_acc] * tt + 0.5 * a[in_acc] * tt * tt
    v[in_acc] = v0[in_acc] + a[in_acc] * tt
    acc[in_acc] = a[in_acc]
    # cruise
    accel_d = (v0 + vc) * 0.5 * ta
    tt = tau[in_cru] - ta[in_cru]
    s[in_cru] = accel_d[in_cru] + vc[in_cru] * tt
    v[in_cru] = vc[in_cru]
    # deceleration (also the rest after the end, with tau clamped to the duration)
    tt = tau[in_dec] - ta[in_dec] - tc[in_dec]
    s[in_dec] = accel_d[in_dec] + vc[in_dec] * tc[in_dec] + vc[in_dec] * tt - 0.5 * a[in_dec] * tt * tt
    v[in_dec] = vc[in_dec] - a[in_dec] * tt
    acc[in_dec] = -a[in_dec]
    n = len(tau)
    pos, vel, accel = np.empty((n, 4)), np.empty((n, 3)), np.empty((n, 3))
    for c in range(4):  # along the unit vector, column by column (faster than broadcasting s[:, None])
        u = Pj[:, _C_U + c]
        pos[:, c] = Pj[:, _C_P + c] + u * s
        if c < 3:
            vel[:, c] = u * v
            accel[:, c] = u * acc
    idarr = np.asarray(ids, dtype=np.int64).reshape(-1, 2)[j]
    return pos, vel, accel, idarr[:, 0], idarr[:, 1]


def _rest_after_end(pos, vel, accel, t, t_end, end_pos):
    """At and after the end of the last move the machine rests at its final position."""
    after = t >= t_end - _EPS_T
    if after.any():
        pos[after] = end_pos
        vel[after] = 0.0
        accel[after] = 0.0


def sample_blocks(moves: Iterable[PlannedMove], geom: DeltaGeometry, *, fs_hz: float, block_len: int = 4096,
                  overlap: int = 512, path: str = "<gcode>", k_start: int = 0) -> Iterator[SampleBlock]:
    """Stream uniform-time samples of ``moves`` in blocks of ``block_len`` with ``overlap`` shared rows.

    Parameters
    ----------
    moves : iterable of PlannedMove
        In execution order, contiguous in time (as the planners yield them).
    geom : DeltaGeometry
        For the carriage positions (SI).
    fs_hz : float
        Sample rate (the profile's ``limits.sample_rate_hz``).
    block_len, overlap : int
        Samples per block and samples shared by consecutive blocks (``0 <= overlap < block_len``).
    path : str
        File name for error messages.
    k_start : int
        Index of the first sample (of the global grid ``k / fs_hz``): the moves need only cover the
        grid from there (a piece of a file, ``--jobs``).

    Raises
    ------
    KinematicsError
        A sample's position is out of the arms' reach (names the G-code line).
    """
    if not fs_hz > 0:
        raise ValueError(f"fs_hz must be > 0, got {fs_hz}")
    if block_len < 1 or not (0 <= overlap < block_len):
        raise ValueError(f"need block_len >= 1 and 0 <= overlap < block_len, got {block_len}, {overlap}")
    fs = float(fs_hz)
    step = block_len - overlap
    it = iter(moves)
    window: list[tuple] = []  # parameter rows of the moves that may still be sampled
    ids: list[tuple] = []
    ends: list[float] = []
    exhausted = False
    t_end = 0.0
    end_pos = None
    k_last = None  # index of the final sample, once known
    k0 = int(k_start)
    first = True
    while True:
        k_hi = k0 + block_len - 1
        if k_last is not None:
            k_hi = min(k_hi, k_last)
        t_hi = k_hi / fs
        # pull moves until the window covers t_hi, plus one more (so the end of the plan is seen in time
        # to mark the block that reaches it as the last one)
        while not exhausted and (len(ends) < 2 or ends[-2] <= t_hi):
            try:
                m = next(it)
            except StopIteration:
                exhausted = True
                t_end = ends[-1] if ends else 0.0
                k_last = max(0, math.ceil(t_end * fs - _EPS_T * fs))
                k_hi = min(k0 + block_len - 1, k_last)
                break
            if m.duration_s <= 0.0:
                continue
            end_pos = m.end_mm
            window.append(_row(m))
            ids.append((m.index, m.lineno))
            ends.append(m.t_end_s)
        if k0 > k_hi:
            return
        k = np.arange(k0, k_hi + 1, dtype=np.int64)
        t = k / fs
        if window:
            pos, vel, acc, midx, lno = _evaluate(window, ids, t)
            if exhausted:
                _rest_after_end(pos, vel, acc, t, t_end, end_pos)
        else:  # no motion at all: a single sample at the start position
            pos = np.zeros((len(t), 4))
            vel = np.zeros((len(t), 3))
            acc = np.zeros((len(t), 3))
            midx = np.full(len(t), -1, dtype=np.int64)
            lno = np.zeros(len(t), dtype=np.int64)
        xyz_m = pos[:, :3] * 1e-3
        q = inverse(geom, xyz_m)
        bad = ~np.isfinite(q).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            p = pos[i, :3]
            raise KinematicsError(
                f"{path}:{int(lno[i])}: position ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) mm at t = {t[i]:.4f} s "
                "is out of the arms' reach")
        last = exhausted and k_hi >= k_last
        yield SampleBlock(int(k0), 0 if first else overlap, fs, t, xyz_m, vel * 1e-3, acc * 1e-3,
                          pos[:, 3].copy(), q, midx, lno, last)
        if last:
            return
        first = False
        k0 += step
        # drop moves that ended before the next block starts
        t_next = k0 / fs
        drop = 0
        while drop < len(ends) - 1 and ends[drop] < t_next:
            drop += 1
        if drop:
            del window[:drop]
            del ids[:drop]
            del ends[:drop]


def concat_blocks(blocks: Iterable[SampleBlock]) -> SampleBlock:
    """Join streamed blocks (overlaps removed) into one block."""
    blocks = list(blocks)
    if not blocks:
        raise ValueError("no blocks to join")
    parts = {f: [] for f in ("t_s", "xyz_m", "v_m_s", "a_m_s2", "e_mm", "q_m", "move_index", "lineno")}
    for b in blocks:
        sl = b.new_rows()
        for f in parts:
            parts[f].append(getattr(b, f)[sl])
    cat = {f: np.concatenate(v) for f, v in parts.items()}
    b0 = blocks[0]
    return SampleBlock(b0.k0, 0, b0.fs_hz, cat["t_s"], cat["xyz_m"], cat["v_m_s"], cat["a_m_s2"], cat["e_mm"],
                       cat["q_m"], cat["move_index"], cat["lineno"], blocks[-1].last)


def sample_all(moves: Iterable[PlannedMove], geom: DeltaGeometry, *, fs_hz: float,
               path: str = "<gcode>") -> SampleBlock:
    """All samples in one block (for short files)."""
    return concat_blocks(sample_blocks(moves, geom, fs_hz=fs_hz, block_len=65536, overlap=0, path=path))


def sample_gcode(source, profile, *, block_len: int = 4096, overlap: int = 512, fs_hz: float | None = None,
                 **plan_kw) -> Iterator[SampleBlock]:
    """Parse, plan and sample a G-code source in one stream (see :class:`~ffcomp.gcode.planner.GcodePlan`)."""
    from .planner import GcodePlan

    plan = GcodePlan(source, profile, **plan_kw)
    fs = float(profile.limits.sample_rate_hz if fs_hz is None else fs_hz)
    return sample_blocks(plan, profile.geometry_si(), fs_hz=fs, block_len=block_len, overlap=overlap,
                         path=plan.path)
