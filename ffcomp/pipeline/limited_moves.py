"""Which planned moves the firmware's own limits bind, sample by sample: the kernels behind the
pins, the plan fallback and the sample-by-sample writing of :mod:`ffcomp.pipeline.compensate_flow`.

:class:`LimitBound`: moves the extruder's limits bind (and z moves right after or before a hold).
:class:`ZLimited`: moves Klipper's delta rule ``max_z_accel * d/|dz|`` binds, written sample by
sample, with z reversals put on their vertex.  Plain functions of planned moves (``PlannedMove``)
and sample arrays; no files.
"""

from __future__ import annotations

import numpy as np

from ..gcode.chain_plan import ChainLimits, segment_limits
from ..gcode.extrusion import extruder_capped as _extruder_capped

__all__ = ["LimitBound", "ZLimited", "moves_where", "holds", "z_held", "z_moving", "z_hop"]


def moves_where(move_index: np.ndarray, moves: dict, pred) -> np.ndarray:
    """Mask of the samples whose planned move satisfies ``pred``."""
    uniq, inv = np.unique(move_index, return_inverse=True)
    hit = np.array([(mv := moves.get(int(mi))) is not None and bool(pred(mv)) for mi in uniq.tolist()], bool)
    return hit[inv.reshape(-1)] if len(hit) else np.zeros(len(move_index), bool)


def holds(move_index: np.ndarray, moves: dict) -> np.ndarray:
    """Samples whose planned move is an extruder-only move or a dwell (the nozzle stands still)."""
    return moves_where(move_index, moves, lambda mv: mv.kind != "move")


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
                z_limited=None) -> tuple[np.ndarray, np.ndarray]:
        """Share of the plan in each sample, for all axes and for z alone: 1 on the moves it takes
        over, a raised-cosine blend over ``blend`` samples either side (the compensated command
        pre-actuates a move before it starts and settles after it: without the blend the firmware
        would have to jump).  ``blend_moves=False``: the all-axes share without the blend (the pin
        repair has already brought the command onto the plan there).  ``z_limited``: see
        :meth:`z_follows_plan`."""
        m = self.mask(move_index, moves)
        return (self._blend(m, blend) if blend_moves else m.astype(float),
                self._blend(moves_where(move_index, moves, lambda mv: self.z_follows_plan(mv, moves, z_limited)),
                            blend))

    @staticmethod
    def _blend(m: np.ndarray, blend: int) -> np.ndarray:
        n = len(m)
        if not m.any():
            return np.zeros(n)
        idx = np.arange(n)
        on = np.nonzero(m)[0]
        j = np.searchsorted(on, idx)
        d_next = np.where(j < len(on), on[np.minimum(j, len(on) - 1)] - idx, n)
        d_prev = np.where(j > 0, idx - on[np.maximum(j - 1, 0)], n)
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
              min_step_m: float = 1.5e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
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
        m = LimitBound._blend(moves_where(move_index, moves, self.limited), blend) > 0
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

