"""Step-stream flow: G-code -> compensated carriage commands -> per-carriage step times.

The step stream carries the compensated carriage commands exactly (to half a step): no firmware
re-planning, no z throttling, no G-code segment tolerance.  The file is written atomically.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass

import numpy as np

from ..compensate.quantise import NoiseShaper, shaped_step_events
from ..gcode.planner import GcodePlan
from ..io_atomic import check_output_path, commit, keep_temp, make_temp, release_temp, sweep_stale
from ..model.lpv import LpvModel
from ..steps import (
    STEPPERS,
    FfstepsWriter,
    SampleFile,
    ffsteps_max_error,
    positions_from_steps,
    read_plain,
    step_events,
    write_plain,
    write_plain_header,
    write_plain_rows,
)
from .compensate_flow import CompensateOptions, CompensationSummary, compensated_stream, inverse_config

__all__ = ["StepsSummary", "steps_file"]


@dataclass
class StepsSummary:
    source: str
    output: str
    method: str
    print_time_s: float = 0.0
    steps: int = 0
    queue_lines: int = 0
    max_step_error_steps: float = 0.0
    wall_time_s: float = 0.0
    speed_ratio: float = 0.0
    restarts: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def steps_file(src: str, out_path: str, profile, *, method: str = "lpv", lenient: bool = False,
               csv: bool = False, shape: bool = False) -> StepsSummary:
    """Compensate ``src`` and write its step stream to ``out_path`` (``.ffsteps`` compact; with
    ``csv`` the plain CSV, or NPZ if the name ends in ``.npz``).  Checks the reconstruction.

    ``shape`` makes the stream quantisation-aware (:mod:`ffcomp.compensate.quantise`): the steps
    are chosen on a 10x finer grid by second-order error feedback, so the lattice's error sits
    near 5 kHz instead of ringing the drive; the carriages then dither by up to two steps around
    the command (the reconstruction check reports that deviation).

    The compact and CSV formats are streamed (memory holds one chunk, and each stepper's open
    direction run); NPZ holds every step time in memory until it is written.
    """
    t0 = time.perf_counter()
    out_path = check_output_path(out_path)  # fails now, not after the work
    model = LpvModel.from_profile(profile)
    dt = 1.0 / profile.limits.sample_rate_hz
    spm = profile.limits.steps_per_mm
    opts = CompensateOptions(method=method, lenient=lenient, predict=False, self_check=False)
    icfg = inverse_config(profile, opts)
    summ_c = CompensationSummary(source=src, output=out_path, method=method)
    plan = GcodePlan(src, profile, lenient=lenient)
    npz = out_path.endswith(".npz")
    plain = csv or npz
    out_dir = os.path.dirname(os.path.abspath(out_path))
    sweep_stale(out_dir)
    fd, tmp = make_temp(out_dir, "steps", os.path.splitext(out_path)[1])
    os.close(fd)
    qfd, qpath = make_temp(out_dir, "stepsq", ".f64")
    os.close(qfd)
    summ = StepsSummary(src, out_path, method)
    sink = qs = None
    try:
        sink = (_NpzSink if npz else _CsvSink if csv else FfstepsWriter)(tmp, spm)
        n0 = None
        shaper = lat = None  # quantisation-aware stepping (shape=True)
        k = 0
        qs = SampleFile(qpath)  # every 10th command, for the read-back check (on disk)
        last = None
        n_steps = 0
        moves: dict = {}
        for qc, meta in compensated_stream(plan, moves, profile, model, icfg, opts, summ_c, src):
            # the planned moves are needed only while their samples are in flight (bounded memory)
            mi0 = int(meta["move_index"][0]) - 2
            for old in [m for m in moves if m < mi0]:
                del moves[old]
            # keep one sample of overlap so crossings between chunks are found
            block = qc if last is None else np.vstack([last, qc])
            t_start = (k - (0 if k == 0 else 1)) * dt
            starts, ev = [], {}
            if shape:
                if shaper is None:
                    shaper = NoiseShaper(spm, 2, 3)
                evs, lat = shaped_step_events(block, t_start, dt, shaper, lat)
                for i, name in enumerate(STEPPERS):
                    ev[name] = evs[i]
                    n_steps += len(evs[i][0])
                    starts.append(int(np.rint(block[0, i] * 1e3 * spm)))
            else:
                for i, name in enumerate(STEPPERS):
                    t, d, s0 = step_events(block[:, i], t_start, dt, spm,
                                           None if n0 is None else int(np.rint(block[0, i] * 1e3 * spm)))
                    ev[name] = (t, d)
                    n_steps += len(t)
                    starts.append(s0)
            if n0 is None:
                n0 = tuple(starts)
                sink.start_steps = n0
            sink.push_chunk(ev)
            last = qc[-1:]
            qs.append(qc[(-k) % 10::10])
            k += len(qc)
        if shape and lat is not None and last is not None:
            # the dither may stop up to two steps from the final command: settle on its nearest step
            # within the last sample, so the machine ends where the plain stream does
            miss = np.rint(last[0] * 1e3 * spm).astype(np.int64) - np.asarray(lat, np.int64)
            if miss.any():
                ev = {}
                for i, name in enumerate(STEPPERS):
                    c = int(abs(miss[i]))
                    t = (k - 1) * dt + (np.arange(c) + 1.0) * dt / (c + 1)
                    ev[name] = (t, np.full(c, np.sign(miss[i]), np.int8))
                    n_steps += c
                sink.push_chunk(ev)
        summ.print_time_s = k * dt
        summ.restarts = summ_c.restarts
        summ.queue_lines = sink.finish()
        # reconstruction check on every 10th sample, read back from the written file
        if len(qs):
            if plain:
                q = qs[0:len(qs)]
                rec = positions_from_steps(read_plain(tmp), np.arange(len(q)) * 10 * dt)
                summ.max_step_error_steps = float(np.max(np.abs(rec - q)) * 1e3 * spm)
            else:
                summ.max_step_error_steps = ffsteps_max_error(tmp, qs, 10 * dt)
        summ.steps = n_steps
        os.chmod(tmp, 0o644)
        commit(tmp, out_path)
        keep_temp(tmp)
        tmp = None
    finally:
        if qs is not None:
            qs.close()
        if sink is not None:
            sink.close()
        release_temp(tmp)
        release_temp(qpath)
    summ.wall_time_s = time.perf_counter() - t0
    summ.speed_ratio = summ.print_time_s / max(summ.wall_time_s, 1e-9)
    return summ


class _CsvSink:
    """Plain CSV, streamed: each chunk's steps (all later than the previous chunk's) sorted by time."""

    def __init__(self, path: str, spm: float):
        self.f = open(path, "w", encoding="utf-8")
        self.spm = spm
        self.start_steps = (0, 0, 0)
        self._head = False

    def push_chunk(self, ev: dict) -> None:
        if not self._head:
            write_plain_header(self.f, self.spm, self.start_steps)
            self._head = True
        write_plain_rows(self.f, ev)

    def finish(self) -> int:
        if not self._head:
            write_plain_header(self.f, self.spm, self.start_steps)
        self.f.close()
        return 0

    def close(self) -> None:
        self.f.close()


class _NpzSink:
    """NPZ needs whole arrays: the step times are gathered in memory and written at the end."""

    def __init__(self, path: str, spm: float):
        self.path, self.spm = path, spm
        self.per = {n: ([], []) for n in STEPPERS}
        self.start_steps = (0, 0, 0)

    def push_chunk(self, ev: dict) -> None:
        for n, (t, d) in ev.items():
            self.per[n][0].append(t)
            self.per[n][1].append(d)

    def finish(self) -> int:
        tt = {n: (np.concatenate(self.per[n][0]) if self.per[n][0] else np.zeros(0),
                  np.concatenate(self.per[n][1]) if self.per[n][1] else np.zeros(0, np.int8)) for n in STEPPERS}
        write_plain(self.path, tt, self.spm, self.start_steps)
        return 0

    def close(self) -> None:
        self.per = {n: ([], []) for n in STEPPERS}
