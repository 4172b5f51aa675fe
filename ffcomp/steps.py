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

import math
import os
from dataclasses import dataclass

import numpy as np

from .errors import MeasurementError

__all__ = ["step_events", "compress_steps", "expand_queue", "StepStream", "write_ffsteps", "FfstepsWriter",
           "read_ffsteps", "ffsteps_max_error", "SampleFile", "positions_from_steps", "write_plain",
           "write_plain_header", "write_plain_rows", "read_plain"]

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


def _fit_np(prev: int, seg: np.ndarray, max_error: int):
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


def _fit_py(prev: int, seg: list, max_error: int):
    """:func:`_fit_np` for short runs, in Python integers."""
    c = len(seg)
    if c == 1:
        return seg[0] - prev, 0
    b1 = b2 = 0
    g = 0
    for k, s in enumerate(seg, 1):
        y = s - prev
        b1 += k * y
        b2 += g * y
        g += k
    a11, a12, a22, det = _MOMENTS[c] if c < len(_MOMENTS) else _moments(c)
    iv = (a22 * b1 - a12 * b2) / det
    ad = (a11 * b2 - a12 * b1) / det
    r = int(round(ad))
    lo, hi = -max_error, max_error
    for cand in (int(round(iv)), math.floor(iv), math.ceil(iv)):
        pos = prev
        step = cand
        for s in seg:  # position after k steps: prev + k iv + add k (k - 1) / 2
            pos += step
            if not lo <= pos - s <= hi:
                break
            step += r
        else:
            return cand, r
    return None


def _moments(c: int) -> tuple[float, float, float, float]:
    """``sum k^2``, ``sum k g``, ``sum g^2`` over ``k = 1..c``, ``g = k (k - 1) / 2`` (closed forms),
    and the determinant of the normal equations."""
    s2 = c * (c + 1) * (2 * c + 1) // 6
    s3 = (c * (c + 1) // 2) ** 2
    s4 = c * (c + 1) * (2 * c + 1) * (3 * c * c + 3 * c - 1) // 30
    a11, a12, a22 = float(s2), (s3 - s2) / 2.0, (s4 - 2 * s3 + s2) / 4.0
    return a11, a12, a22, a11 * a22 - a12 * a12


_MOMENTS = [(0.0, 0.0, 0.0, 0.0)] + [_moments(c) for c in range(1, 129)]


def compress_steps(ticks: np.ndarray, max_error: int, first_prev: int) -> list[tuple[int, int, int]]:
    """(interval, count, add) compression of one direction run of step ticks (Klipper's queue form).

    Exponential then binary search for the longest prefix one (interval, add) pair reproduces within
    ``max_error`` ticks (least-squares fit, rounded); ``first_prev`` is the tick the first interval
    counts from.
    """
    out = []
    ticks = np.asarray(ticks, np.int64)
    tl = ticks.tolist()
    n = len(ticks)
    i = 0
    prev = int(first_prev)
    guess = 8

    def fit(c):
        """(interval, add) for the next ``c`` steps, or None: short probes in Python integers (numpy's
        per-call cost dominates there), long ones with numpy."""
        if c <= 96:
            return _fit_py(prev, tl[i:i + c], max_error)
        return _fit_np(prev, ticks[i:i + c], max_error)

    while i < n:
        best = (tl[i] - prev, 0)  # one step always fits exactly
        best_c, lo, hi = 1, 1, None
        # start from the previous entry's length: neighbouring entries are alike
        c = min(n - i, max(2, guess))
        while True:
            f = fit(c)
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
            f = fit(mid)
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


def _ffsteps_header(f, steps_per_mm: float, start_steps, clock_hz: int, max_error_s: float) -> None:
    f.write("# ffcomp-steps 1\n")
    f.write(f"# clock_hz: {clock_hz}\n# steps_per_mm: {steps_per_mm:.10g}\n")
    f.write(f"# start_steps: {' '.join(str(int(v)) for v in start_steps)}\n# start_time_s: 0.0\n")
    f.write(f"# max_error_s: {max_error_s:g}\n")


class _RunCompressor:
    """One stepper's queue lines, written run by run as step times arrive in chunks.

    A direction run is compressed once it is complete (the next step goes the other way, or
    :meth:`finish`), so only the open run is held in memory.
    """

    def __init__(self, name: str, out, clock_hz: int, max_err_ticks: int):
        self.name, self.out, self.clock, self.max_err = name, out, clock_hz, max_err_ticks
        self.pending: list[np.ndarray] = []
        self.dir = 0
        self.lines = 0

    def push(self, t_s: np.ndarray, d: np.ndarray) -> None:
        if len(t_s) == 0:
            return
        ticks = np.rint(np.asarray(t_s) * self.clock).astype(np.int64)
        d = np.asarray(d)
        cut = (np.nonzero(np.diff(d))[0] + 1).tolist()
        for a, b in zip([0] + cut, cut + [len(d)]):
            da = int(d[a])
            if self.pending and da != self.dir:
                self._flush()
            self.pending.append(ticks[a:b])
            self.dir = da

    def finish(self) -> int:
        self._flush()
        return self.lines

    def _flush(self) -> None:
        if not self.pending:
            return
        run = np.concatenate(self.pending)
        self.pending = []
        first_prev = int(run[0]) - (int(run[1] - run[0]) if len(run) > 1 else 1)
        entries = compress_steps(run, self.max_err, first_prev)
        name, sd = self.name, f"{self.dir:+d}"
        e0 = entries[0]
        lines = [f"{name} {sd} {first_prev} {e0[0]} {e0[1]} {e0[2]}\n"]
        lines += [f"{name} {sd} {iv} {c} {ad}\n" for iv, c, ad in entries[1:]]
        self.out.write("".join(lines))
        self.lines += len(entries)


def write_ffsteps(f, per_stepper: dict, steps_per_mm: float, start_steps, clock_hz: int = 10_000_000,
                  max_error_s: float = 5e-6) -> int:
    """Write the compact format to an open text file; returns the number of queue lines."""
    _ffsteps_header(f, steps_per_mm, start_steps, clock_hz, max_error_s)
    max_err = max(1, int(round(max_error_s * clock_hz)))
    n_lines = 0
    for name in STEPPERS:
        t, d = per_stepper[name]
        rc = _RunCompressor(name, f, clock_hz, max_err)
        rc.push(t, d)
        n_lines += rc.finish()
    return n_lines


class FfstepsWriter:
    """The compact format, streamed: push each stepper's steps chunk by chunk (in time order), then
    :meth:`finish`.  The format groups lines by stepper, so each stepper's lines go to a temporary
    file beside ``path`` until the end; memory holds only each stepper's open direction run.
    """

    def __init__(self, path: str, steps_per_mm: float, clock_hz: int = 10_000_000, max_error_s: float = 5e-6):
        self.path, self.spm, self.clock, self.max_error_s = path, steps_per_mm, clock_hz, max_error_s
        max_err = max(1, int(round(max_error_s * clock_hz)))
        self._parts = {n: f"{path}.{n}.part" for n in STEPPERS}
        self._files = {n: open(self._parts[n], "w", encoding="utf-8") for n in STEPPERS}
        self._rc = {n: _RunCompressor(n, self._files[n], clock_hz, max_err) for n in STEPPERS}
        self.start_steps = (0, 0, 0)

    def push(self, name: str, t_s: np.ndarray, d: np.ndarray) -> None:
        self._rc[name].push(t_s, d)

    def push_chunk(self, ev: dict) -> None:
        """``ev``: stepper name -> (step times s, directions) of one chunk."""
        for name, (t_s, d) in ev.items():
            self._rc[name].push(t_s, d)

    def finish(self) -> int:
        """Write ``path`` (header, then the steppers' lines); returns the number of queue lines."""
        n = sum(rc.finish() for rc in self._rc.values())
        for f in self._files.values():
            f.close()
        with open(self.path, "w", encoding="utf-8") as out:
            _ffsteps_header(out, self.spm, self.start_steps, self.clock, self.max_error_s)
            for name in STEPPERS:
                with open(self._parts[name], encoding="utf-8") as part:
                    while True:
                        buf = part.read(1 << 20)
                        if not buf:
                            break
                        out.write(buf)
        self.close()
        return n

    def close(self) -> None:
        """Remove the temporary parts (also after a failure)."""
        for name in STEPPERS:
            f = self._files[name]
            if not f.closed:
                f.close()
            if os.path.exists(self._parts[name]):
                os.unlink(self._parts[name])


def ffsteps_max_error(path: str, q_m, dt_s: float) -> float:
    """Largest difference, in steps, between a ``.ffsteps`` file and carriage positions.

    ``q_m`` holds the positions (m) at times ``0, dt_s, 2 dt_s, ...``: an (N, 3) array or anything
    whose ``q_m[i0:i1]`` gives those rows (e.g. :class:`SampleFile`, so long files need not be in
    memory).  The file is read run by run; memory holds one direction run at a time.
    """
    head, worst = {}, 0.0
    n_q = len(q_m)
    state: dict = {}
    prm: dict = {}

    def n_before(tick, right: bool) -> int:
        """Samples at times ``< tick`` (``<= tick`` with ``right``)."""
        x = tick / prm["dtc"]
        i = math.floor(x) + 1 if right else math.ceil(x)
        return min(max(int(i), 0), n_q)

    def compare(st, i0, i1, counts):
        nonlocal worst
        if i1 > i0:
            q = np.asarray(q_m[i0:i1])[:, st["col"]]
            worst = max(worst, float(np.max(np.abs(counts - q * 1e3 * prm["spm"]))))
            st["ti"] = i1

    def run_done(name, d, entries, first_prev):
        st = state[name]
        ticks = expand_queue(first_prev, entries)
        compare(st, st["ti"], n_before(int(ticks[0]), False), st["n"])  # before the run
        i0, i1 = st["ti"], n_before(int(ticks[-1]), True)
        if i1 > i0:
            k = np.searchsorted(ticks, np.arange(i0, i1) * prm["dtc"], side="right")
            compare(st, i0, i1, st["n"] + d * k)
        st["n"] += d * len(ticks)

    def start():
        prm["spm"] = float(head["steps_per_mm"])
        prm["dtc"] = dt_s * float(head["clock_hz"])
        first = [int(v) for v in head["start_steps"].split()]
        state.update({n: {"n": first[i], "ti": 0, "col": i} for i, n in enumerate(STEPPERS)})

    cur = None  # (name, dir, entries, first_prev)
    with open(path, encoding="utf-8") as f:
        for raw in f:
            if raw.startswith("#"):
                k, _, v = raw[1:].partition(":")
                head[k.strip()] = v.strip()
                continue
            parts = raw.split()
            if not parts:
                continue
            if not state:  # the header is complete
                start()
            name, d, nums = parts[0], int(parts[1]), [int(v) for v in parts[2:]]
            if len(nums) == 4:
                if cur is not None:
                    run_done(*cur)
                cur = (name, d, [tuple(nums[1:])], nums[0])
            else:
                cur[2].append(tuple(nums))
    if not state:
        start()
    if cur is not None:
        run_done(*cur)
    for name in STEPPERS:  # after the last step: the final count
        st = state[name]
        compare(st, st["ti"], n_q, st["n"])
    return worst


class SampleFile:
    """(N, 3) float64 rows appended to a binary file and read back by row ranges (``f[i0:i1]``)."""

    def __init__(self, path: str):
        self.path = path
        self._w = open(path, "wb")
        self._r = None
        self.n = 0

    def append(self, rows: np.ndarray) -> None:
        rows = np.ascontiguousarray(rows, dtype=np.float64).reshape(-1, 3)
        self._w.write(rows.tobytes())
        self.n += len(rows)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, sl: slice) -> np.ndarray:
        i0, i1, _ = sl.indices(self.n)
        if self._r is None:
            self._w.flush()
            self._r = open(self.path, "rb")
        self._r.seek(i0 * 24)
        return np.fromfile(self._r, dtype=np.float64, count=max(i1 - i0, 0) * 3).reshape(-1, 3)

    def close(self) -> None:
        for f in (self._w, self._r):
            if f is not None:
                f.close()
        if os.path.exists(self.path):
            os.unlink(self.path)


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
        write_plain_header(f, steps_per_mm, start_steps)
        write_plain_rows(f, per_stepper)


def write_plain_header(f, steps_per_mm: float, start_steps) -> None:
    """The CSV header (see :func:`write_plain`)."""
    f.write(f"# ffcomp-steps-csv 1\n# steps_per_mm: {steps_per_mm:.10g}\n")
    f.write(f"# start_steps: {' '.join(str(int(v)) for v in start_steps)}\ntime_s,stepper,dir\n")


def write_plain_rows(f, per_stepper: dict) -> None:
    """CSV rows of the steps in ``per_stepper`` (name -> (times s, dirs)), in time order."""
    rows = []
    for n in STEPPERS:
        tt, dd = per_stepper[n]
        rows.append((np.asarray(tt), np.full(len(tt), n), np.asarray(dd)))
    T = np.concatenate([r[0] for r in rows])
    S = np.concatenate([r[1] for r in rows])
    D = np.concatenate([r[2] for r in rows])
    o = np.argsort(T, kind="stable")
    f.write("".join(f"{a:.9f},{b},{c:+d}\n" for a, b, c in zip(T[o].tolist(), S[o].tolist(), D[o].tolist())))


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
