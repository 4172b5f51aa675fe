"""Self-check of a compensated G-code file: re-plan it and compare with the intended commands."""

from __future__ import annotations

import math
import time
from operator import attrgetter

import numpy as np

from ..errors import SelfCheckError
from ..gcode.klipper_chains import BLOCK, MoveBlock
from ..gcode.moves import MOVE
from ..gcode.planner import GcodePlan
from ..gcode.segment_lines import SEG_COLS
from ..kinematics import inverse
from ..linalg3 import max_abs3

__all__ = ["self_check", "measure", "merge", "judge", "shape_limit_um", "TIMING_NOTE_MS"]

#: drift (ms) above which the summary notes the timing cost
TIMING_NOTE_MS = 0.2

#: a list, or None: if a list, :func:`measure` appends per batch of re-planned segments
#: ``(output line, end time s, lateness s, re-planned duration s, intended duration s, stream)``
#: (debugging; a stream is a stretch between stops, each on its own clock)
TRACE: list | None = None




def self_check(path: str, qfile: str, profile, geom, summ, opts,
                segfile: str | None = None, head_len: int = 0) -> None:
    """Re-plan the output with the firmware-faithful planner and compare carriages with the intent.

    Every re-planned XYZ segment is sampled from its own start at the intended sample spacing and
    compared with the intended commands of the samples it stands for, so the check sees both the
    shape (tolerance, firmware acceleration ramps) and the timing inside each segment; the drift of
    the whole file's duration is reported separately (``output_print_time_s``).
    """
    r = measure(path, qfile, profile, geom, summ.start_mm, segfile, head_len)
    judge(r, summ, opts, 1.0 / profile.limits.sample_rate_hz)


def merge(parts: list[dict], k_offsets: list[int], dt: float) -> dict:
    """The :func:`measure` results of consecutive pieces of one output (``--jobs``) as one: the
    pieces' sample indices shifted by ``k_offsets``, their re-planned durations added."""
    out = dict(parts[0])
    out["worst_k"] += k_offsets[0]
    out["drift_at_k"] += k_offsets[0]
    for r, ko in zip(parts[1:], k_offsets[1:]):
        if r["worst"] > out["worst"]:
            out["worst"], out["worst_k"] = r["worst"], r["worst_k"] + ko
        if abs(r["drift_max"]) > abs(out["drift_max"]):
            out["drift_max"], out["drift_at_k"] = r["drift_max"], r["drift_at_k"] + ko
        for k in ("sq", "cnt", "t_end", "time_s"):
            out[k] += r[k]
        for k in ("worst_cu", "worst_abs"):
            out[k] = max(out[k], r[k])
        out["drift_end"] = r["drift_end"]
    out["drift_at"] = out["drift_at_k"] * dt
    return out


def measure(path, qfile: str, profile, geom, start_mm, segfile: str | None = None, head_len: int = 0,
            name: str | None = None, chains: bool = True, trace: list | None = None,
            trace_other: list | None = None, timing_only: bool = False) -> dict:
    """The self-check's numbers (see :func:`self_check`) for the output ``path`` (a file name, or an
    iterable of its lines named ``name``), re-planned from rest at ``start_mm``.

    ``chains``: re-plan the runs of straight moves between rests vectorised
    (:class:`~ffcomp.gcode.klipper_chains.KlipperChainPlanner`: the same plan to about 1e-9 s, 2x
    faster); False: move by move.  ``trace``: a list to append the per-segment rows to (as
    :data:`TRACE`; default :data:`TRACE`); ``trace_other``: a list to append ``(line, kind, start s,
    duration s, entry and exit speed mm/s, acceleration mm/s^2)`` of every other re-planned move to
    (extruder-only moves, dwells).  ``timing_only``:
    measure the clock only (the trace and the drift; no positions are compared).
    """
    t_start = time.perf_counter()
    if trace is None:
        trace = TRACE
    qf = open(qfile, "rb")  # read in windows: a memory map would keep the whole file resident
    table = _SegmentTable(segfile, head_len)
    dt = 1.0 / profile.limits.sample_rate_hz
    worst, worst_k, sq, cnt = 0.0, 0, 0.0, 0
    worst_cu = 0.0
    batch_pos, batch_k, batch_cu, batch_abs = [], [], [], []
    worst_abs = 0.0

    def flush():
        nonlocal worst, worst_k, sq, cnt, worst_cu, worst_abs
        if not batch_pos:
            return
        P = np.concatenate(batch_pos) * 1e-3
        K = np.concatenate(batch_k)
        CU = np.concatenate(batch_cu)
        q = inverse(geom, P)
        k0, k1 = int(K.min()), int(K.max()) + 1
        qf.seek(k0 * 12)
        win = np.frombuffer(qf.read((k1 - k0) * 12), dtype=np.float32).reshape(-1, 3)
        qi = win[K - k0].astype(float)
        d = max_abs3(q - qi)
        da = max_abs3(inverse(geom, np.concatenate(batch_abs) * 1e-3) - qi)
        worst_abs = max(worst_abs, float(np.nanmax(da)))
        if CU.any():
            worst_cu = max(worst_cu, float(np.max(d[CU])))
            d = np.where(CU, 0.0, d)
        i = int(np.nanargmax(d))
        if d[i] > worst:
            worst, worst_k = float(d[i]), int(K[i])
        sq += float(np.nansum(d * d))
        cnt += len(d)
        batch_pos.clear()
        batch_k.clear()
        batch_cu.clear()
        batch_abs.clear()

    anchor: dict[int, float] = {}  # stream -> print time of its sample 0 in the re-planned output
    drift = {"max": 0.0, "at": 0.0, "end": 0.0}
    rows: list = []  # (R, geo) of re-planned XYZ moves not compared yet, in order
    buf: list = []  # single re-planned moves not turned into rows yet

    def flush_rows():
        if buf:
            rows.append(_move_rows(buf))
            buf.clear()
        if rows:
            R = np.concatenate([r[0] for r in rows]) if len(rows) > 1 else rows[0][0]
            geo = np.concatenate([r[1] for r in rows]) if len(rows) > 1 else rows[0][1]
            rows.clear()
            for i in range(0, len(R), 5000):  # (a long chain: memory stays bounded)
                segments(R[i:i + 5000], geo[i:i + 5000])

    def segments(R: np.ndarray, geo: np.ndarray):
        """Compare re-planned XYZ moves (rows ``R``: line, accel, start, cruise speed, the three
        phase times, start time; ``geo``: start point and unit vector) with the intent."""
        # the segments the writer wrote, by their line in the output
        ln = R[:, 0].astype(np.int64)
        tab = table.upto(int(ln[-1]))
        seg_lines = tab[:, 0]
        j = np.minimum(np.searchsorted(seg_lines, ln), max(len(seg_lines) - 1, 0))
        ok = (seg_lines[j] == ln) if len(seg_lines) else np.zeros(len(ln), bool)
        R, geo, j = R[ok], geo[ok], j[ok]
        if not len(R):
            return
        ka, kb, cu, stream = tab[j, 1], tab[j, 2], tab[j, 3].astype(bool), tab[j, 4]
        fa, fb = tab[j, 5] * 1e-9, tab[j, 6] * 1e-9  # starts and ends between samples (rest points), s
        dur = R[:, 4] + R[:, 5] + R[:, 6]
        t0 = R[:, 7]
        # the absolute clock: a stream's sample k is due at anchor + k dt, the anchor being where the
        # re-planned output starts the stream's first segment
        for s_ in np.unique(stream).tolist():
            if s_ not in anchor:
                first = int(np.argmax(stream == s_))
                anchor[s_] = float(t0[first] - ka[first] * dt - fa[first])
        c = np.array([anchor[s_] for s_ in stream.tolist()]) if len(anchor) > 1 else \
            np.full(len(R), next(iter(anchor.values())))
        late = (t0 + dur) - (kb * dt + fb + c)  # how late each segment ends, s
        if trace is not None:
            trace.append((R[:, 0].copy(), t0 + dur, late.copy(), dur.copy(), (kb - ka) * dt + fb - fa, stream.copy()))
        i = int(np.argmax(np.abs(late)))
        if abs(late[i]) > abs(drift["max"]):
            drift["max"], drift["at"] = float(late[i]), float(kb[i] * dt)
        drift["end"] = float(late[-1])
        if timing_only:
            return
        cnt = kb - ka
        idx = np.repeat(np.arange(len(R)), cnt)
        k = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt) + 1
        kk = ka[idx] + k
        # the shape: each segment at the same share of its own duration (the limit applies to
        # this; the timing is the drift's business); the absolute clock: where the output is when
        # the command is due (drift included; reported)
        span = cnt * dt + fb - fa  # the segment's intended duration
        tau_own = np.clip((k * dt - fa[idx]) / span[idx], 0.0, 1.0) * dur[idx]
        tau_abs = np.clip(kk * dt + c[idx] - t0[idx], 0.0, dur[idx])
        a_, v0, vc, ta, tc = R[idx, 1], R[idx, 2], R[idx, 3], R[idx, 4], R[idx, 5]
        G = geo[idx]
        P = _along(G, _distance_v(a_, v0, vc, ta, tc, tau_own))
        Pa = _along(G, _distance_v(a_, v0, vc, ta, tc, tau_abs))
        batch_pos.append(P)
        batch_abs.append(Pa)
        batch_k.append(kk)
        batch_cu.append(cu[idx])
        flush()

    last = None
    n_rows = 0
    start = tuple(start_mm or (0.0, 0.0, 0.0))  # the plan's start (ffcomp.gcode.start)
    for last in GcodePlan(path, profile, lenient=True, start_position_mm=(*start, 0.0), chains=chains,
                          **({"path": name} if name else {})):
        if last.kind == BLOCK:
            if buf:
                rows.append(_move_rows(buf))
                buf.clear()
            rows.append(_block_rows(last))
            n_rows += len(last)
        else:
            buf.append(last)
            n_rows += 1
            if trace_other is not None and last.kind != MOVE:
                trace_other.append((last.lineno, last.kind, last.t_start_s, last.t_end_s - last.t_start_s,
                                    last.start_v_mm_s, last.end_v_mm_s, last.accel_mm_s2))
        if n_rows >= 5000:
            flush_rows()
            n_rows = 0
    flush_rows()
    table.close()
    t_end = last.t_end_s if last is not None else 0.0
    qf.close()
    return {"worst": worst, "worst_k": worst_k, "sq": sq, "cnt": cnt, "worst_cu": worst_cu, "worst_abs": worst_abs,
            "drift_max": drift["max"], "drift_at_k": int(round(drift["at"] / dt)), "drift_at": drift["at"],
            "drift_end": drift["end"], "t_end": t_end, "time_s": time.perf_counter() - t_start}


def judge(r: dict, summ, opts, dt: float) -> None:
    """Put the self-check's numbers into the summary; raise :class:`SelfCheckError` beyond the limits."""
    worst, worst_k, sq, cnt = r["worst"], r["worst_k"], r["sq"], r["cnt"]
    worst_cu, worst_abs, t_end = r["worst_cu"], r["worst_abs"], r["t_end"]
    drift = {"max": r["drift_max"], "at": r["drift_at"], "end": r["drift_end"]}
    summ.output_print_time_s = t_end
    summ.self_check_time_s = r.get("time_s")
    summ.self_check_max_um = worst * 1e6
    summ.self_check_rms_um = math.sqrt(sq / max(cnt, 1)) * 1e6
    summ.self_check_catch_up_max_um = worst_cu * 1e6
    summ.self_check_drift_ms = drift["max"] * 1e3
    summ.self_check_drift_at_s = drift["at"]
    summ.self_check_drift_end_ms = drift["end"] * 1e3
    summ.self_check_abs_max_um = worst_abs * 1e6
    lim_um = shape_limit_um(opts)
    if abs(drift["max"]) * 1e3 > TIMING_NOTE_MS:
        summ.warnings += 1
        summ.notes.append(
            f"timing: the re-planned output runs up to {drift['max'] * 1e3:+.2f} ms off the intended clock "
            f"(near t = {drift['at']:.3f} s; {drift['end'] * 1e3:+.2f} ms at the end), up to {worst_abs * 1e6:.0f} um "
            f"from the intended carriage commands at the same time: the firmware's limits (max_z_accel, the "
            f"extruder's) do not let those segments run in their time")
    if abs(drift["max"]) * 1e3 > opts.self_check_drift_ms:
        raise SelfCheckError(
            f"self-check failed: the re-planned output runs {drift['max'] * 1e3:+.1f} ms off the intended clock "
            f"near t = {drift['at']:.3f} s (limit {opts.self_check_drift_ms:g} ms). Nothing was written.")
    if worst_cu * 1e6 > 4 * lim_um:
        raise SelfCheckError(
            f"self-check failed: a catch-up after an extruder-only move or dwell strays {worst_cu * 1e6:.1f} um "
            f"from the intended carriage commands (limit {4 * lim_um:g} um). Nothing was written.")
    if worst * 1e6 > lim_um:
        raise SelfCheckError(
            f"self-check failed: the re-planned output strays {worst * 1e6:.1f} um from the intended carriage "
            f"commands near t = {worst_k * dt:.3f} s (limit {lim_um:g} um). Nothing was written.")


def shape_limit_um(opts) -> float:
    """The self-check's limit on the shape error, um: ``--self-check-tol-um``, but never below what the
    point placement tolerance ``--tol-um`` itself allows (a carriage moves up to about twice the
    nozzle's distance, plus the firmware's ramps)."""
    return float(max(opts.self_check_tol_um, 3.0 * opts.tol_um))


_SCALARS = attrgetter("lineno", "accel_mm_s2", "start_v_mm_s", "cruise_v_mm_s", "accel_t_s", "cruise_t_s",
                      "decel_t_s", "t_start_s")


def _move_rows(moves: list) -> tuple[np.ndarray, np.ndarray]:
    """Rows of re-planned XYZ moves for the comparison: ``R`` (line, accel, start and cruise speed,
    the three phase times, start time) and ``geo`` (start point and unit vector); other kinds are
    left out."""
    mvs = [m for m in moves if m.kind == MOVE]
    return (np.array([_SCALARS(m) for m in mvs], dtype=float).reshape(-1, 8),
            np.array([m.start_mm[:3] + m.unit[:3] for m in mvs], dtype=float).reshape(-1, 6))


def _block_rows(b: MoveBlock) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_move_rows` of a chain planned at once."""
    R = np.empty((len(b), 8))
    for c, col in enumerate((b.lineno, b.accel, b.start_v, b.cruise_v, b.accel_t, b.cruise_t, b.decel_t,
                             b.t_start)):
        R[:, c] = col
    geo = np.empty((len(b), 6))
    geo[:, :3] = b.start[:, :3]
    geo[:, 3:] = b.unit[:, :3]
    return R, geo


class _SegmentTable:
    """The writer's segment table (int64 rows: output line, first and last sample, catch-up flag,
    stream, start and end past those samples in ns),
    read forward in step with the re-planned moves, which come in line order."""

    def __init__(self, path: str | None, head_len: int):
        self.f = open(path, "rb") if path else None
        self.head_len = head_len
        self.buf = np.zeros((0, SEG_COLS), np.int64)

    def upto(self, line: int) -> np.ndarray:
        """Rows of output lines ``<= line`` not returned before (lines shifted by the header)."""
        while self.f is not None and (not len(self.buf) or self.buf[-1, 0] <= line):
            raw = self.f.read(8 * SEG_COLS * 65536)
            if not raw:
                break
            rows = np.frombuffer(raw, dtype=np.int64).reshape(-1, SEG_COLS).copy()
            rows[:, 0] += self.head_len
            self.buf = np.concatenate([self.buf, rows])
        n = int(np.searchsorted(self.buf[:, 0], line, side="right"))
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def close(self) -> None:
        if self.f is not None:
            self.f.close()


def _along(G: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points ``start + s * unit`` (n, 3) from rows ``G`` (n, 6) of start and unit vector, column by
    column (the same values as broadcasting ``s[:, None]``, faster on millions of samples)."""
    P = np.empty((len(s), 3))
    for c in range(3):
        P[:, c] = G[:, c] + s * G[:, 3 + c]
    return P


def _distance_v(a, v0, vc, ta, tc, tau):
    """Distance along planned trapezoids at times ``tau`` after their starts (all arrays), mm."""
    d_a = (v0 + vc) * 0.5 * ta
    t3 = tau - ta - tc
    return np.where(tau < ta, v0 * tau + 0.5 * a * tau * tau,
                    np.where(tau < ta + tc, d_a + vc * (tau - ta), d_a + vc * tc + vc * t3 - 0.5 * a * t3 * t3))
