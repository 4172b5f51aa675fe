"""Step streams: per-carriage step times from compensated commands, compressed, written, read back.

A stepper at ``steps_per_mm`` (microsteps included) stands at step count ``n`` and takes a step
whenever the commanded position crosses a half-step boundary ``(n +- 1/2) / steps_per_mm``: the
count is then always the command rounded to the nearest step, so the reconstruction error is at
most half a step (plus the timing tolerance of the compression).  Commands are linear between
samples, so each crossing time is exact.

Compact format (``.ffsteps``, text, one file for all three carriages)::

    # ffcomp-steps 1
    # clock_hz: 10000000
    # steps_per_mm: 80
    # start_steps: nA nB nC            step counts at time 0
    # start_time_s: 0.0
    A +1 <first_clock> <interval> <count> <add>
    A +1 <interval> <count> <add>
    A -1 <first_clock> <interval> <count> <add>
    ...

Each line is one queue entry in Klipper's style: ``count`` steps in direction ``+1``/``-1``, the
first ``interval`` ticks after the previous step (or at ``first_clock`` after a direction change,
given as an absolute tick), each following interval ``add`` ticks longer than the one before.
A step time is within ``max_error`` ticks of its exact time.  The plain format is NPZ (arrays
``A_t``, ``A_dir``, ... of absolute step times in seconds and directions) or CSV
(``time_s,stepper,dir``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MeasurementError

__all__ = ["step_events", "compress_steps", "expand_queue", "StepStream", "write_ffsteps", "read_ffsteps",
           "positions_from_steps", "write_plain", "read_plain"]

STEPPERS = ("A", "B", "C")


def step_events(q_m: np.ndarray, t0_s: float, dt_s: float, steps_per_mm: float, n0: int | None = None):
    """Step times and directions for one carriage command ``q_m`` (N,) sampled every ``dt_s``.

    Returns ``(t_s, dir, n0)``: absolute step times, +1/-1 directions, and the initial step count
    (the first sample rounded to the nearest step unless ``n0`` is given).
    """
    x = np.asarray(q_m, float) * 1e3 * steps_per_mm  # position in steps
    if n0 is None:
        n0 = int(np.rint(x[0]))
    xa, xb = x[:-1], x[1:]
    up = xb >= xa
    # boundaries b + 1/2 crossed: in (xa, xb] going up, in [xb, xa) going down
    lo_b = np.where(up, np.floor(xa - 0.5) + 1, np.ceil(xb - 0.5))
    hi_b = np.where(up, np.floor(xb - 0.5), np.ceil(xa - 0.5) - 1)
    cnt = np.maximum(0, hi_b - lo_b + 1).astype(np.int64)
    total = int(cnt.sum())
    if total == 0:
        return np.zeros(0), np.zeros(0, np.int8), n0
    idx = np.repeat(np.arange(len(cnt)), cnt)
    off = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    # in time order: ascending boundaries going up, descending going down
    b = np.where(up[idx], lo_b[idx] + off, hi_b[idx] - off) + 0.5
    f = (b - xa[idx]) / (xb[idx] - xa[idx])
    t = t0_s + (idx + f) * dt_s
    d = np.where(up[idx], 1, -1).astype(np.int8)
    return t, d, n0


def _fit(prev: int, seg: np.ndarray, max_error: int):
    """Best integer (interval, add) for steps ``seg`` after tick ``prev``, or None if over the bound.

    Least squares on ``t_k - prev = k interval + k (k - 1) / 2 add`` (2x2 normal equations in
    closed form), rounded, then checked against the bound.
    """
    c = len(seg)
    y = (seg - prev).astype(float)
    if c == 1:
        cand = [(int(y[0]), 0)]
    else:
        k = np.arange(1, c + 1, dtype=float)
        g = k * (k - 1) * 0.5
        a11, a12, a22 = float(k @ k), float(k @ g), float(g @ g)
        b1, b2 = float(k @ y), float(g @ y)
        det = a11 * a22 - a12 * a12
        iv = (a22 * b1 - a12 * b2) / det
        ad = (a11 * b2 - a12 * b1) / det
        r = int(round(ad))
        cand = [(int(round(iv)), r), (int(np.floor(iv)), r), (int(np.ceil(iv)), r)]
    ki = np.arange(1, c + 1, dtype=np.int64)
    tri = (ki * (ki - 1)) // 2
    for iv, ad in cand:
        if np.all(np.abs(prev + ki * iv + ad * tri - seg) <= max_error):
            return iv, ad
    return None


def compress_steps(ticks: np.ndarray, max_error: int, first_prev: int) -> list[tuple[int, int, int]]:
    """(interval, count, add) compression of one direction run of step ticks (Klipper's queue form).

    Exponential then binary search for the longest prefix one (interval, add) pair reproduces within
    ``max_error`` ticks (least-squares fit, rounded); ``first_prev`` is the tick the first interval
    counts from.
    """
    out = []
    ticks = np.asarray(ticks, np.int64)
    n = len(ticks)
    i = 0
    prev = int(first_prev)
    guess = 8
    while i < n:
        best = _fit(prev, ticks[i:i + 1], max_error) or (int(ticks[i] - prev), 0)
        best_c, lo, hi = 1, 1, None
        # start from the previous entry's length: neighbouring entries are alike
        c = min(n - i, max(2, guess))
        while True:
            f = _fit(prev, ticks[i:i + c], max_error)
            if f is None:
                hi = c
                break
            best, best_c, lo = f, c, c
            if c == n - i:
                hi = c + 1
                break
            c = min(n - i, c * 2)
        # binary search between the last fitting and the first failing count
        while hi - lo > 1:
            mid = (lo + hi) // 2
            f = _fit(prev, ticks[i:i + mid], max_error)
            if f is None:
                hi = mid
            else:
                best, best_c, lo = f, mid, mid
        guess = best_c
        iv, ad = best
        out.append((iv, best_c, ad))
        prev = prev + best_c * iv + ad * (best_c * (best_c - 1)) // 2
        i += best_c
    return out


def expand_queue(first_prev: int, entries) -> np.ndarray:
    """Ticks of the steps a list of (interval, count, add) entries describes."""
    ticks = []
    prev = first_prev
    for interval, count, add in entries:
        k = np.arange(1, count + 1)
        t = prev + k * interval + add * (k * (k - 1)) // 2
        ticks.append(t)
        prev = int(t[-1])
    return np.concatenate(ticks) if ticks else np.zeros(0, np.int64)


@dataclass
class StepStream:
    """Decoded steps of the three carriages (absolute times, directions) and the start counts."""

    steps_per_mm: float
    start_steps: tuple
    t: dict
    dir: dict

    def n_steps(self) -> int:
        return int(sum(len(v) for v in self.t.values()))


def positions_from_steps(stream: StepStream, times_s: np.ndarray) -> np.ndarray:
    """Carriage positions (N, 3) in metres at ``times_s`` reconstructed from the step stream."""
    out = np.empty((len(times_s), 3))
    for i, name in enumerate(STEPPERS):
        t = stream.t[name]
        d = stream.dir[name].astype(np.int64)
        cum = np.concatenate([[0], np.cumsum(d)])
        k = np.searchsorted(t, times_s, side="right")
        out[:, i] = (stream.start_steps[i] + cum[k]) / stream.steps_per_mm * 1e-3
    return out


def write_ffsteps(f, per_stepper: dict, steps_per_mm: float, start_steps, clock_hz: int = 10_000_000,
                  max_error_s: float = 5e-6) -> int:
    """Write the compact format to an open text file; returns the number of queue lines."""
    f.write("# ffcomp-steps 1\n")
    f.write(f"# clock_hz: {clock_hz}\n# steps_per_mm: {steps_per_mm:.10g}\n")
    f.write(f"# start_steps: {' '.join(str(int(v)) for v in start_steps)}\n# start_time_s: 0.0\n")
    f.write(f"# max_error_s: {max_error_s:g}\n")
    max_err = max(1, int(round(max_error_s * clock_hz)))
    n_lines = 0
    for name in STEPPERS:
        t, d = per_stepper[name]
        if len(t) == 0:
            continue
        ticks = np.rint(np.asarray(t) * clock_hz).astype(np.int64)
        # runs of one direction
        cut = np.nonzero(np.diff(d))[0] + 1
        for a, b in zip(np.concatenate([[0], cut]), np.concatenate([cut, [len(d)]])):
            run = ticks[a:b]
            first_prev = int(run[0]) - (int(run[1] - run[0]) if len(run) > 1 else 1)
            entries = compress_steps(run, max_err, first_prev)
            f.write(f"{name} {int(d[a]):+d} {first_prev} {entries[0][0]} {entries[0][1]} {entries[0][2]}\n")
            for e in entries[1:]:
                f.write(f"{name} {int(d[a]):+d} {e[0]} {e[1]} {e[2]}\n")
            n_lines += len(entries)
    return n_lines


def read_ffsteps(path: str) -> StepStream:
    """Read a ``.ffsteps`` file; errors name the file, line and text."""
    head = {}
    t = {n: [] for n in STEPPERS}
    dirs = {n: [] for n in STEPPERS}
    cur = {n: None for n in STEPPERS}  # (dir, entries, first_prev)
    with open(path, encoding="utf-8") as f:
        for lineno, raw in enumerate(f, 1):
            s = raw.strip()
            if not s:
                continue
            if s.startswith("#"):
                if ":" in s:
                    k, _, v = s[1:].partition(":")
                    head[k.strip()] = v.strip()
                elif "ffcomp-steps" in s and s != "# ffcomp-steps 1":
                    raise MeasurementError(path, lineno, "unsupported step format version", raw)
                continue
            parts = s.split()
            try:
                name, d = parts[0], int(parts[1])
                nums = [int(v) for v in parts[2:]]
            except (ValueError, IndexError):
                raise MeasurementError(path, lineno, "malformed step queue line", raw) from None
            if name not in STEPPERS or d not in (1, -1) or len(nums) not in (3, 4):
                raise MeasurementError(path, lineno, "malformed step queue line", raw)
            if len(nums) == 4:  # new direction run
                _flush(cur, name, t, dirs)
                cur[name] = (d, [tuple(nums[1:])], nums[0])
            else:
                if cur[name] is None or cur[name][0] != d:
                    raise MeasurementError(path, lineno, "queue entry without a run start", raw)
                cur[name][1].append(tuple(nums))
    for name in STEPPERS:
        _flush(cur, name, t, dirs)
    try:
        clock = float(head["clock_hz"])
        spm = float(head["steps_per_mm"])
        start = tuple(int(v) for v in head["start_steps"].split())
    except (KeyError, ValueError) as e:
        raise MeasurementError(path, None, f"missing or bad header ({e})") from None
    tt = {n: (np.concatenate(t[n]) / clock if t[n] else np.zeros(0)) for n in STEPPERS}
    dd = {n: (np.concatenate(dirs[n]) if dirs[n] else np.zeros(0, np.int8)) for n in STEPPERS}
    return StepStream(spm, start, tt, dd)


def _flush(cur, name, t, dirs):
    if cur[name] is None:
        return
    d, entries, first_prev = cur[name]
    ticks = expand_queue(first_prev, entries)
    t[name].append(ticks.astype(float))
    dirs[name].append(np.full(len(ticks), d, np.int8))
    cur[name] = None


def write_plain(path: str, per_stepper: dict, steps_per_mm: float, start_steps) -> None:
    """NPZ (``.npz``) or CSV (anything else) with absolute step times and directions."""
    if str(path).endswith(".npz"):
        arrays = {"steps_per_mm": np.array(steps_per_mm), "start_steps": np.array(start_steps)}
        for n in STEPPERS:
            arrays[f"{n}_t"], arrays[f"{n}_dir"] = per_stepper[n]
        with open(path, "wb") as f:
            np.savez_compressed(f, **arrays)
        return
    with open(path, "w", encoding="utf-8") as f:
        f.write(f"# ffcomp-steps-csv 1\n# steps_per_mm: {steps_per_mm:.10g}\n")
        f.write(f"# start_steps: {' '.join(str(int(v)) for v in start_steps)}\ntime_s,stepper,dir\n")
        rows = []
        for n in STEPPERS:
            tt, dd = per_stepper[n]
            rows.append((np.asarray(tt), np.full(len(tt), n), np.asarray(dd)))
        T = np.concatenate([r[0] for r in rows])
        S = np.concatenate([r[1] for r in rows])
        D = np.concatenate([r[2] for r in rows])
        o = np.argsort(T, kind="stable")
        for a, b, c in zip(T[o], S[o], D[o]):
            f.write(f"{a:.9f},{b},{int(c):+d}\n")


def read_plain(path: str) -> StepStream:
    if str(path).endswith(".npz"):
        z = np.load(path)
        return StepStream(float(z["steps_per_mm"]), tuple(int(v) for v in z["start_steps"]),
                          {n: z[f"{n}_t"] for n in STEPPERS}, {n: z[f"{n}_dir"] for n in STEPPERS})
    head = {}
    T, S, D = [], [], []
    with open(path, encoding="utf-8") as f:
        for lineno, raw in enumerate(f, 1):
            s = raw.strip()
            if s.startswith("#"):
                k, _, v = s[1:].partition(":")
                head[k.strip()] = v.strip()
                continue
            if not s or s.startswith("time_s"):
                continue
            try:
                a, b, c = s.split(",")
                T.append(float(a))
                S.append(b)
                D.append(int(c))
            except ValueError:
                raise MeasurementError(path, lineno, "malformed step row", raw) from None
    T, S, D = np.array(T), np.array(S), np.array(D, np.int8)
    start = tuple(int(v) for v in head["start_steps"].split())
    return StepStream(float(head["steps_per_mm"]), start, {n: T[S == n] for n in STEPPERS},
                      {n: D[S == n] for n in STEPPERS})
