"""Which planned moves the firmware's own limits bind, sample by sample: the kernels behind the
pins, the plan fallback and the sample-by-sample writing of :mod:`ffcomp.pipeline.compensate_flow`.

:class:`LimitBound`: moves the extruder's limits bind (and z moves right after or before a hold).
:class:`ZLimited`: moves Klipper's delta rule ``max_z_accel * d/|dz|`` binds, written sample by
sample, with z reversals put on their vertex.  Plain functions of planned moves (``PlannedMove``)
and sample arrays; no files.
"""

from __future__ import annotations

import math

import numpy as np

from ..gcode.chain_plan import ChainLimits, segment_limits
from ..gcode.extrusion import extruder_capped as _extruder_capped
from ..gcode.moves import FIRMWARE

__all__ = ["LimitBound", "ZLimited", "moves_where", "holds", "after_firmware", "lead_into", "z_held", "z_moving",
           "z_hop"]


def moves_where(move_index: np.ndarray, moves: dict, pred) -> np.ndarray:
    """Mask of the samples whose planned move satisfies ``pred``."""
    uniq, inv = np.unique(move_index, return_inverse=True)
    hit = np.array([(mv := moves.get(int(mi))) is not None and bool(pred(mv)) for mi in uniq.tolist()], bool)
    return hit[inv.reshape(-1)] if len(hit) else np.zeros(len(move_index), bool)


def holds(move_index: np.ndarray, moves: dict, t_s: np.ndarray | None = None, dt: float = 0.0) -> np.ndarray:
    """Samples whose planned move is an extruder-only move or a dwell (the nozzle stands still); with
    the samples' times ``t_s`` (s) and the sample time ``dt`` (s), also those of
    :func:`after_firmware`."""
    held = moves_where(move_index, moves, lambda mv: mv.kind != "move")
    if t_s is not None:
        held |= after_firmware(move_index, moves, t_s, dt)
    return held


def after_firmware(move_index: np.ndarray, moves: dict, t_s: np.ndarray, dt: float) -> np.ndarray:
    """The first sample of each move that leaves rest right after a firmware's extruder-only move
    (``G10``/``G11``, kind ``firmware``): the sample after the move's start, less than ``dt`` later.

    The writer can shorten an extruder-only move of the file's own (and wait out the rest), so the
    command may leave the rest point one sample before the plan does; a ``G10``/``G11`` lasts what
    the firmware makes of it, ending between two samples, and the command must stand on the plan
    until the sample after that end, or the first segment cannot reach it in time from rest.
    """
    def follows(mv) -> bool:
        prev = moves.get(mv.index - 1)
        return mv.kind == "move" and prev is not None and prev.kind == FIRMWARE

    hit = moves_where(move_index, moves, follows)
    if hit.any():
        start = np.array([moves[int(i)].t_start_s for i in move_index[hit].tolist()])
        hit[hit] = np.asarray(t_s)[hit] - start < dt * (1.0 - 1e-9)
    return hit


def lead_into(move_index: np.ndarray, moves: dict, t_s: np.ndarray, span_s: float, pred,
              printed_s: float = 0.0, z_span_s: float | None = None, wet: bool = False) -> np.ndarray:
    """The samples within ``span_s`` (s) of the end of a travel (kind ``move``, no extrusion), or
    within ``printed_s`` of the end of a move that extrudes into one that does not (``wet``: into
    any), whose next move satisfies ``pred``; ``t_s``: the samples' times, s.  ``z_span_s`` (default
    ``span_s``): the span for a travel that moves more in z than in XY."""
    if max(span_s, printed_s, z_span_s or 0.0) <= 0.0 or not len(move_index):
        return np.zeros(len(move_index), bool)
    uniq, inv = np.unique(move_index, return_inverse=True)
    from_s = np.full(len(uniq), np.inf)  # per move: the time from which its samples lead in
    for q, i in enumerate(uniq.tolist()):
        mv, nx = moves.get(int(i)), moves.get(int(i) + 1)
        if mv is None or nx is None or mv.kind != "move":
            continue
        printed = mv.end_mm[3] != mv.start_mm[3]
        if printed and nx.end_mm[3] != nx.start_mm[3] and not wet:
            continue  # (a lift that extrudes: Klipper's extruder junction rule governs that corner)
        if printed:
            span = printed_s
        elif z_span_s is not None and math.hypot(mv.end_mm[0] - mv.start_mm[0], mv.end_mm[1] - mv.start_mm[1]) \
                < abs(mv.end_mm[2] - mv.start_mm[2]):
            span = z_span_s
        else:
            span = span_s
        if span > 0.0 and pred(nx):
            from_s[q] = mv.t_end_s - span
    return np.asarray(t_s) > from_s[inv.reshape(-1)]


def enters_by_extruder(mv, moves: dict, instant_corner_v_mm_s: float) -> bool:
    """Whether the plan enters move ``mv`` at the speed Klipper's extruder junction rule allows,
    ``instantaneous_corner_velocity / |r - r_prev|`` for the extrusion per mm ``r`` of ``mv`` and of
    the move before it (a travel into an extruding or retracting lift): a command that comes
    into such a corner faster than the plan meets the same rule on its written segments, and the
    move after it starts late (random files, 0.3-0.6 ms on the default profile)."""
    prev = moves.get(mv.index - 1)
    if prev is None or prev.kind != "move" or mv.kind != "move" or mv.start_v_mm_s <= 1e-9:
        return False
    dr = abs(mv.unit[3] - prev.unit[3])
    return dr > 1e-9 and mv.start_v_mm_s <= instant_corner_v_mm_s / dr * (1.0 + 1e-6)


def z_held(move_index: np.ndarray, moves: dict) -> np.ndarray:
    """Samples whose planned move keeps z constant."""
    return moves_where(move_index, moves, lambda mv: abs(mv.end_mm[2] - mv.start_mm[2]) < 1e-9)


class LimitBound:
    """Which planned moves the extruder's limits bind: moves that extrude without XY travel or
    retract while moving, whose acceleration cap ``max_extrude_only_accel * d/|de|`` is within
    ``factor`` of the acceleration the plan already uses, so a compensated command (which
    accelerates harder than the plan) cannot run on time there.  (Moves bound by ``max_z_accel``
    stay compensated: their lateness is recovered by the feed solve and reported.)"""

    def __init__(self, lim: ChainLimits, factor: float = 4.0):
        self.extruder_only, self.factor = _NoAccel(lim), factor
        self.cache: dict[int, bool] = {}
        # per blended mask: samples from its last masked sample to the end of the last chunk (the
        # blend after a masked move goes on into the next chunk; None: none in this stream yet)
        self.since: dict[str, int | None] = {}

    def bound(self, mv) -> bool:
        b = self.cache.get(mv.index)
        if b is None:
            b = False
            if mv.kind == "move" and (mv.accel_t_s > 0 or mv.decel_t_s > 0) and _extruder_capped(mv):
                s0, s1 = np.array([mv.start_mm[:3]]), np.array([mv.end_mm[:3]])
                de = np.array([mv.end_mm[3] - mv.start_mm[3]])
                acc_cap = segment_limits(self.extruder_only, s0, s1, de)[1][0]
                b = bool(acc_cap < self.factor * mv.accel_mm_s2)
            if len(self.cache) > 4096:
                self.cache.clear()
            self.cache[mv.index] = b
        return b

    def mask(self, move_index: np.ndarray, moves: dict) -> np.ndarray:
        return moves_where(move_index, moves, self.bound)

    def z_after_hold(self, mv, moves: dict) -> bool:
        """A move with z travel right after an extruder-only move or dwell (a z-hop after a
        retraction): the compensated command would pre-actuate its z during the hold, which a
        G-code file cannot move in, and catch up after it at ``max_z_accel``: its z follows the plan."""
        if mv.kind != "move" or abs(mv.end_mm[2] - mv.start_mm[2]) < 1e-9:
            return False
        prev = moves.get(mv.index - 1)
        return prev is not None and prev.kind != "move"

    def z_before_hold(self, mv, moves: dict) -> bool:
        """A move with z travel right before an extruder-only move or dwell (the z move down to
        the layer before an unretract): where ``max_z_accel`` binds it (:class:`ZLimited`), the pin
        repair would settle the command before the hold without that bound, and the z move would
        run late; it follows the plan.  (The next move is known by then: the commands come hundreds of
        milliseconds behind the plan.)"""
        if mv.kind != "move" or abs(mv.end_mm[2] - mv.start_mm[2]) < 1e-9:
            return False
        nxt = moves.get(mv.index + 1)
        return nxt is not None and nxt.kind != "move"

    def z_follows_plan(self, mv, moves: dict, z_limited=None, max_chain: int = 64) -> bool:
        """Whether ``mv``'s z follows the plan: a move with z travel right after a hold
        (:meth:`z_after_hold`), and every move right after such a one that ``z_limited`` (a
        predicate, e.g. :meth:`ZLimited.limited`) says ``max_z_accel`` binds.  The plan already
        accelerates such a move in z as hard as the firmware allows, so blending the command back
        from the plan's z onto its own there adds acceleration the firmware caps: the segments run
        late (2 ms on a z-only move after an XYZ move after a retraction, ``other_delta``).  The
        blend then falls in the first move after them."""
        for _ in range(max_chain):
            if self.z_after_hold(mv, moves):
                return True
            if z_limited is None or mv.kind != "move" or not z_limited(mv):
                return False
            mv = moves.get(mv.index - 1)
            if mv is None:
                return False
        return False

    def weights(self, move_index: np.ndarray, moves: dict, blend: int = 24, blend_moves: bool = True,
                z_limited=None, k_plan: np.ndarray | None = None, dt_s: float | None = None,
                new_stream: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Share of the plan in each sample of a chunk, for all axes and for z alone: 1 on the moves
        it takes over, a raised-cosine blend over ``blend`` samples either side (the compensated
        command pre-actuates a move before it starts and settles after it: without the blend the
        firmware would have to jump).  ``blend_moves=False``: the all-axes share without the blend
        (the pin repair has already brought the command onto the plan there).  ``z_limited``: see
        :meth:`z_follows_plan`.

        Chunks come in order: a blend runs on across a chunk boundary (the blend after a masked
        move from the last chunk's; the one before a masked move that starts in the next chunks
        from the planned moves ahead, with ``k_plan``, the samples' plan index, and ``dt_s``); at a
        ``new_stream`` (a homing jump) it starts afresh.  (Cut at a chunk boundary, a z move's
        settling blend jumped 26 um in one sample: 1.0 ms late on cylinder_prusa, other_delta.)"""
        if new_stream:
            self.since.clear()

        def zf(mv):
            return self.z_follows_plan(mv, moves, z_limited)

        m = self.mask(move_index, moves)
        mz = moves_where(move_index, moves, zf)
        w = self._blend_on(m, blend, "w", self._ahead(move_index, moves, self.bound, blend, k_plan, dt_s)) \
            if blend_moves else m.astype(float)
        return w, self._blend_on(mz, blend, "z", self._ahead(move_index, moves, zf, blend, k_plan, dt_s))

    @staticmethod
    def _ahead(move_index: np.ndarray, moves: dict, pred, blend: int, k_plan, dt_s) -> int | None:
        """Samples after a chunk's last one up to the first sample of a move ahead that ``pred``
        masks, if within ``blend`` (None: none)."""
        if k_plan is None or dt_s is None or not len(move_index) or k_plan[-1] < 0:
            return None
        k_last, mi = int(k_plan[-1]), int(move_index[-1])
        for idx in range(mi + 1, mi + 64):
            mv = moves.get(idx)
            if mv is None:
                return None
            k0 = int(np.ceil(mv.t_start_s / dt_s - 1e-9))
            if k0 - k_last - 1 >= blend:
                return None
            if mv.kind == "move" and pred(mv):
                return max(k0 - k_last - 1, 0)
        return None

    def _blend_on(self, m: np.ndarray, blend: int, key: str, ahead: int | None) -> np.ndarray:
        """:meth:`_blend` of a chunk with the stream's state (see :meth:`weights`)."""
        prev = self.since.get(key)
        self.since[key] = _since_after(prev, m)
        return self._blend(m, blend, prev, ahead)

    @staticmethod
    def _blend(m: np.ndarray, blend: int, prev: int | None = None, ahead: int | None = None) -> np.ndarray:
        """Raised-cosine blend around the masked samples of ``m``; ``prev``: samples from a masked
        sample before ``m`` to its start (minus one), ``ahead``: from ``m``'s end to one after it."""
        n = len(m)
        if not m.any() and prev is None and ahead is None:
            return np.zeros(n)
        idx = np.arange(n)
        on = np.nonzero(m)[0]
        j = np.searchsorted(on, idx)
        big = n + blend
        d_next = np.where(j < len(on), on[np.minimum(j, len(on) - 1)] - idx, big) if on.size else np.full(n, big)
        d_prev = np.where(j > 0, idx - on[np.maximum(j - 1, 0)], big) if on.size else np.full(n, big)
        if prev is not None:
            d_prev = np.where((j == 0), np.minimum(d_prev, prev + 1 + idx), d_prev)
        if ahead is not None:
            d_next = np.where(j >= len(on), np.minimum(d_next, n - idx + ahead), d_next)
        d = np.minimum(d_next, d_prev).astype(float)
        return np.where(d < blend, 0.5 * (1.0 + np.cos(np.pi * d / blend)), 0.0)


class ZLimited:
    """Which planned moves Klipper's delta rule ``max_z_accel * d/|dz|`` binds: moves with z travel
    whose acceleration cap is within ``factor`` of the acceleration the plan already uses.

    Their compensated command accelerates (in z) as hard as the firmware allows (the streaming
    inverse keeps it there, :attr:`InverseConfig.z_accel_bound`), so the firmware has no slack to
    recover time: written as segments of several samples, each segment's trapezoid leaves the
    speed behind the command's where the command's acceleration rises towards the cap, and the
    lag never comes back (0.5-1 ms per ramp on ``other_delta``).  Their samples (and ``blend``
    samples either side, where the command pre-actuates and settles) are written one by one.
    """

    def __init__(self, lim: ChainLimits, factor: float = 2.0):
        self.lim, self.factor = lim, factor
        self.cache: dict[int, bool] = {}
        self.last = None  # the last sample seen (m)
        self.since: int | None = None  # samples from the last limited sample to the last chunk's end

    def limited(self, mv) -> bool:
        b = self.cache.get(mv.index)
        if b is None:
            b = False
            dz = abs(mv.end_mm[2] - mv.start_mm[2])
            if mv.kind == "move" and dz > 1e-9 and (mv.accel_t_s > 0 or mv.decel_t_s > 0):
                d = float(np.linalg.norm(np.subtract(mv.end_mm[:3], mv.start_mm[:3])))
                b = bool(self.lim.max_z_accel * d / dz < self.factor * mv.accel_mm_s2)
            if len(self.cache) > 4096:
                self.cache.clear()
            self.cache[mv.index] = b
        return b

    def dense(self, move_index: np.ndarray, moves: dict, xyz_m: np.ndarray, blend: int = 24,
              min_step_m: float = 1.5e-6, k_plan: np.ndarray | None = None, dt_s: float | None = None,
              new_stream: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Mask of the samples written one by one, of the samples moved onto a z reversal, and
        the time of the reversal (samples after the sample moved onto it; None if none moved).

        Written one by one: the samples of the limited moves and ``blend`` samples either side,
        except where the command moved less than ``min_step_m`` since the previous sample (at a
        reversal: the writer would make a dwell of such a step, and the firmware would stand still
        for its time).  Where z reverses on those samples, the extreme sample is moved (in place,
        by under a micrometre) onto the vertex of the parabola through it and its neighbours: the
        firmware stops at the written extreme point, and braking at ``max_z_accel`` onto a point
        short of the command's turning point would take longer than the command does (0.2-0.8 ms
        late per reversal on ``other_delta``); the writer puts the point at the vertex's time (a
        sample's time would leave the segments either side up to half a sample early and late).
        ``xyz_m``: (n, 3) the command, m.
        """
        if new_stream:
            self.since = None
        lm = moves_where(move_index, moves, self.limited)
        prev, self.since = self.since, _since_after(self.since, lm)
        # (the blend runs on across chunk boundaries, as in LimitBound.weights)
        m = LimitBound._blend(lm, blend, prev, LimitBound._ahead(move_index, moves, self.limited, blend,
                                                                 k_plan, dt_s)) > 0
        prev = xyz_m[:1] if self.last is None else self.last[None]
        snapped = np.zeros(len(xyz_m), bool)
        shift = None
        if m.any() and len(xyz_m) > 2:
            z = np.concatenate([prev[:, 2], xyz_m[:, 2]])
            dz = np.diff(z)
            # sample k: z_k is an extreme (not a rounding-level wobble where the z travel starts)
            k = np.nonzero(m[:-1] & (dz[:-1] * dz[1:] < 0) & (np.minimum(np.abs(dz[:-1]), np.abs(dz[1:])) > 1e-8))[0]
            if k.size:
                zm, z0, zp = z[k], z[k + 1], z[k + 2]
                curv = zm - 2.0 * z0 + zp
                ok = np.abs(curv) > 0
                k, zm, z0, zp, curv = k[ok], zm[ok], z0[ok], zp[ok], curv[ok]
                tau = np.clip(0.5 * (zm - zp) / curv, -0.5, 0.5)  # vertex time, samples from k
                xyz_m[k, 2] = z0 - 0.25 * (zm - zp) * tau
                nxt, prv = xyz_m[k + 1, :2], np.where((k > 0)[:, None], xyz_m[np.maximum(k - 1, 0), :2], prev[:, :2])
                xyz_m[k, :2] += 0.5 * tau[:, None] * (nxt - prv)
                snapped[k] = True
                if k.size:
                    shift = np.zeros(len(xyz_m))
                    shift[k] = tau
        self.last = xyz_m[-1].copy()
        step = np.linalg.norm(np.diff(xyz_m, axis=0, prepend=prev), axis=1)
        keep = m & ((step >= min_step_m) | snapped)
        # the turning point is written; a sample just before it that is too close is not
        close = np.nonzero(snapped[1:] & (step[1:] < min_step_m))[0]
        keep[close] = False
        return keep, snapped, shift


def _since_after(prev: int | None, m: np.ndarray) -> int | None:
    """Samples from the last masked sample to the end of chunk ``m`` (a mask), given ``prev``, the
    same count at the end of the chunk before (None: no masked sample yet)."""
    on = np.nonzero(m)[0]
    return (len(m) - 1 - int(on[-1])) if on.size else (None if prev is None else prev + len(m))


class _NoAccel:
    """A :class:`ChainLimits` view with only the extruder's caps."""

    def __init__(self, lim):
        self.__dict__.update(lim.__dict__)
        self.accel = self.max_velocity = self.max_z_accel = self.max_z_velocity = float("inf")
        self.slow_xy2 = self.very_slow_xy2 = float("inf")


def z_hop(mv) -> bool:
    """A move that travels more in z than in XY (a z-hop, a layer change at one XY point)."""
    s, e = mv.start_mm, mv.end_mm
    dz = abs(e[2] - s[2])
    return bool(dz > 1e-9 and dz >= np.hypot(abs(e[0] - s[0]), abs(e[1] - s[1])))


def z_moving(move_index: np.ndarray, moves: dict) -> np.ndarray:
    """Samples whose planned move travels in z."""
    return moves_where(move_index, moves, lambda mv: abs(mv.end_mm[2] - mv.start_mm[2]) >= 1e-9)

