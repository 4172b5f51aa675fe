"""``--jobs N``: compensate one file on N cores of one machine.

The source is cut into N pieces at points where the planned toolhead stands still (see
:class:`~ffcomp.pipeline.compensate_flow.Piece`): the first stop (M600, M400, a heater wait, an
unknown macro) or retraction / dwell after a move ending at rest at or after the source lines
``i * lines / N``.  Each piece runs in a worker process (single-threaded BLAS) that plans the whole
file from its start up to the end of its piece (so modal state, positions, limits and E are exact)
but samples, inverts, pin-repairs and writes only its piece; a compensation stream ends at each cut
with ``post_s`` of rest and the next piece's stream starts there with ``pre_s`` of rest, exactly as
at a stop.  The parent then concatenates the bodies (the source's lines, in order), the intended
commands and the segment tables (sample indices, body lines and streams shifted), merges the
writers' statistics (the header's firmware needs: the maximum over the pieces) and the summaries;
the header, the self-check of the whole output and the atomic replace are the serial flow's.

Cost of a cut: none at a stop (the serial run ends a stream there too); at a retraction or dwell
``post_s + pre_s`` (0.35 s by default) of extra rest, during which the nozzle stands still where the
plan stands still.  Every temporary file is created and registered by the parent
(:func:`~ffcomp.io_atomic.make_temp`), so a stop signal leaves nothing behind; a worker only opens
them.  A worker's error is raised again in the parent as the same exception (file, line), the error
of the earliest piece that failed (the one a serial run would have met first); nothing is written.
"""

from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import re
import signal
import time
from dataclasses import fields, replace
from multiprocessing.connection import wait

import numpy as np

from ..errors import SelfCheckError
from ..gcode.segment_lines import SEG_COLS
from ..gcode.writer_stats import WriterStats
from ..io_atomic import make_temp, release_temp
from .compensate_flow import JUMP_M, BodyResult, CompensationSummary, Piece, write_body
from .header import firmware_needs, header_lines
from .self_check import judge, measure, merge, shape_limit_um

__all__ = ["write_body_parallel", "piece_lines", "CUT_NOTE"]

#: the summary note on what the cuts cost
CUT_NOTE = ("--jobs {jobs}: the file was compensated in {pieces} pieces cut where the toolhead stands still "
            "({stops} at stops, no cost; {holds} at retractions/dwells, each adding {rest:.2f} s of rest: "
            "{extra:.2f} s in all)")

_SUMMED = ("restarts", "clamped", "plan_fallback_samples", "pin_windows", "pinned_samples", "hold_margins",
           "hold_margin_time_s", "cap_windows")
# (quiet z moves: each worker plans the file from its start, the last one all of it)
_MAXED = ("max_correction_um", "pin_max_change_um", "print_time_s", "cap_max_change_um", "quiet_z_moves",
          "quiet_z_time_s")


def piece_lines(total_lines: int, jobs: int, src: str | None = None) -> list[Piece]:
    """The pieces for ``jobs`` workers: cuts searched from equal shares of the estimated print time
    (:func:`_time_marks`; of the source lines when ``src`` is None or has no moves)."""
    cuts = None
    if src is not None:
        marks = _time_marks(src, every=max(1, total_lines // 400))
        if marks is not None and marks[-1][1] > 0:
            lines = np.array([m[0] for m in marks])
            times = np.array([m[1] for m in marks])
            cuts = [int(lines[min(np.searchsorted(times, i * times[-1] / jobs), len(lines) - 1)])
                    for i in range(1, jobs)]
    if cuts is None:
        cuts = [max(1, round(i * total_lines / jobs)) for i in range(1, jobs)]
    los = [None, *cuts]
    his = [*cuts, None]
    return [Piece(lo, hi) for lo, hi in zip(los, his)]


_WORD = re.compile(rb"([XYZEF])\s*(-?\d*\.?\d+)")


def _time_marks(src: str, every: int = 1000) -> list[tuple[int, float]] | None:
    """A rough running print time of a file, every ``every`` lines: ``(line, seconds)``.  Only for
    balancing the pieces (distance over feed of each G0/G1, absolute or relative; no accelerations);
    the cuts themselves are found by the plan.  None if the file cannot be read."""
    pos = {b"X": 0.0, b"Y": 0.0, b"Z": 0.0, b"E": 0.0}
    feed, t, rel, rel_e = 1500.0, 0.0, False, False
    marks = []
    try:
        with open(src, "rb") as f:
            for n, raw in enumerate(f, 1):
                code = raw.split(b";", 1)[0]
                if code[:2] in (b"G1", b"G0") and code[2:3] in (b" ", b"\t", b"\n", b"\r", b""):
                    d2, de = 0.0, 0.0
                    for k, v in _WORD.findall(code):
                        x = float(v)
                        if k == b"F":
                            feed = max(x, 1.0)
                            continue
                        if k == b"E":
                            de = abs(x) if rel_e else abs(x - pos[k])
                            pos[k] = pos[k] + x if rel_e else x
                            continue
                        new = pos[k] + x if rel else x
                        d2 += (new - pos[k]) ** 2
                        pos[k] = new
                    t += (d2 ** 0.5 if d2 > 0 else de) * 60.0 / feed
                elif code.startswith((b"G91", b"G90", b"M82", b"M83", b"G92")):
                    c = code[:3]
                    if c == b"G91":
                        rel = rel_e = True
                    elif c == b"G90":
                        rel, rel_e = False, False
                    elif c == b"M83":
                        rel_e = True
                    elif c == b"M82":
                        rel_e = False
                    else:
                        for k, v in _WORD.findall(code):
                            if k in pos:
                                pos[k] = float(v)
                if n % every == 0:
                    marks.append((n, t))
            marks.append((n, t))
    except (OSError, ValueError, UnboundLocalError):
        return None
    return marks


def _single_thread_blas() -> None:
    """One BLAS/OpenMP thread in this (worker) process: the pieces already use every core."""
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[v] = "1"
    try:
        with open("/proc/self/maps") as f:
            libs = {ln.split()[-1] for ln in f if ".so" in ln and "blas" in ln.lower()}
    except OSError:
        return
    for lib in libs:
        try:
            h = ctypes.CDLL(lib)
        except OSError:
            continue
        for name in ("openblas_set_num_threads", "openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
                     "scipy_openblas_set_num_threads64_"):
            fn = getattr(h, name, None)
            if fn is not None:
                fn(1)


def _worker(conn, src, profile, opts, start, piece, paths, total_lines) -> None:
    """Run one piece (in a forked process) and send back ``("ok", BodyResult, counters)`` or
    ``("error", class, state, message)``; progress goes as ``("progress", line)``."""
    from .. import io_atomic

    io_atomic._LIVE.clear()  # the parent's temporary files are the parent's to remove
    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, signal.SIG_DFL)
    _single_thread_blas()
    last = [0.0]

    def progress(line, total):
        now = time.monotonic()
        if now - last[0] > 0.5:
            last[0] = now
            conn.send(("progress", int(line)))

    t0 = time.perf_counter()
    try:
        summ = CompensationSummary(source=src, output="", method=opts.method)
        bd = write_body(src, profile, opts, start, summ, *paths, progress=progress, total_lines=total_lines,
                        piece=piece)
        if opts.self_check and not opts.self_check_whole and bd.k_written:
            bd.self_checks = [_check_piece(src, profile, opts, start, piece, bd, paths)]
        counters = {k: getattr(summ, k) for k in (*_SUMMED, *_MAXED)}
        counters["wall_s"] = time.perf_counter() - t0
        counters["cpu_s"] = time.process_time()
        conn.send(("ok", bd, counters))
    except BaseException as e:  # noqa: BLE001 - every failure goes back to the parent
        try:
            conn.send(("error", type(e), dict(e.__dict__), str(e)))
        except Exception:  # an unpicklable error: its message
            conn.send(("error", RuntimeError, {}, f"{type(e).__name__}: {e}"))
    finally:
        conn.close()


def _check_piece(src, profile, opts, start, piece, bd, paths) -> dict:
    """The self-check of one piece: the header and the piece's body re-planned from rest where the
    piece starts (the file's start, or the plan's point at the cut, where the previous piece ends:
    :func:`judge_pieces` checks that seam)."""
    body_path, qfile, segfile = paths
    needs = firmware_needs(profile, opts, bd.accel, bd.stats)
    head, _ = header_lines(profile, opts, src, bd.accel, needs)
    at = start.position_mm[:3] if piece.lo_line is None else bd.start_mm

    def lines():
        for ln in head:
            yield ln + "\n"
        with open(body_path, encoding="utf-8", errors="surrogateescape", newline="") as f:
            yield from f

    return measure(lines(), qfile, profile, _geom(profile), at, segfile, len(head),
                   name=f"{src} (compensated, piece)")


def _geom(profile):
    from ..model.lpv import LpvModel

    return LpvModel.from_profile(profile).geometry


def judge_pieces(bd: BodyResult, summ, opts, profile) -> None:
    """The self-check of a ``--jobs`` output from its pieces' checks (see :func:`_check_piece`): their
    numbers merged on the whole file's sample clock, and the seams: where a piece ends must be where
    the next one starts (the next piece was checked from there)."""
    dt = 1.0 / profile.limits.sample_rate_hz
    judge(merge(bd.self_checks, bd.k_offsets, dt), summ, opts, dt)
    gap_um = bd.seam_gap_mm * 1e3
    if gap_um > shape_limit_um(opts):
        raise SelfCheckError(f"self-check failed: a piece of the --jobs run ends {gap_um:.1f} um from where the "
                             f"next one starts (limit {shape_limit_um(opts):g} um). Nothing was written.")


def _rebuild(cls, state: dict, msg: str) -> BaseException:
    """The worker's exception, the same class and attributes (file, line) and message."""
    try:
        e = cls.__new__(cls)
        BaseException.__init__(e, msg)
        e.__dict__.update(state)
        return e
    except Exception:
        return RuntimeError(msg)


def write_body_parallel(src: str, profile, opts, start, summ, body_path: str, qfile: str, segfile: str,
                        progress=None, total_lines: int = 0, out_dir: str = ".", jobs: int = 2) -> BodyResult:
    """:func:`~ffcomp.pipeline.compensate_flow.write_body` on ``jobs`` processes (see the module)."""
    pieces = piece_lines(total_lines, jobs, src)
    temps: list[list[str]] = []
    procs: list = []
    try:
        for _ in pieces:
            trio = []
            for kind, suf in (("body", ".gcode"), ("q", ".f32"), ("seg", ".i64")):
                fd, p = make_temp(out_dir, kind, suf)
                os.close(fd)
                trio.append(p)
            temps.append(trio)
        ctx = mp.get_context("fork")
        conns = []
        for i, piece in enumerate(pieces):
            r, w = ctx.Pipe(duplex=False)
            pr = ctx.Process(target=_worker, args=(w, src, profile, opts, start, piece, temps[i], total_lines),
                             daemon=True, name=f"ffcomp-piece-{i}")
            pr.start()
            w.close()
            procs.append(pr)
            conns.append(r)
        results: dict[int, tuple] = {}
        errors: dict[int, BaseException] = {}
        done_line = [0] * len(pieces)
        lo = [p.lo_line or 0 for p in pieces]
        live = dict(enumerate(conns))
        while live:
            # the earliest failing piece decides (a serial run would have met its error first)
            if errors and all(i in results or i in errors for i in range(min(errors) + 1)):
                break
            for c in wait(list(live.values()), timeout=1.0):
                i = next(k for k, v in live.items() if v is c)
                try:
                    msg = c.recv()
                except EOFError:  # died without a word (killed)
                    errors.setdefault(i, RuntimeError(f"the worker for piece {i + 1} of {len(pieces)} died "
                                                      f"(exit code {procs[i].exitcode})"))
                    del live[i]
                    continue
                if msg[0] == "progress":
                    done_line[i] = max(msg[1] - lo[i], 0)
                    if progress is not None:
                        progress(min(sum(done_line), total_lines), total_lines)
                elif msg[0] == "ok":
                    results[i] = msg[1:]
                    del live[i]
                else:
                    errors[i] = _rebuild(*msg[1:])
                    del live[i]
                    for j in list(live):  # later pieces cannot change the outcome
                        if j > i:
                            procs[j].terminate()
        if errors:
            raise errors[min(errors)]
        for pr in procs:
            pr.join()
        return _merge(pieces, [results[i] for i in range(len(pieces))], temps, summ, body_path, qfile, segfile,
                      opts, jobs, 1.0 / profile.limits.sample_rate_hz)
    finally:
        for pr in procs:
            if pr.is_alive():
                pr.terminate()
            pr.join()
        for trio in temps:
            for p in trio:
                release_temp(p)


def _merge(pieces, results, temps, summ, body_path, qfile, segfile, opts, jobs, dt_s) -> BodyResult:
    """Concatenate the pieces' bodies, commands and segment tables; merge their statistics."""
    line_off = k_off = stream_off = 0
    with open(body_path, "w", encoding="utf-8", errors="surrogateescape", newline="") as fb, \
            open(qfile, "wb") as fq, open(segfile, "wb") as fs:
        for (bd, _), (bpath, qpath, spath) in zip(results, temps):
            n_lines = 0
            with open(bpath, encoding="utf-8", errors="surrogateescape", newline="") as f:
                for ln in f:
                    fb.write(ln)
                    n_lines += 1
            with open(qpath, "rb") as f:
                while chunk := f.read(1 << 24):
                    fq.write(chunk)
            with open(spath, "rb") as f:
                while raw := f.read(8 * SEG_COLS * 65536):
                    rows = np.frombuffer(raw, dtype=np.int64).reshape(-1, SEG_COLS).copy()
                    rows[:, 0] += line_off
                    rows[:, 1:3] += k_off
                    rows[:, 4] += stream_off
                    fs.write(rows.tobytes())
            line_off += n_lines
            k_off += bd.k_written
            stream_off += bd.streams
    bds = [bd for bd, _ in results]
    for _, counters in results:
        for k in _SUMMED:
            setattr(summ, k, getattr(summ, k) + counters[k])
        for k in _MAXED:
            setattr(summ, k, max(getattr(summ, k), counters[k]))
    stats = WriterStats()
    for f in fields(WriterStats):
        vals = [getattr(bd.stats, f.name) for bd in bds]
        if f.name == "notes":
            setattr(stats, f.name, [n for v in vals for n in v])
        elif f.name.startswith("peak_"):
            setattr(stats, f.name, max(vals))
        else:
            setattr(stats, f.name, sum(vals))
    last = bds[-1]  # the last piece planned (and parsed) the whole file: its parser's counts are the file's
    if sum(bd.n_xyz for bd in bds) == 0:
        from ..errors import GcodeError

        raise GcodeError(summ.source, last.lines_read, "the file has no XYZ motion (empty, comments only, or no "
                         "moves): nothing to compensate")
    cuts = [bd.cut_hi for bd in bds if bd.cut_hi is not None]
    holds = sum(1 for c in cuts if c[2] == "hold")
    rest = opts.inverse.post_s + opts.inverse.pre_s
    summ.notes.append(CUT_NOTE.format(jobs=jobs, pieces=len(cuts) + 1, stops=len(cuts) - holds, holds=holds,
                                      rest=rest, extra=holds * rest)
                      + "; the pieces took " + ", ".join(f"{c['wall_s']:.1f} s" for _, c in results)
                      + " (print " + ", ".join(f"{bd.k_written * dt_s:.0f} s" for bd, _ in results) + ")")
    summ.jobs = jobs
    summ.pieces = [{"first_line": (bd.cut_lo or (None, 1))[1], "cut": (bd.cut_hi or (None, None, None))[2],
                    "print_s": bd.k_written * dt_s, "wall_s": c["wall_s"], "cpu_s": c["cpu_s"]}
                   for bd, c in results]
    sq = [sum(bd.pred_sq[r] for bd in bds) for r in range(2)]
    mx = [max(bd.pred_mx[r] for bd in bds) for r in range(2)]
    written = [bd for bd in bds if bd.k_written]  # empty pieces (no cut found for them) wrote nothing
    k_offsets = list(np.cumsum([0] + [bd.k_written for bd in written])[:-1].tolist())
    gap = 0.0
    for a, b in zip(written[:-1], written[1:]):
        if a.end_mm is not None and b.start_mm is not None:
            g = float(np.max(np.abs(np.subtract(a.end_mm, b.start_mm))))
            if g <= JUMP_M * 1e3:  # more: a homing between the pieces (a new stream, as in the serial run)
                gap = max(gap, g)
    checks = [bd.self_checks[0] for bd in written] if opts.self_check and not opts.self_check_whole else None
    return replace(last, stats=stats, pred_sq=sq, pred_n=sum(bd.pred_n for bd in bds), pred_mx=mx,
                   pred_time_s=sum(bd.pred_time_s for bd in bds),
                   k_written=sum(bd.k_written for bd in bds), streams=sum(bd.streams for bd in bds), cut_lo=None,
                   cut_hi=None, self_checks=checks, k_offsets=k_offsets, seam_gap_mm=gap)
