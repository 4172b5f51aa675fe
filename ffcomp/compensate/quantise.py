"""Quantisation-aware step streams: put the step lattice's error where the printer does not respond.

A stepper stands on whole (micro)steps.  A firmware steps where the command crosses a half-step
boundary, so the carriage command becomes a staircase whose error, up to half a step, is
concentrated where the carriage moves slowly (corners, reversals, standstill): there the steps
are sparse and the staircase has low-frequency content that rings the 60 Hz drive pair.

:class:`NoiseShaper` chooses the step to stand on at every tick of a fine grid (``upsample`` ticks
per command sample) from the command *plus the error made so far* (error feedback, the
delta-sigma idea): the error is then ``(1 - z^-1)^order`` times a white sequence, a high-pass
whose content sits near half the tick rate (5 kHz for 10 ticks per 1 kHz sample), where drive and
mechanics attenuate it by orders of magnitude.  The command's own content (compensation included)
is kept exactly below that; the price is more steps (the lattice toggles between neighbours while
the carriage stands) and an instantaneous error of up to ``order`` steps (of the fine rate).

On a 1 kHz grid (what a G-code file can carry, one point per sample) the shaping does not help:
the shaped band (500 Hz) is too close to the resonances and a first-order loop sits in idle tones
on slow inputs (``benchmarks/bench_options.py`` measures both).  The step-stream output
(:func:`ffcomp.pipeline.steps_flow.steps_file` with ``shape=True``) uses it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["NoiseShaper", "shape_quantisation", "shaped_step_events", "UPSAMPLE"]

#: ticks of the shaping grid per command sample (10: 10 kHz for 1 kHz commands)
UPSAMPLE = 10


class NoiseShaper:
    """Error-feedback quantiser to the step lattice, streamed (its state carries over chunks).

    Parameters
    ----------
    steps_per_mm : float
    order : {1, 2}
        Order of the error feedback (2: ``(1 - z^-1)^2``, error within two steps).
    channels : int
        Independent signals (carriages).
    origin_m : float
        Position of step 0 (homing fixes the lattice).
    """

    def __init__(self, steps_per_mm: float, order: int = 2, channels: int = 3, origin_m: float = 0.0):
        if order not in (1, 2):
            raise ValueError(f"order must be 1 or 2, got {order}")
        self.step = 1e-3 / float(steps_per_mm)
        self.c1, self.c2 = (1.0, 0.0) if order == 1 else (2.0, -1.0)
        self.origin = float(origin_m)
        self.e1 = np.zeros(channels)  # past quantiser errors, steps
        self.e2 = np.zeros(channels)

    def __call__(self, q_m: np.ndarray) -> np.ndarray:
        """Whole step numbers (n, channels) for positions ``q_m`` (n, channels) on the fine grid."""
        x = (np.asarray(q_m, float) - self.origin) / self.step
        out = np.empty(x.shape, np.int64)
        e1, e2, c1, c2 = self.e1, self.e2, self.c1, self.c2
        for k in range(len(x)):
            v = x[k] - c1 * e1 - c2 * e2  # then n - x = (1 - z^-1)^order e
            n = np.rint(v)
            e2, e1 = e1, n - v
            out[k] = n
        self.e1, self.e2 = e1, e2
        return out


def shape_quantisation(q_m: np.ndarray, steps_per_mm: float, order: int = 2, origin_m: float = 0.0) -> np.ndarray:
    """Positions on the step lattice (same shape as ``q_m``, (N, k)), error shaped ``(1 - z^-1)^order``."""
    q = np.asarray(q_m, float)
    s = NoiseShaper(steps_per_mm, order, q.shape[1], origin_m)
    return origin_m + s(q) * s.step


def shaped_step_events(block_m: np.ndarray, t0_s: float, dt_s: float, shaper: NoiseShaper,
                       n_prev: np.ndarray | None, upsample: int = UPSAMPLE):
    """Step events of a command chunk, shaped on a grid ``upsample`` times finer than ``dt_s``.

    ``block_m`` (n, k) are commands at ``t0_s + j dt_s``, linear in between (its first row repeats
    the last of the previous chunk, whose ticks are already done, unless ``n_prev`` is None).
    Returns per channel ``(t_s, dir)`` and the lattice position after the chunk (k,).  Steps of one
    tick are spread evenly over it (several when the carriage moves fast).
    """
    q = np.asarray(block_m, float)
    n, k = q.shape
    h = dt_s / upsample
    j = np.arange((n - 1) * upsample + 1)
    tf = t0_s + j * h
    fine = np.stack([np.interp(j / upsample, np.arange(n), q[:, i]) for i in range(k)], 1)
    if n_prev is not None:
        fine, tf = fine[1:], tf[1:]
    lat = shaper(fine)
    start = lat[:1] if n_prev is None else np.asarray(n_prev, np.int64)[None]
    d = np.diff(np.concatenate([start, lat]), axis=0)
    events = []
    for i in range(k):
        cnt = np.abs(d[:, i])
        idx = np.repeat(np.arange(len(cnt)), cnt)
        if idx.size == 0:
            events.append((np.zeros(0), np.zeros(0, np.int8)))
            continue
        off = np.arange(idx.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        t = tf[idx] - h + (off + 0.5) * h / cnt[idx]
        events.append((t, np.sign(d[idx, i]).astype(np.int8)))
    return events, lat[-1] if len(lat) else start[0]
