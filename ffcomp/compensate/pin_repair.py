"""Pinning the command where a G-code file cannot move it: a local least-squares repair.

A G-code file cannot move the nozzle during an extruder-only move (a retraction) or a dwell, and a
firmware limit (``max_z_accel``, the extruder's caps) may forbid a command that accelerates harder
than the plan on some moves.  On those samples (*pins*) the command must equal the plan.  Cutting
the unconstrained command ``c*`` there would excite the machine; instead the command around each
pinned stretch is re-solved:

    c = c* + Delta,  Delta = q - c* on pinned samples,  Delta = 0 outside the window,

and the free ``Delta`` (piecewise linear through knots every ``knot_samples``, continuous into the
pinned values) minimises the model's response to ``Delta`` over the window and a ringing tail,
plus a small penalty on its second difference:

    min || H * Delta ||^2 / err^2 + sum_k |W J a_k|^2,   a_k = D2 Delta_k / dt^2

(``J`` the Jacobian at the window's pose: the penalty is on the nozzle's acceleration, with its own
scale for z, because Klipper caps a segment's acceleration by ``max_z_accel * d/|dz|``: a correction
that jerks the nozzle in z would make the firmware run late)

``H`` is the pulse response, carriage command -> carriage position, of the model linearised at the
window's pose (first-order hold, as the firmware moves linearly between points), cached on a pose
grid.  Since ``c*`` already makes the output follow the reference, the response to ``Delta`` is
the whole change of the tracking error.  Pure numerics: no files, no G-code.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.signal import fftconvolve
from scipy.sparse import csr_matrix

from ..kinematics import reachable
from ..model.lpv import LpvModel, state_space
from .qp import active_set_qp

#: factorised windows kept by :func:`repair_window` (an LRU cache; about 1 MB each)
MAX_CACHED_WINDOWS = 256

__all__ = ["RepairConfig", "PulseResponses", "repair_window", "pinned_clusters"]


@dataclass(frozen=True)
class RepairConfig:
    """Settings of the pin repair (documented defaults).

    margin_s : free command before and after a pinned stretch that the repair may change, s
    tail_s : response after the window that counts in the objective (the ringing), s
    tail_stride : every how many samples of that tail count (it is smooth)
    knot_samples : spacing of the correction's knots, samples
    err_m : response error that costs as much as ...
    accel_xy_m_s2, accel_z_m_s2 : ... this much nozzle acceleration of the correction in one sample
        (in XY and in z), m/s^2
    cell_xy_m, cell_z_m : pose grid of the cached pulse responses, m
    pin_z_after_hold, pin_z_before_hold : pin a move with z travel right after / right before an
        extruder-only move or dwell (a z-hop after a retraction, the move down before an unretract)
    z_only_hops : (experimental, off) the z-hop after a hold pins the nozzle's z alone to the plan,
        its x and y free: the command pre-actuates the travel after the hop during it.  The move
        down before a hold stays pinned whole.  With ``lift_xy_accel_factor`` 100, on
        ``cube_prusa.gcode`` (simulated, lag-aligned RMS over the whole file) 13.3 -> 11.2 um on the
        default profile and 16.3 -> 14.2 um on other_delta, x and y by a third to a half; but the
        contour RMS rises 5.9 -> 6.7 / 7.6 -> 8.3 um, and over the extruded samples (93 % of the
        file) neither moves (5.9 / 2.0 um default, 6.7 / 2.7 um other_delta): the gain is the
        travels' own tracking, not the part's.  The fidelity bench's z-hop row: lag 0.457 -> 0.406 /
        0.319 -> 0.236.
    lift_xy_accel_factor : with ``z_only_hops``, the acceleration penalty of the x/y correction on
        samples whose z alone is pinned (a lift) is this much heavier, so the correction runs
        nearly straight there: Klipper slows the short segments of a lift at ``max_z_accel``
        wherever they turn (centripetal junction rule), and with the factor 1 the bench's z-hop
        row ran 2.8 ms late on other_delta (now -0.62 ms, clock error 16 um)
    edge_weight, edge_samples : the acceleration penalty is this much heavier within about this many
        samples of a pin (the firmware starts there from the plan's state)
    lead_in_s : the last this-many seconds of a move that runs into a pinned move which
        ``max_z_accel`` binds (a z-hop's travel into the move down) are pinned too: the travel
        arrives at the corner on the plan, not bending in z while it brakes (Klipper caps a
        segment's acceleration at ``max_z_accel * d/|dz|``; on the fidelity bench's z-hop row,
        other_delta, the re-planned output ran 0.63 ms early there, 13 um off the command, and with
        2 ms 0.25 ms and 4 um; 1 ms left 0.32 ms, 3-5 ms no better than 2; with the cap pass,
        ``cap_windows``, 2 ms left that row at +0.200 ms and 2.5 ms -0.031 ms)
    lead_in_z_s : the same for a travel that moves more in z than in XY (a z move into a pinned z
        move): 2.5 ms there put a random file's clock 21.7 um off (6.6 with 2 ms) and another's
        drift +0.09 -> +0.24 ms
    lead_in_printed_s : the same for a printed line that runs into such a pinned move (a layer
        change's lift right after the line, ``pin_layer_lifts``): its last this-many seconds are
        pinned.  The free command pre-actuated the lift while the plan braked the line in XY at
        the print acceleration, so the last milliseconds ran steep at that braking, past Klipper's
        centripetal cap ``max_z_accel / |u_z|`` (which the repair's exact bound, licensed by the
        command's own acceleration there, cannot take back).  On ``other_delta`` (scratch runs of
        the nineteenth round): cube_prusa's drift +0.25 -> +0.12 ms (events beyond 0.2 ms 1 -> 0),
        cylinder_prusa's events beyond 0.2 ms 36 -> 3, cube_wipe_prusa -0.28 -> +0.17 ms; the price
        is the printed lines' contour on cube_prusa (truth plant) 2.54 -> 2.67 um (lag 5.34 -> 5.39);
        1 ms kept half of the clock's gain for 2.62 um
    lead_in_extruder : the lead-ins above also run into a pinned move that the plan enters at
        Klipper's extruder junction speed, ``instantaneous_corner_velocity / |r - r_prev|`` (a travel
        into an extruding or retracting lift: the free command came into that corner at 5-7 mm/s
        where the rule allows 1.4, and the lift ran 0.3-0.6 ms late;
        :func:`~ffcomp.pipeline.limited_moves.enters_by_extruder`)
    lead_in_wet : ``lead_in_printed_s`` also where the pinned move extrudes or retracts itself (a
        printed line into a retracting lift the plan enters at ``icv / |diff_r|``, 0.8 mm/s: the
        free command came into that corner at 11 mm/s and the lift ran 0.93 ms late; random files
        of ``bench_random_drift.py``, both seeds: default 6 -> 3 of 140 beyond 0.2 ms, other_delta
        19 -> 16, one file worse, -0.59 -> +0.71 ms; the fidelity bench and the sample files as
        before; thirty-third round)
    steep_accel_factor : in windows whose free command lies on moves ``max_z_accel`` binds, the
        acceleration scales above are divided by this (the firmware caps those segments and their
        junctions at ``max_z_accel * d/|dz|``)
    still_near_steep : the samples where the plan stands still next to a pinned move that
        ``max_z_accel`` binds (up to twice ``margin_s`` of them) are pinned too: before a pinned lift
        from rest the free command pre-actuated the lift, and the repair turned that into a dip and
        rise by 13 um that the firmware ran late (cube_cura after its homing, +0.21 ms on the default
        profile); after a pinned z move to rest it settled by 8 um in z (relative_extrusion,
        other_delta, +0.61 ms)
    pin_layer_lifts : a lift (more z than XY) that ``max_z_accel`` binds right after a printed line
        (a layer change without a retraction) is pinned: the free command pre-actuated it during the
        line and turned from XY into z within a few samples, which Klipper's centripetal rule at
        ``max_z_accel / |u_z|`` takes slower than the command (other_delta: the random files' median
        drift 0.29 -> 0.20 ms, cube_wipe_prusa +0.37 -> -0.33 ms)
    cap_windows : the free command that accelerates, along or across its path, harder than
        Klipper's delta cap ``max_z_accel * d/|dz|`` allows (and harder than the plan there) is
        changed as little as the model's response allows to keep it
        (:mod:`ffcomp.compensate.delta_cap`), and so is what a pin window's repair leaves past it.
        The fidelity bench's z travel on other_delta: +0.93 -> +0.12 ms (an XZ reversal, where the
        correction turned the command steeper than the plan while it braked at 10,000 mm/s^2)
    ramp_pins : the free samples right after a pinned run where the plan's nozzle z acceleration is at
        ``max_z_accel`` (its ramp in a move that limit binds: a free lift on from a pinned layer
        change's lift) are pinned too, up to ``2 margin_s``: while the plan ramps at the limit
        the command cannot take up or give back a correction there at all (the repair's bounded
        solve finds no feasible command; unbounded, it ramped 100 um in 15 ms, 4,600 mm/s^2 in a
        3,000 mm/s^2 lift, 2.2 ms off the clock on a random file on other_delta); the repair's window
        then does it after the ramp
    rest_before_go : where the plan stands still up to a pinned run that leaves rest (an extruding
        z-only lift right after a stream's pre-roll), the free sample before the run is pinned to
        that rest point as well.  The pre-roll's pre-actuation ended 0.5 um beside the lift's line,
        so the lift's first segment was an XY move to Klipper, without the extruder's acceleration
        cap the plan has: it ran 0.3 ms early (a random file on the default profile)
    print_weight : the model's response on the samples where the plan prints (extrudes while it
        moves in XY: what marks the part) counts this many times in the objective; the rest (the hold, a
        lift, the travel) takes more of the change.  ``cube_prusa.gcode`` simulated on
        ``other_delta_truth.toml``, its printed lines' lag-aligned / contour RMS: 6.84 / 2.85 um at 1
        (unweighted), 5.32 / 2.51 at 2 (the default), 4.76 / 2.48 at 3, 4.37 / 2.37 um at 5; the
        whole file's 16.6 / 7.9 -> 16.5 / 8.1 um at 2.  The price is the clock where the lifts run
        at ``max_z_accel``: on other_delta the file's drift -0.27 -> -0.50 ms at 2 (-0.59 at 3)
    """

    margin_s: float = 0.04
    tail_s: float = 0.3
    knot_samples: int = 3
    err_m: float = 1e-6
    accel_xy_m_s2: float = 0.5
    accel_z_m_s2: float = 0.1
    cell_xy_m: float = 0.05
    cell_z_m: float = 0.05
    pin_z_after_hold: bool = True
    tail_stride: int = 3
    edge_weight: float = 30.0
    edge_samples: float = 3.0
    pin_z_before_hold: bool = True
    steep_accel_factor: float = 5.0
    z_only_hops: bool = False
    lift_xy_accel_factor: float = 100.0
    lead_in_s: float = 0.0025
    lead_in_z_s: float = 0.002
    lead_in_printed_s: float = 0.002
    lead_in_extruder: bool = True
    lead_in_wet: bool = True
    still_near_steep: bool = True
    ramp_pins: bool = True
    rest_before_go: bool = True
    pin_layer_lifts: bool = True
    print_weight: float = 2.0
    cap_windows: bool = True


class PulseResponses:
    """Pulse responses ``H[k]`` (L, 3, 3) of the model in the joint frame, per pose cell."""

    def __init__(self, model: LpvModel, dt_s: float, cfg: RepairConfig = RepairConfig()):
        self.model, self.dt, self.cfg = model, dt_s, cfg
        self.L = max(int(round(cfg.tail_s / dt_s)), 8)
        self.cache: dict[tuple, np.ndarray] = {}

    def key(self, xyz_m: np.ndarray) -> tuple:
        c = self.cfg
        return (int(np.floor(xyz_m[0] / c.cell_xy_m + 0.5)), int(np.floor(xyz_m[1] / c.cell_xy_m + 0.5)),
                int(np.floor(xyz_m[2] / c.cell_z_m + 0.5)))

    def centre(self, k: tuple, xyz_m: np.ndarray) -> np.ndarray:
        """The pose a cell stands for: its centre, or ``xyz_m`` where the centre is unreachable."""
        c = self.cfg
        pose = np.array([k[0] * c.cell_xy_m, k[1] * c.cell_xy_m, max(k[2] * c.cell_z_m, 0.0)])
        return pose if bool(reachable(self.model.geometry, pose)) else np.asarray(xyz_m, float)

    def at(self, xyz_m: np.ndarray) -> np.ndarray:
        k = self.key(xyz_m)
        H = self.cache.get(k)
        if H is None:
            sys_ = state_space(self.model, self.centre(k, xyz_m), frame="joint", dt_s=self.dt, method="foh")
            A, B, C, D = (np.asarray(x) for x in (sys_.A, sys_.B, sys_.C, sys_.D))
            H = np.empty((self.L, 3, 3))
            H[0] = D
            x = B.copy()
            for i in range(1, self.L):
                H[i] = C @ x
                x = A @ x
            if len(self.cache) > 4096:
                self.cache.clear()
            self.cache[k] = H
        return H


def pinned_clusters(pin: np.ndarray, gap: int) -> list[tuple[int, int]]:
    """Pinned runs ``[a, b)`` of a mask, merged when fewer than ``gap`` free samples separate them."""
    p = np.asarray(pin, bool)
    if not p.any():
        return []
    d = np.diff(np.r_[0, p.astype(np.int8), 0])
    st, en = np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]
    out = [[int(st[0]), int(en[0])]]
    for a, b in zip(st[1:].tolist(), en[1:].tolist()):
        if a - out[-1][1] < gap:
            out[-1][1] = b
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def _interp_matrix(pin: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of the window's samples from its knots.

    Knots: every pinned sample (fixed), zero knots just outside the window (fixed), and free knots
    every ``m`` samples in each free run.  Returns ``S`` (n, n_free) and ``F`` (n, n) mapping the
    free knot values and the pinned samples' values (zero where not pinned) to all samples.
    """
    n = len(pin)
    free_pos = []
    k = 0
    while k < n:
        if pin[k]:
            k += 1
            continue
        b = k
        while b < n and not pin[b]:
            b += 1
        # free run [k, b): knots about m apart over it, both of its ends included
        cnt = max(int(np.ceil((b - k) / m)), 1)
        pos = np.unique(np.round(np.linspace(k, b - 1, cnt + 1 if cnt > 1 else 1)).astype(int))
        free_pos.extend(pos.tolist())
        k = b
    free_pos = np.array(sorted(set(free_pos)), int)
    fixed_pos = np.r_[-1, np.nonzero(pin)[0], n]
    kp = np.r_[free_pos, fixed_pos]
    is_free = np.r_[np.ones(len(free_pos), bool), np.zeros(len(fixed_pos), bool)]
    order = np.argsort(kp, kind="stable")
    kp, is_free = kp[order], is_free[order]
    col = np.full(len(kp), -1)
    col[is_free] = np.arange(is_free.sum())
    samp = np.arange(n)
    j = np.searchsorted(kp, samp, side="right")  # kp[j-1] <= k < kp[j]
    left, right = kp[j - 1], kp[np.minimum(j, len(kp) - 1)]
    span = np.maximum(right - left, 1)
    wr = (samp - left) / span
    wl = 1.0 - wr
    S = np.zeros((n, len(free_pos)))
    F = np.zeros((n, n))
    for knot_idx, w in ((j - 1, wl), (np.minimum(j, len(kp) - 1), wr)):
        pos = kp[knot_idx]
        fr = is_free[knot_idx]
        S[samp[fr], col[knot_idx[fr]]] += w[fr]
        inside = ~fr & (pos >= 0) & (pos < n)
        F[samp[inside], pos[inside]] += w[inside]
    return S, F


def _edge_weights(pin: np.ndarray, cfg: RepairConfig) -> np.ndarray:
    """Weight (n,) of the acceleration penalty at each sample: ``1 + edge_weight exp(-d / edge_samples)``
    with ``d`` the distance to the nearest pinned sample (1 everywhere without pins)."""
    n = len(pin)
    at = np.nonzero(pin)[0]
    if cfg.edge_weight <= 0 or not len(at):
        return np.ones(n)
    idx = np.arange(n)
    j = np.clip(np.searchsorted(at, idx), 0, len(at) - 1)
    dist = np.minimum(np.abs(idx - at[j]), np.abs(idx - at[np.maximum(j - 1, 0)]))
    return 1.0 + cfg.edge_weight * np.exp(-dist / cfg.edge_samples)


def _second_difference(S: np.ndarray) -> np.ndarray:
    """Second difference of the rows of ``S`` (n, m), zero beyond both ends (the correction vanishes
    outside the window): (n, m)."""
    z = np.zeros((1, S.shape[1]))
    return np.diff(np.vstack([z, S, z]), 2, axis=0)


def _cached(cache: dict | None, ck, build):
    """``build()``, or the value ``cache`` holds for ``ck`` (a least-recently-used cache of at most
    :data:`MAX_CACHED_WINDOWS` entries, about 1 MB each; None: no cache)."""
    if cache is None:
        return build()
    op = cache.pop(ck, None)
    if op is None:
        while len(cache) >= MAX_CACHED_WINDOWS:  # least recently used first
            cache.pop(next(iter(cache)))
        op = build()
    cache[ck] = op  # most recently used last
    return op


class _Operator:
    """The parts of one window's least squares that depend only on its pin pattern and pose cell."""

    __slots__ = ("S", "F", "Phi", "keep", "D2S", "wrow", "P", "factor", "nf", "W")


def _operator(H: np.ndarray, pin: np.ndarray, J: np.ndarray, dt_s: float, cfg: RepairConfig) -> _Operator:
    op = _Operator()
    op.W = None
    n = len(pin)
    op.S, op.F = _interp_matrix(pin, cfg.knot_samples)
    nf = op.nf = op.S.shape[1]
    if nf == 0:
        return op
    # responses of the free knots' hats per (output i, input j); the ringing after the window is
    # smooth: every tail_stride-th row of it is enough
    R = np.stack([fftconvolve(op.S, H[:, i, j][:, None], axes=0) for i in range(3) for j in range(3)])
    op.keep = np.r_[np.arange(min(n, R.shape[1])), np.arange(n, R.shape[1], cfg.tail_stride)]
    R = R[:, op.keep]
    rows = R.shape[1]
    Phi = np.zeros((3 * rows, 3 * nf))
    for i in range(3):
        for j in range(3):
            Phi[i * rows:(i + 1) * rows, j * nf:(j + 1) * nf] = R[3 * i + j]
    op.Phi = Phi
    # nozzle acceleration of the correction (second difference, zeros beyond the window), weighted
    # per axis: P = J^T W J / dt^4 ...
    D2S = _second_difference(op.S)
    Wd = np.array([1.0 / cfg.accel_xy_m_s2**2, 1.0 / cfg.accel_xy_m_s2**2, 1.0 / cfg.accel_z_m_s2**2])
    op.P = (J.T * Wd) @ J / dt_s**4
    # ... and weighted up next to the pins: there the firmware starts from the plan's state (from
    # rest after a hold) and cannot take a jump
    op.wrow = np.sqrt(_edge_weights(pin, cfg))[:, None]  # row k of the second difference is centred on sample k
    op.D2S = D2S * op.wrow
    G = Phi.T @ Phi / cfg.err_m**2 + np.kron(op.P, op.D2S.T @ op.D2S)
    G[np.diag_indices_from(G)] += 1e-12 * max(float(np.mean(np.diag(G))), 1e-30)
    op.factor = cho_factor(G, lower=True, check_finite=False)
    return op


def _weighted(op: _Operator, printing: np.ndarray, cfg: RepairConfig) -> _Operator:
    """``op`` with the response on the samples where the plan prints (``printing``, the window's
    samples) counting ``cfg.print_weight`` times: the same parts, the weights and their factor."""
    n = len(printing)
    rows = len(op.keep)
    w = np.ones(rows)
    inside = op.keep < n
    w[inside] = np.where(printing[op.keep[inside]], cfg.print_weight, 1.0)
    out = copy.copy(op)  # (shares op's arrays)
    out.W = np.tile(w * w, 3)  # (squared: the normal equations' row weights)
    G = (op.Phi.T * out.W) @ op.Phi / cfg.err_m**2 + np.kron(op.P, op.D2S.T @ op.D2S)
    G[np.diag_indices_from(G)] += 1e-12 * max(float(np.mean(np.diag(G))), 1e-30)
    out.factor = cho_factor(G, lower=True, check_finite=False)
    return out


class _FrameOperator:
    """:class:`_Operator` for pins per nozzle component (the correction solved in the nozzle frame)."""

    __slots__ = ("S", "F", "Phi", "keep", "D2S", "wrow", "factor", "nf", "Hn", "Jinv")


def _frame_operator(H: np.ndarray, pins: np.ndarray, J: np.ndarray, dt_s: float, cfg: RepairConfig
                    ) -> _FrameOperator:
    """The least squares of :func:`repair_window` with ``pins`` (n, 3) per nozzle component: the
    correction is ``Delta = J^-1 delta`` with ``delta`` the nozzle's, each of its components
    interpolated from its own knots (fixed where that component is pinned), its acceleration
    penalty diagonal (x and y at ``accel_xy_m_s2``, z at ``accel_z_m_s2``)."""
    op = _FrameOperator()
    n = len(pins)
    op.Jinv = np.linalg.inv(J)
    op.Hn = H @ op.Jinv  # carriage response to a nozzle-frame command
    mats = [_interp_matrix(pins[:, k], cfg.knot_samples) for k in range(3)]
    op.S, op.F = [m[0] for m in mats], [m[1] for m in mats]
    op.nf = [S.shape[1] for S in op.S]
    R = [[fftconvolve(op.S[k], op.Hn[:, i, k][:, None], axes=0) for k in range(3)] for i in range(3)]
    L = R[0][0].shape[0]
    op.keep = np.r_[np.arange(min(n, L)), np.arange(n, L, cfg.tail_stride)]
    op.Phi = np.vstack([np.hstack([R[i][k][op.keep] for k in range(3)]) for i in range(3)])
    wd = (1.0 / cfg.accel_xy_m_s2, 1.0 / cfg.accel_xy_m_s2, 1.0 / cfg.accel_z_m_s2)
    op.wrow = [(np.sqrt(_edge_weights(pins[:, k], cfg)) * wd[k] / dt_s**2)[:, None] for k in range(3)]
    lift = pins[:, 2] & ~pins[:, 0]  # z pinned, x and y free: the hop's segments turn with x and y
    if cfg.lift_xy_accel_factor != 1.0 and lift.any():
        for k in (0, 1):
            op.wrow[k] = op.wrow[k] * np.where(lift, cfg.lift_xy_accel_factor, 1.0)[:, None]
    op.D2S = [_second_difference(op.S[k]) * op.wrow[k] for k in range(3)]
    nt = sum(op.nf)
    G = op.Phi.T @ op.Phi / cfg.err_m**2
    o = 0
    for k in range(3):
        G[o:o + op.nf[k], o:o + op.nf[k]] += op.D2S[k].T @ op.D2S[k]
        o += op.nf[k]
    if nt:
        G[np.diag_indices_from(G)] += 1e-12 * max(float(np.mean(np.diag(G))), 1e-30)
        op.factor = cho_factor(G, lower=True, check_finite=False)
    return op


def _repair_frames(op: _FrameOperator, c: np.ndarray, q: np.ndarray, pins: np.ndarray, J: np.ndarray,
                   cfg: RepairConfig) -> np.ndarray:
    fixed = np.where(pins, (q - c) @ J.T, 0.0)  # the nozzle-frame correction the pins ask for
    o = np.stack([op.F[k] @ fixed[:, k] for k in range(3)], 1)
    out = o.copy()
    if sum(op.nf):
        Yo = np.stack([sum(np.convolve(op.Hn[:, i, k], o[:, k]) for k in range(3)) for i in range(3)], 1)[op.keep]
        rhs = -(op.Phi.T @ Yo.T.reshape(-1)) / cfg.err_m**2
        off = 0
        for k in range(3):
            D2o = _second_difference(o[:, k:k + 1]) * op.wrow[k]
            rhs[off:off + op.nf[k]] -= (op.D2S[k].T @ D2o)[:, 0]
            off += op.nf[k]
        z = cho_solve(op.factor, rhs, check_finite=False)
        off = 0
        for k in range(3):
            out[:, k] += op.S[k] @ z[off:off + op.nf[k]]
            off += op.nf[k]
    return c + out @ op.Jinv.T


#: :func:`_z_bounded` bounds the samples where the nozzle's z velocity is at least this share of
#: its speed, or its speed below ``STILL_M_S`` (m/s)
STEEP_SHARE = 0.3
STILL_M_S = 2e-3
#: :func:`_z_bounded` gives up (keeps the unbounded knots) where its bound would move a knot further
#: than this (m)
MAX_BOUND_CHANGE_M = 1e-3
#: :func:`_z_bounded` keeps each of x and y within this share of the centripetal cap
#: ``max_z_accel / |u_z|`` (the rule bounds their vector sum)
XY_SHARE = float(np.sqrt(0.5))


def _z_bounded(op: _Operator, c: np.ndarray, o: np.ndarray, z0: np.ndarray, pin: np.ndarray, J: np.ndarray,
               dt_s: float, z_limit: float) -> np.ndarray | None:
    """The free knots ``z`` (nf, 3) of :func:`repair_window` with the repaired command's nozzle z
    acceleration within ``z_limit`` (m/s^2) on its free samples where the nozzle runs steep (z
    velocity at least :data:`STEEP_SHARE` of its speed) or nearly stands still (under
    :data:`STILL_M_S`), or within what the command had there before the repair where that is more;
    or None where the unconstrained knots ``z0`` keep it already (or the exact solve gives up).

    Klipper caps every segment's acceleration at ``max_z_accel * d/|dz|``, so a nozzle that moves
    in z harder than ``max_z_accel`` runs late; the repair's acceleration penalty is soft, and next
    to a pinned z move (the lift after homing, a layer change's) the corrected command dipped and
    rose by 5-15 um in a few milliseconds, 0.2-0.6 ms off the clock.  On the steep samples that move,
    the nozzle's x and y accelerations stay within ``z_limit / |u_z|`` as well (Klipper's centripetal
    junction rule across such a move: a correction bent a 150 mm/s descent sideways and the firmware
    ran it 0.55 ms late, 62 um off the clock), each within ``1/sqrt(2)`` of it (:data:`XY_SHARE`; the
    rule bounds the vector).  The rows cover the pinned samples next to free ones too: their second
    difference moves with the free knots, and there the command turns into a pinned lift (a layer
    change after a printed line on ``cube_prusa.gcode``, other_delta: the command came into the lift
    at 7,500 mm/s^2 in x/y where the cap was 5,000, and Klipper ran it 0.5 ms off the clock).  One small QP
    (:func:`~ffcomp.compensate.qp.active_set_qp`) on the window's normal equations.
    """
    n, nf = op.S.shape
    # where the firmware's segments run steep or nearly stand still: a flat segment's cap,
    # max_z_accel * d/|dz|, is many times max_z_accel (there the bound cost the printed lines' contour
    # 10 % on cube_prusa, other_delta, for nothing)
    v = np.gradient(c + o + op.S @ z0, axis=0) @ J.T / dt_s  # the unbounded repair's nozzle velocity
    sp = np.linalg.norm(v, axis=1)
    steep = (np.abs(v[:, 2]) >= STEEP_SHARE * sp) | (sp < STILL_M_S)
    # every sample whose second difference moves with the free knots: the free ones and the pinned
    # ones next to them (the command's turn into a pinned lift happens there)
    touched = ~pin[1:-1] | ~pin[:-2] | ~pin[2:]
    rows = np.nonzero(touched & steep[1:-1])[0] + 1
    # and the window's two ends, where the correction meets the unrepaired command outside: its own
    # part of the acceleration there (a bound that held the command hard inside left the correction
    # at 36 um on the last sample, a step the firmware took 0.4 ms late)
    ends = np.array([r for r in (0, n - 1) if n >= 3 and not pin[r] and steep[r]], int)
    if n < 3 or not (rows.size or ends.size):
        return None
    inner = np.r_[np.ones(rows.size, bool), np.zeros(ends.size, bool)]
    rows = np.r_[rows, ends]
    c2 = np.zeros((rows.size, 3))  # the command's own second difference (zero at the ends: see above)
    c2[inner] = np.diff(c, 2, axis=0)[rows[inner] - 1]
    acc0 = c2 + _second_difference(o)[rows]  # the repaired command's before the free knots' part
    D2 = _second_difference(op.S)[rows]
    # z on every such sample; x and y on those that move (across a steep move: Klipper's centripetal
    # junction rule at max_z_accel / |u_z|)
    moving = sp[rows] >= STILL_M_S
    parts = [(2, np.ones(len(rows), bool), np.full(len(rows), z_limit))]
    if moving.any():
        # the rule bounds the vector (x, y) acceleration: each component within 1/sqrt(2) of the cap
        a_seg = XY_SHARE * np.minimum(z_limit * sp[rows] / np.maximum(np.abs(v[rows, 2]), 1e-12), 1000.0)
        parts += [(k, moving, a_seg) for k in (0, 1)]
    A, base, lim = [], [], []
    for k, sel, cap in parts:
        jk = J[k] / dt_s**2
        A.append(np.hstack([jk[j] * D2[sel] for j in range(3)]))  # (R, 3 nf), carriage-major
        base.append(acc0[sel] @ jk)
        lim.append(np.maximum(cap[sel], np.abs(c2[sel] @ jk) * 1.0001))
    A, base, lim = np.vstack(A), np.concatenate(base), np.concatenate(lim)
    zvec0 = z0.T.reshape(-1)
    v = A @ zvec0 + base
    if np.all(np.abs(v) <= lim * 1.02):
        return None
    zv = active_set_qp(zvec0, csr_matrix(A), -lim - base, lim - base,
                        lambda r: cho_solve(op.factor, r, check_finite=False), 3 * nf, 1)
    # a working set the window's normal equations barely resist (bounds that fight one another on
    # a few knots) gave knots metres away: such a solve is no repair
    if zv is None or not np.all(np.isfinite(zv)) or float(np.max(np.abs(zv - zvec0))) > MAX_BOUND_CHANGE_M:
        return None
    return zv.reshape(3, nf).T


def repair_window(H: np.ndarray, c: np.ndarray, q: np.ndarray, pin: np.ndarray, J: np.ndarray, dt_s: float,
                  cfg: RepairConfig = RepairConfig(), cache: dict | None = None, key=None,
                  zpin: np.ndarray | None = None, z_limit_m_s2: float | None = None,
                  printing: np.ndarray | None = None) -> np.ndarray:
    """The repaired command of one window: ``c`` (n, 3) with ``q`` on the pinned samples.

    ``H`` (L, 3, 3): pulse response at the window's pose; ``J`` (3, 3): the Jacobian dX/dq there;
    ``dt_s``: the sample time.  The correction vanishes beyond the window.  ``cache`` (a dict) and
    ``key`` (the pose cell of ``H`` and ``J``): the factorised normal equations of a pin pattern seen
    before at that cell are reused (retractions repeat).  ``zpin`` (n,), optional: samples where
    only the nozzle's z is pinned to the plan's (``J q``'s z row, to first order), its x and y free
    (a z-hop right after a retraction: the firmware must run its z as planned, but the command may
    pre-actuate the travel that follows in x and y meanwhile); the correction is then solved in the
    nozzle frame.  ``z_limit_m_s2`` (optional): the firmware's ``max_z_accel``; the repaired command's
    nozzle z acceleration stays within it on the free samples where the nozzle runs steep or nearly
    stands still (:func:`_z_bounded`).
    """
    pin = np.asarray(pin, bool)
    if zpin is not None and np.any(zpin & ~pin):
        pins = np.repeat(pin[:, None], 3, axis=1)
        pins[:, 2] |= np.asarray(zpin, bool)
        fop = _cached(cache, ("frames", key, len(pin), np.packbits(pins).tobytes()),
                      lambda: _frame_operator(H, pins, J, dt_s, cfg))
        out = _repair_frames(fop, c, q, pins, J, cfg)
        out[pin] = q[pin]
        return out
    pk = (key, len(pin), np.packbits(pin).tobytes())
    op = _cached(cache, pk, lambda: _operator(H, pin, J, dt_s, cfg))
    pr = None if printing is None or cfg.print_weight == 1.0 else np.asarray(printing, bool)
    if pr is not None and pr.any() and op.nf:  # (its weights and factor only: the responses are op's)
        base = op
        op = _cached(cache, pk + (np.packbits(pr).tobytes(),), lambda: _weighted(base, pr, cfg))
    fixed = np.where(pin[:, None], q - c, 0.0)
    o = op.F @ fixed  # (n, 3): the pinned values, ramps towards the free knots excluded (they are in S)
    if op.nf == 0:
        return c + o
    Yo = np.stack([sum(np.convolve(H[:, i, j], o[:, j]) for j in range(3)) for i in range(3)], 1)[op.keep]
    D2o = _second_difference(o) * op.wrow
    yo = Yo.T.reshape(-1) if op.W is None else Yo.T.reshape(-1) * op.W  # (W: the squared weights)
    rhs = -(op.Phi.T @ yo) / cfg.err_m**2 - (op.D2S.T @ D2o @ op.P.T).T.reshape(-1)
    z = cho_solve(op.factor, rhs, check_finite=False).reshape(3, op.nf).T
    if z_limit_m_s2 is not None:
        zb = _z_bounded(op, c, o, z, pin, J, dt_s, z_limit_m_s2)
        if zb is not None:
            z = zb
    out = c + o + op.S @ z
    out[pin] = q[pin]
    return out
