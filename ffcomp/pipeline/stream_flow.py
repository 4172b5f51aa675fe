"""The compensation stream of a planned file: samples -> streaming inverse -> carriage commands,
each with its sample's reference, in order.

A homing or a stop ends a stream (``post_s`` of rest) and the next starts from rest (``pre_s``); with
``CompensateOptions.hold_margin_s`` the stream gets rest around retractions
(:mod:`ffcomp.gcode.margins`).  :func:`~ffcomp.pipeline.compensate_flow.write_body` writes the
commands as G-code, :mod:`ffcomp.pipeline.steps_flow` as step streams.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from typing import TYPE_CHECKING

import numpy as np

from ..compensate.inverse import InverseConfig
from ..compensate.stream_inverse import StreamingInverse
from ..errors import GcodeError
from ..gcode.margins import hold_margins
from ..gcode.planner import GcodePlan
from ..gcode.sampler import sample_blocks
from ..kinematics import carriage_rates
from ..linalg3 import max_abs3
from ..model.lpv import LpvModel
from .limited_moves import holds
from .options import JUMP_M, REST_MOVE, REST_PRE, CompensateOptions, CompensationSummary

if TYPE_CHECKING:
    from .pieces import _PieceState

__all__ = ["compensated_stream", "inverse_config", "inv_pre_samples"]


def compensated_stream(plan: GcodePlan, moves: dict, profile, model: LpvModel, icfg: InverseConfig, opts,
                       summ: CompensationSummary, src: str, pstate: _PieceState | None = None):
    """Compensated carriage commands of a planned file, in order, with each sample's reference.

    Yields ``(q_cmd (n, 3), meta)``; ``meta`` holds the reference ``q``, ``xyz`` (m), ``e`` (mm),
    ``move_index`` and ``lineno`` of the same samples.  Planned moves are recorded in ``moves``
    (index -> PlannedMove) as they go by.  A homing (a jump of the carriages) ends one compensation
    stream and starts the next; each stream begins with ``pre_s`` and ends with ``post_s`` of rest,
    which the output keeps (so the command can pre-actuate the first move and settle after the last).
    A stop command (M600, PAUSE, T1, G29, M109, an unknown macro...: the planner brings the toolhead to
    rest there) or a sync (M400, M84) ends a stream the same way, so the command stands still at the
    plan's rest position when the firmware runs it, and the next stream starts from rest after it.  A
    file without XYZ motion is an error (nothing to compensate).

    ``pstate`` (``--jobs``): only the samples of one :class:`Piece` are compensated: the plan runs from
    the file's start (modal state, positions, limits and E stay right) but its moves before the
    piece's first cut are not sampled, and the last stream ends at the next cut as at a stop.
    """
    geom = model.geometry
    dt = 1.0 / profile.limits.sample_rate_hz
    fifo = _Fifo()
    inv = None
    last_q = None
    last_meta = None
    stops: list[tuple] = []  # (print time, line) of stops not yet applied to the stream
    plan.planner.on_stop = lambda t_s, lineno: stops.append((t_s, lineno))
    n_xyz = 0
    planned = iter(plan)
    k_start = 0
    if pstate is not None:
        planned = pstate.begin(plan, planned, stops, profile.limits.sample_rate_hz)
        if planned is None:  # an empty piece: its first cut is also its last
            return
        k_start = pstate.k_lo

    def tee():
        nonlocal n_xyz
        for mv in planned:
            if pstate is not None and pstate.ends_at(mv):
                return
            moves[mv.index] = mv
            if mv.kind == "move":
                n_xyz += 1
            yield mv

    def out(qc):
        if len(qc):
            yield qc, fifo.pop(len(qc))

    n_margin = int(round(opts.hold_margin_s / dt))
    prev_mi = last_x = last_ln = None

    def push_post(meta):
        n_post = int(round(icfg.post_s / dt))
        qq, xx, ee, mi, ln = meta
        fifo.push(q=np.repeat(qq[None], n_post, 0), xyz=np.repeat(xx[None], n_post, 0),
                  e=np.repeat(ee, n_post), move_index=np.full(n_post, REST_MOVE), lineno=np.repeat(ln, n_post),
                  k=np.full(n_post, -1, np.int64))

    for blk in sample_blocks(tee(), geom, fs_hz=profile.limits.sample_rate_hz, block_len=opts.block_len,
                             overlap=0, path=src, k_start=k_start):
        if pstate is not None and pstate.hi is not None and blk.k0 + len(blk.t_s) > pstate.k_hi:
            blk = _head(blk, pstate.k_hi - blk.k0)  # the next piece starts at the cut
            if blk is None:
                break
        q = blk.q_m
        # homing (or any jump) restarts the compensation stream
        jumps = np.nonzero(max_abs3(np.diff(q, axis=0)) > JUMP_M)[0] + 1
        if last_q is not None and np.max(np.abs(q[0] - last_q)) > JUMP_M:
            jumps = np.concatenate([[0], jumps])
        # stops: the stream ends where the plan comes to rest (the first sample at or after the stop)
        t_end = blk.t_s[-1]
        here = [s_ for s_ in stops if s_[0] <= t_end]
        stops[:] = [s_ for s_ in stops if s_[0] > t_end]
        at_stop = np.searchsorted(blk.t_s, np.asarray([t for t, _ in here], float) - 1e-9) if here else np.zeros(0, int)
        # the stream after a stop starts with the line after the stop's: its pre-roll is written
        # after the stop's line (the sample at the stop may still belong to the move before it)
        stop_line = {}
        for i_, (_, ln_) in zip(at_stop.tolist(), here):
            stop_line[i_] = max(stop_line.get(i_, 0), int(ln_) + 1)
        at_stop = np.unique(at_stop)
        cuts = np.union1d(jumps, at_stop).astype(int)
        for pc in np.split(np.arange(len(q)), cuts):
            if len(pc) == 0:
                continue
            if inv is not None and pc[0] in cuts:
                push_post(last_meta)
                yield from out(inv.finish())
                inv = None
                if pc[0] in jumps:
                    summ.restarts += 1
            sl = slice(pc[0], pc[-1] + 1)
            if inv is None:
                inv = StreamingInverse(model, dt, icfg, keep_padding=True)
                k = pc[0]
                n_pre = inv_pre_samples(icfg, dt)
                ln_pre = int(blk.lineno[k])
                if k in stop_line:
                    # after the stop's line, unless the stream's own samples carry that line (the
                    # firmware's dwells around an M84 / M18: the command line is written after them,
                    # last, and nothing moves after a motor-off)
                    stop_ln = stop_line[k] - 1
                    ln_pre = max(ln_pre, stop_ln if np.any(blk.lineno[pc] == stop_ln) else stop_ln + 1)
                fifo.push(q=np.repeat(q[k:k + 1], n_pre, 0), xyz=np.repeat(blk.xyz_m[k:k + 1], n_pre, 0),
                          e=np.repeat(blk.e_mm[k:k + 1], n_pre), move_index=np.full(n_pre, REST_PRE),
                          lineno=np.full(n_pre, ln_pre),
                          k=np.full(n_pre, -1, np.int64))
            last_meta = (q[pc[-1]], blk.xyz_m[pc[-1]], blk.e_mm[pc[-1]], blk.move_index[pc[-1]], blk.lineno[pc[-1]])
            marks = (hold_margins(blk.move_index[sl], moves, prev_mi if pc[0] not in cuts else None)
                     if n_margin else [])
            a = sl.start
            for i, where in marks + [(sl.stop - sl.start, None)]:
                b = sl.start + i
                if b > a:
                    part = slice(a, b)
                    fifo.push(q=q[part], xyz=blk.xyz_m[part], e=blk.e_mm[part], move_index=blk.move_index[part],
                              lineno=blk.lineno[part], k=blk.k0 + np.arange(a, b, dtype=np.int64))
                    # the planner's exact rates only where the inverse uses them (by default it takes
                    # the derivatives of the samples themselves)
                    qd, qdd = (carriage_rates(geom, blk.xyz_m[part], blk.v_m_s[part], blk.a_m_s2[part])
                               if icfg.derivatives == "given" else (None, None))
                    hold = holds(blk.move_index[part], moves, blk.t_s[part], dt) if opts.pin_holds else None
                    yield from out(inv.push(q[part], blk.xyz_m[part], qd, qdd, hold))
                if where is None:
                    break
                # the added rest: where the plan stands (the retraction's first sample, or the
                # unretraction's last: the previous block's if the move starts a block)
                if where == "before" or b > 0:
                    r = b if where == "before" else b - 1
                    qr, xr, lr, mr = q[r], blk.xyz_m[r], blk.lineno[r], int(blk.move_index[r])
                else:
                    qr, xr, lr, mr = last_q, last_x, last_ln, prev_mi
                er = moves[mr].start_mm[3] if where == "before" else moves[mr].end_mm[3]
                rest_q, rest_x = np.repeat(qr[None], n_margin, 0), np.repeat(xr[None], n_margin, 0)
                fifo.push(q=rest_q, xyz=rest_x, e=np.full(n_margin, er), move_index=np.full(n_margin, REST_MOVE),
                          lineno=np.full(n_margin, lr), k=np.full(n_margin, -1, np.int64))
                yield from out(inv.push(rest_q, rest_x))
                summ.hold_margins += 1
                summ.hold_margin_time_s += n_margin * dt
                a = b
        last_q = q[-1].copy()
        last_x, last_ln, prev_mi = blk.xyz_m[-1].copy(), blk.lineno[-1], int(blk.move_index[-1])
        summ.print_time_s = float(blk.t_s[-1])
    if inv is not None:
        push_post(last_meta)
        yield from out(inv.finish())
    if pstate is not None:
        pstate.n_xyz = n_xyz
        return
    if n_xyz == 0:
        raise GcodeError(src, plan.parser.lines_read, "the file has no XYZ motion (empty, comments only, or no "
                         "moves): nothing to compensate")


def inverse_config(profile, opts: CompensateOptions) -> InverseConfig:
    """The inverse settings of a run: the options' plus the command bounds from the profile (and,
    for Klipper, its ``max_z_accel``: the firmware caps the z acceleration of every segment there)."""
    lim = profile.limits
    bounds = opts.inverse.bounds or (lim.max_correction_mm * 1e-3, lim.max_carriage_velocity_mm_s * 1e-3,
                                     lim.max_carriage_accel_mm_s2 * 1e-3)
    zb = opts.inverse.z_accel_bound
    if zb is None and lim.planner == "klipper":
        zb = lim.max_z_accel_mm_s2 * 1e-3
    return InverseConfig(**{**asdict(opts.inverse), "method": opts.method, "bounds": bounds, "z_accel_bound": zb})


def inv_pre_samples(icfg: InverseConfig, dt: float) -> int:
    """Rest samples the streaming inverse puts before a stream."""
    from ..compensate.inverse import _round_to

    return _round_to(int(round(icfg.pre_s / dt)), icfg.knot_samples)


def _head(blk, n: int):
    """The first ``n`` samples of a block (None if none)."""
    if n <= 0:
        return None
    if n >= len(blk.t_s):
        return blk
    return replace(blk, t_s=blk.t_s[:n], xyz_m=blk.xyz_m[:n], v_m_s=blk.v_m_s[:n], a_m_s2=blk.a_m_s2[:n],
                   e_mm=blk.e_mm[:n], q_m=blk.q_m[:n], move_index=blk.move_index[:n], lineno=blk.lineno[:n])


class _Fifo:
    """Per-sample metadata waiting for its compensated command."""

    def __init__(self):
        self.parts: dict[str, list[np.ndarray]] = {}

    def push(self, **cols):
        for k, v in cols.items():
            self.parts.setdefault(k, []).append(np.asarray(v))

    def pop(self, n: int) -> dict[str, np.ndarray]:
        out = {}
        for k, lst in self.parts.items():
            arr = np.concatenate(lst) if len(lst) > 1 else lst[0]
            out[k], rest = arr[:n], arr[n:]
            self.parts[k] = [rest]
        return out
