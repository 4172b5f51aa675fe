"""The pin repair (:mod:`ffcomp.compensate.pin_repair`) on the compensated stream, in bounded memory.

Chunks of compensated carriage commands with their per-sample metadata go in; the same chunks (the
same lengths: a chunk boundary may be a stream boundary for the caller) come out, a little later,
with the command equal to the plan on pinned samples (extruder-only moves, dwells, moves the
firmware's limits bind, z-hops right after a retraction) and re-solved around them, and with the
free stretches that pass Klipper's delta caps re-solved to keep them.  Rows are held back until
every window that could reach them is complete (``margin`` samples after the last pinned run), so
the delay is a window plus a margin; a homing jump (a new stream) closes a window.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace
from typing import Callable, Iterable, Iterator

import numpy as np

from ..compensate.delta_cap import DeltaCap, cap_breaks, cap_window
from ..compensate.pin_repair import PulseResponses, RepairConfig, pinned_clusters, repair_window
from ..kinematics import jacobian
from ..linalg3 import max_abs3
from .options import REST_PRE

__all__ = ["PinStats", "pin_repaired"]


class PinStats:
    """What the repair did: windows solved, pinned samples, largest change of the command (m); the
    windows brought within Klipper's delta cap and their largest change (m)."""

    def __init__(self):
        self.windows = 0
        self.pinned_samples = 0
        self.max_change_m = 0.0
        self.cap_windows = 0  # windows brought within Klipper's delta cap (delta_cap)
        self.cap_max_change_m = 0.0


def _still_near(seed: np.ndarray, qref: np.ndarray, reach: int) -> np.ndarray:
    """The samples where the plan stands still that adjoin ``seed`` (a mask) through standing samples
    only, at most ``reach`` samples from it."""
    n = len(seed)
    still = np.zeros(n, bool)
    still[1:-1] = (max_abs3(qref[1:-1] - qref[:-2]) < 1e-12) & (max_abs3(qref[2:] - qref[1:-1]) < 1e-12)
    out = seed.copy()
    for _ in range(reach):
        grow = still & ~out & (np.r_[False, out[:-1]] | np.r_[out[1:], False])
        if not grow.any():
            break
        out |= grow
    return out & ~seed


#: :func:`_ramp_near`: the plan's nozzle z acceleration counts as at the firmware's ``max_z_accel``
#: from this share of it on
RAMP_PIN_SHARE = 0.95


def _ramp_near(seed: np.ndarray, steep: np.ndarray, z_m: np.ndarray, dt_s: float, limit_m_s2: float,
               reach: int) -> np.ndarray:
    """The samples of moves ``max_z_accel`` binds (``steep``) where the plan's nozzle z acceleration
    (``z_m``: its z, m) is at ``limit_m_s2`` (:data:`RAMP_PIN_SHARE`) that follow ``seed`` (a mask)
    through such samples only, at most ``reach`` samples after it.  (Only after: the plan's braking
    at the limit into a pinned run, pinned as well, put two random files 0.28 and 0.77 ms off the
    clock at the low-speed corners that followed, and took none off.)"""
    n = len(seed)
    hard = np.zeros(n, bool)
    if n >= 3:
        hard[1:-1] = np.abs(np.diff(z_m, 2)) >= RAMP_PIN_SHARE * limit_m_s2 * dt_s * dt_s
    hard &= steep
    out = seed.copy()
    if not hard.any():
        return out & ~seed
    for _ in range(reach):
        grow = hard & ~out & np.r_[False, out[:-1]]
        if not grow.any():
            break
        out |= grow
    return out & ~seed


#: how many times a window's cap pass runs (each linearised about the last one's command)
CAP_PASSES = 3
#: a window's cap pass that would change the command by more than this (m) is not taken
CAP_MAX_CHANGE_M = 10e-6


def pin_repaired(chunks: Iterable[tuple[np.ndarray, dict]], pin_fn: Callable[[dict], np.ndarray], model, dt_s: float,
                 cfg: RepairConfig = RepairConfig(), stats: PinStats | None = None, jump_m: float = 2e-3,
                 steep_fn: Callable[[dict], np.ndarray] | None = None,
                 zpin_fn: Callable[[dict], np.ndarray] | None = None,
                 z_limit_m_s2: float | None = None, cap: DeltaCap | None = None
                 ) -> Iterator[tuple[np.ndarray, dict]]:
    """Yield ``(q_cmd, meta)`` chunks with the pinned samples held on the plan (``meta["q"]``).

    ``pin_fn(meta)`` gives the pin mask of a chunk's samples when the chunk arrives; ``steep_fn(meta)``
    (optional) the samples of moves the firmware's ``max_z_accel`` binds: a window whose free
    samples touch them penalises the correction's acceleration ``cfg.steep_accel_factor`` times
    harder (in acceleration), since the firmware caps those segments, their junctions included, at
    ``max_z_accel * d/|dz|`` (a fast z move right after a pinned z-hop ran 7.7 ms late without).
    ``zpin_fn(meta)`` (optional): samples where only the nozzle's z is pinned to the plan
    (:func:`~ffcomp.compensate.pin_repair.repair_window`'s ``zpin``), x and y free.
    ``z_limit_m_s2`` (optional): the firmware's ``max_z_accel``, which the repaired command's nozzle z
    acceleration keeps (:func:`~ffcomp.compensate.pin_repair.repair_window`).  ``cap`` (optional,
    with ``cfg.cap_windows``): Klipper's delta caps (:mod:`ffcomp.compensate.delta_cap`); a free
    stretch whose command passes them, and what a pin window's repair leaves past them, are
    re-solved to keep them (by at most :data:`CAP_MAX_CHANGE_M`; counted in ``stats``).
    """
    stats = stats if stats is not None else PinStats()
    responses = PulseResponses(model, dt_s, cfg)
    geom = model.geometry
    ops: dict = {}  # factorised windows by (pose cell, pin pattern)
    jac: dict = {}  # Jacobian per pose cell
    M = max(int(round(cfg.margin_s / dt_s)), 1)
    buf_q = np.zeros((0, 3))
    buf_meta: dict[str, np.ndarray] | None = None
    buf_pin = np.zeros(0, bool)
    buf_rest = np.zeros(0, bool)  # pinned to the next sample's rest position (see solve)
    buf_next = np.zeros(0, bool)  # pinned after a moving pinned run's end (see solve)
    buf_qt = np.zeros((0, 3))  # that position
    buf_steep = np.zeros(0, bool)  # samples of moves max_z_accel binds (steep_fn)
    buf_zpin = np.zeros(0, bool)  # samples whose nozzle z alone is pinned (zpin_fn)
    f = max(float(cfg.steep_accel_factor), 1e-9)
    cfg_steep = replace(cfg, accel_xy_m_s2=cfg.accel_xy_m_s2 / f, accel_z_m_s2=cfg.accel_z_m_s2 / f)
    repaired_upto = 0  # buffer rows before this belong to clusters already repaired
    buf_cap = np.zeros(0, bool)  # free samples past Klipper's delta cap (cap_breaks)
    cap_upto = 0  # buffer rows before this were checked
    sizes: deque[int] = deque()  # lengths of the chunks in the buffer

    def capped(q: np.ndarray, xp: np.ndarray, qp: np.ndarray, pw: np.ndarray, pose, key, J) -> np.ndarray:
        """``q`` (a window's command; ``pw`` its pins, held) brought within Klipper's delta cap where
        it passes it (:func:`cap_breaks`): :func:`cap_window`, again on its result (its rows are
        linearised about the command) up to :data:`CAP_PASSES` times."""
        jr, q0 = None, q
        for _ in range(CAP_PASSES):
            if not np.any(cap_breaks(geom, q, xp, cap, pw, q_plan=qp)):
                break
            if jr is None:
                jr = jacobian(geom, xp)
            new = cap_window(responses.at(pose), q, J, jr, xp, cap, cfg, pin=pw, cache=ops, key=key)
            if new is q:
                break
            if float(np.max(np.abs(new - q0))) > CAP_MAX_CHANGE_M:
                return q0  # the stretch the firmware cannot run on its clock is not a small change away
            q = new
        if q is not q0:
            stats.cap_windows += 1
            stats.cap_max_change_m = max(stats.cap_max_change_m, float(np.max(np.abs(q - q0))))
        return q

    def solve(final: bool) -> int:
        """Repair the clusters whose windows are complete; returns how many rows are final."""
        nonlocal repaired_upto, cap_upto
        n = len(buf_q)
        if cap is not None and cfg.cap_windows and n - cap_upto >= 3:
            c0 = max(cap_upto - 1, 0)
            br = cap_breaks(geom, buf_q[c0:], buf_meta["xyz"][c0:], cap, q_plan=buf_meta["q"][c0:])
            buf_cap[c0 + 1:n - 1] |= br[1:-1]
            cap_upto = n - 1
        # stream boundaries (homing jumps, and the start of every stream's pre-roll: after a stop
        # the firmware stands still while it runs the stop's command): windows never cross them (a
        # z-hop's repair after a G10 reached back into the stream before and moved its resting
        # command by up to 16 um in its last 40 ms, the firmware's flush at the G10 then slowed it)
        qref = buf_meta["q"]
        jumps = np.nonzero(max_abs3(np.diff(qref, axis=0)) > jump_m)[0] + 1 if n > 1 else np.zeros(0, int)
        mi_all = buf_meta.get("move_index")
        if mi_all is not None and n > 1:
            pre = mi_all == REST_PRE
            jumps = np.union1d(jumps, np.nonzero(pre[1:] & ~pre[:-1])[0] + 1)
        bounds = np.r_[0, jumps, n].astype(int)
        # the plan comes to rest between two samples before a pinned run where it stands still (a
        # hold): the last sample before the run is pinned too, to the rest position, so the firmware
        # stands there when the hold begins (rather than covering the last sub-sample of motion from
        # rest after it) and the repair sees it (the command arrives there at the firmware's ramps);
        # and where the plan stands still up to a pinned run that leaves rest (RepairConfig's
        # rest_before_go), the sample before it stands on that rest point
        orig = buf_pin & ~buf_rest & ~buf_next
        st = np.nonzero(orig[1:] & ~orig[:-1])[0]  # st free, st + 1 pinned
        st = st[(st + 2 < n) | final]
        if st.size:
            nxt = np.minimum(st + 2, n - 1)
            hold = max_abs3(qref[nxt] - qref[st + 1]) < 1e-9  # the plan stands still in the run
            still = hold | (cfg.rest_before_go & (st > 0)
                            & (max_abs3(qref[st] - qref[np.maximum(st - 1, 0)]) < 1e-12))  # ... or up to it
            sel = still & ~buf_rest[st]
            st, hold = st[sel], hold[sel]
            buf_rest[st] = buf_pin[st] = True
            buf_qt[st] = np.where(hold[:, None], qref[st + 1], qref[st])
        # a pinned run that moves (a z-hop) up to where its move ends takes the next move's first
        # sample too, on the plan: the writer then ends the run on the plan's corner at its time
        # (the firmware takes the corner as the plan does, not a sample early)
        orig = buf_pin & ~buf_next
        en = np.nonzero(orig[:-1] & ~orig[1:])[0]  # en pinned, en + 1 free
        en = en[(en > 0) & ~buf_next[np.minimum(en + 1, n - 1)]]
        mi = buf_meta.get("move_index")
        if en.size and mi is not None:
            turn = (mi[en + 1] != mi[en]) & (max_abs3(qref[en] - qref[en - 1]) > 1e-9)
            en = en[turn]
            buf_next[en + 1] = buf_pin[en + 1] = True
        qtgt = np.where(buf_rest[:, None], buf_qt, qref)
        safe = n if final else max(n - M, 0)
        pin_now = buf_pin
        if cfg.still_near_steep and n > 2:
            ext = _still_near(buf_pin & buf_steep, qref, 2 * M)
            if repaired_upto > 0:  # never into a repaired cluster's window (it would merge and be skipped)
                ext[:repaired_upto + M] = False
            pin_now = buf_pin | ext
        if cfg.ramp_pins and z_limit_m_s2 is not None and n > 2:
            ext = _ramp_near(pin_now, buf_steep, buf_meta["xyz"][:, 2], dt_s, z_limit_m_s2, 2 * M)
            if repaired_upto > 0:  # (as above)
                ext[:repaired_upto + M] = False
            pin_now = pin_now | ext
        any_pin = pin_now | buf_zpin
        marks = any_pin | (buf_cap & ~pin_now)
        for s0, s1 in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
            if not marks[s0:s1].any():
                continue
            for a, b in pinned_clusters(marks[s0:s1], M):
                a, b = a + s0, b + s0
                if not final and s1 == n and b + M > n:  # the window (or the run) is not all here yet
                    return max(min(safe, a - M), 0)
                if a < repaired_upto:
                    continue
                w0, w1 = max(a - M, s0), min(b + M, s1)
                old = buf_q[w0:w1]
                pose = buf_meta["xyz"][(a + b) // 2]
                key = responses.key(pose)
                J = jac.get(key)
                if J is None:
                    J = jac[key] = jacobian(geom, responses.centre(key, pose))
                if not any_pin[a:b].any():  # a free stretch past the delta cap (only cap marks it)
                    new = capped(old, buf_meta["xyz"][w0:w1], buf_meta["q"][w0:w1], np.zeros(w1 - w0, bool), pose,
                                 key, J)
                    buf_q[w0:w1] = new
                    repaired_upto = b
                    continue
                steep = bool(np.any(buf_steep[w0:w1] & ~any_pin[w0:w1]))
                printing = None
                if cfg.print_weight != 1.0 and "e" in buf_meta:  # the plan extrudes while it moves in XY
                    e_w, x_w = buf_meta["e"][w0:w1], buf_meta["xyz"][w0:w1, :2]
                    seg = (np.diff(e_w) > 1e-9) & (np.max(np.abs(np.diff(x_w, axis=0)), axis=1) > 1e-12)
                    printing = np.r_[seg, seg[-1:]] if seg.size else np.zeros(w1 - w0, bool)
                new = repair_window(responses.at(pose), old, qtgt[w0:w1], pin_now[w0:w1], J, dt_s,
                                    cfg_steep if steep else cfg, cache=ops, key=(key, steep),
                                    zpin=buf_zpin[w0:w1] & ~pin_now[w0:w1], z_limit_m_s2=z_limit_m_s2,
                                    printing=printing)
                if cap is not None and cfg.cap_windows and not buf_zpin[w0:w1].any():
                    # what the repair leaves past the delta cap on its free samples: re-solved with
                    # the pins held (every sample a knot)
                    new = capped(new, buf_meta["xyz"][w0:w1], buf_meta["q"][w0:w1], pin_now[w0:w1], pose, key, J)
                stats.max_change_m = max(stats.max_change_m, float(np.max(np.abs(new - old))))
                stats.windows += 1
                stats.pinned_samples += int(any_pin[a:b].sum())
                buf_q[w0:w1] = new
                repaired_upto = b
        return safe

    for qc, meta in chunks:
        pin = np.asarray(pin_fn(meta), bool)
        buf_q = np.vstack([buf_q, qc])
        buf_pin = np.concatenate([buf_pin, pin])
        buf_rest = np.concatenate([buf_rest, np.zeros(len(pin), bool)])
        buf_next = np.concatenate([buf_next, np.zeros(len(pin), bool)])
        buf_steep = np.concatenate([buf_steep, np.asarray(steep_fn(meta), bool) if steep_fn is not None
                                    else np.zeros(len(pin), bool)])
        buf_zpin = np.concatenate([buf_zpin, np.asarray(zpin_fn(meta), bool) if zpin_fn is not None
                                   else np.zeros(len(pin), bool)])
        buf_qt = np.vstack([buf_qt, np.zeros((len(pin), 3))])
        buf_cap = np.concatenate([buf_cap, np.zeros(len(pin), bool)])
        if buf_meta is None:
            buf_meta = {k: np.asarray(v) for k, v in meta.items()}
        else:
            buf_meta = {k: np.concatenate([buf_meta[k], meta[k]]) for k in buf_meta}
        sizes.append(len(qc))
        safe = solve(final=False)
        # whole chunks only, as they came (a chunk boundary may be a stream boundary for the caller)
        while sizes and sizes[0] <= safe:
            k = sizes.popleft()
            out_q, out_meta = buf_q[:k].copy(), {key: v[:k] for key, v in buf_meta.items()}
            buf_q, buf_pin, buf_rest, buf_qt = buf_q[k:], buf_pin[k:], buf_rest[k:], buf_qt[k:]
            buf_next, buf_steep, buf_zpin = buf_next[k:], buf_steep[k:], buf_zpin[k:]
            buf_cap = buf_cap[k:]
            cap_upto = max(cap_upto - k, 0)
            buf_meta = {key: v[k:] for key, v in buf_meta.items()}
            repaired_upto = max(repaired_upto - k, 0)
            safe -= k
            yield out_q, out_meta
    if buf_meta is not None and len(buf_q):
        solve(final=True)
        while sizes:
            k = sizes.popleft()
            yield buf_q[:k].copy(), {key: v[:k] for key, v in buf_meta.items()}
            buf_q = buf_q[k:]
            buf_meta = {key: v[k:] for key, v in buf_meta.items()}
