"""Tracking-error metrics of a simulated effector trajectory against its planned reference.

Three views of the same error, from strictest to most forgiving:

* time-aligned: ``act(t) - ref(t)``, what a follower must achieve;
* lag-aligned: ``act(t) - ref(t - lag)`` after the constant ``lag`` that minimises the RMS
  error (a pure delay does not spoil a print);
* contour: distance of each actual point from the reference path, blind to any timing.

Inputs are positions in metres sampled on one uniform time grid, shaped (N, 3).  Summaries are
reported in micrometres and bed locations in millimetres (the ``_um`` / ``_mm`` suffixes).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy import optimize, signal
from scipy.spatial import cKDTree

UM_PER_M = 1e6
MM_PER_M = 1e3
_CHUNK_ELEMS = 2**15  # points x neighbours per contour batch (bounds the temporaries)


def _as_pair(ref: np.ndarray, act: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ref, act = np.asarray(ref, dtype=float), np.asarray(act, dtype=float)
    if ref.shape != act.shape or ref.ndim != 2:
        raise ValueError(f"ref and act must both have shape (N, 3); got {ref.shape} and {act.shape}")
    return ref, act


def _uniform_step_s(t_s: np.ndarray, n: int) -> float:
    t_s = np.asarray(t_s, dtype=float)
    if t_s.shape != (n,) or n < 2:
        raise ValueError(f"t_s must have shape ({n},) with at least two samples, got {t_s.shape}")
    dt_s = (t_s[-1] - t_s[0]) / (n - 1)
    if not dt_s > 0.0 or not np.allclose(np.diff(t_s), dt_s, rtol=1e-6, atol=0.0):
        raise ValueError("t_s must be increasing and uniformly spaced")
    return float(dt_s)


def _at(x: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Rows of ``x`` at fractional indices ``pos`` (linear interpolation, edges held)."""
    n = x.shape[0]
    pos = np.clip(pos, 0.0, n - 1.0)
    i0 = np.minimum(pos.astype(np.intp), n - 2)
    w = (pos - i0).reshape(pos.shape + (1,) * (x.ndim - 1))
    return x[i0] * (1.0 - w) + x[i0 + 1] * w


def _delayed(x: np.ndarray, delay_samples: float) -> np.ndarray:
    """``x`` at fractional index ``j - delay_samples`` for every sample ``j``."""
    return _at(x, np.arange(x.shape[0]) - delay_samples)


def time_aligned_error(ref: np.ndarray, act: np.ndarray) -> np.ndarray:
    """Error ``act - ref`` sample by sample, shape (N, 3), in the inputs' unit."""
    ref, act = _as_pair(ref, act)
    return act - ref


def best_lag(t_s: np.ndarray, ref: np.ndarray, act: np.ndarray, max_lag_s: float = 0.02) -> float:
    """Constant delay ``lag`` minimising the RMS of ``act(t) - ref(t - lag)``.

    A coarse scan over whole-sample lags in ``[-max_lag_s, max_lag_s]`` is refined to sub-sample
    resolution by Brent's bounded method (golden section with parabolic steps) on the RMS error,
    with ``ref`` linearly interpolated.  The RMS is taken over the samples at least
    ``max_lag_s`` from either end, the same set for every lag, so that no extrapolated sample
    enters the objective.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Uniform sample times in s.
    ref, act : ndarray, shape (N, 3)
        Reference and actual positions in m.
    max_lag_s : float, optional
        Largest delay searched, in s (either sign).

    Returns
    -------
    float
        Lag in s; positive when ``act`` trails ``ref``.
    """
    ref, act = _as_pair(ref, act)
    n = ref.shape[0]
    dt_s = _uniform_step_s(t_s, n)
    k_max = int(math.floor(max_lag_s / dt_s + 1e-9))
    if n - 2 * k_max - 2 < 2:
        raise ValueError(f"trajectory of {n} samples is too short for max_lag_s = {max_lag_s} s")
    j0, j1 = k_max + 1, n - k_max - 1
    act_in, j_in = act[j0:j1], np.arange(j0, j1)

    def sq_sum(d: np.ndarray) -> float:
        return float(np.einsum("ij,ij->", d, d))

    def mse_at(delay_samples: float) -> float:
        return sq_sum(act_in - _at(ref, j_in - delay_samples))

    lags = np.arange(-k_max, k_max + 1)
    k_best = int(lags[np.argmin([sq_sum(act_in - ref[j0 - k:j1 - k]) for k in lags])])
    lo, hi = max(k_best - 1, -max_lag_s / dt_s), min(k_best + 1, max_lag_s / dt_s)
    if hi <= lo:
        return k_best * dt_s
    res = optimize.minimize_scalar(mse_at, bounds=(lo, hi), method="bounded",
                                   options={"xatol": 1e-7})
    best = res.x if res.fun <= mse_at(float(k_best)) else float(k_best)
    return float(best * dt_s)


def time_offset_samples(ref: np.ndarray, act: np.ndarray, max_shift: int) -> int:
    """Whole-sample shift ``k`` (``|k| <= max_shift``) that best aligns ``act[j + k]`` with ``ref[j]``.

    For records whose timelines start at different instants (a compensated file runs a pre-roll of
    rest and pre-actuation before its first move): the least-squares match of the positions over
    the overlap, all shifts at once by FFT cross-correlation (positions relative to the first sample
    of each record, so the rest before motion counts as zero).  Positive: ``act`` runs late.
    """
    ref, act = np.asarray(ref, float), np.asarray(act, float)
    a, b = ref - ref[0], act - act[0]
    n = len(a) + len(b)
    nfft = 1 << int(np.ceil(np.log2(max(n, 2))))
    fa, fb = np.fft.rfft(a, nfft, axis=0), np.fft.rfft(b, nfft, axis=0)
    xc = np.fft.irfft(np.sum(np.conj(fa) * fb, axis=1), nfft)  # xc[k] = sum_j a[j] b[j + k]
    # squared error over the overlap: sum b^2 (overlap) - 2 xc + sum a^2 (overlap)
    ca, cb = np.cumsum(np.sum(a * a, 1)), np.cumsum(np.sum(b * b, 1))
    best, best_k = math.inf, 0
    for k in range(-max_shift, max_shift + 1):
        if k >= 0:
            m = min(len(a), len(b) - k)
            if m < 2:
                continue
            ea, eb = ca[m - 1], cb[k + m - 1] - (cb[k - 1] if k else 0.0)
        else:
            m = min(len(a) + k, len(b))
            if m < 2:
                continue
            ea, eb = ca[-k + m - 1] - ca[-k - 1], cb[m - 1]
        c = xc[k] if k >= 0 else xc[nfft + k]
        mse = (ea + eb - 2.0 * c) / m
        if mse < best:
            best, best_k = mse, k
    return best_k


def lag_aligned_error(t_s: np.ndarray, ref: np.ndarray, act: np.ndarray,
                      max_lag_s: float = 0.02) -> tuple[np.ndarray, float]:
    """Error ``act(t) - ref(t - lag)`` after the :func:`best_lag` shift.

    Returns
    -------
    err : ndarray, shape (N, 3)
        Lag-aligned error in the inputs' unit; ``ref`` is held at its first/last value for
        ``t - lag`` outside the grid (exact when the path starts and ends at rest).
    lag_s : float
        The lag in s.
    """
    lag_s = best_lag(t_s, ref, act, max_lag_s)
    ref, act = _as_pair(ref, act)
    dt_s = _uniform_step_s(t_s, ref.shape[0])
    return act - _delayed(ref, lag_s / dt_s), lag_s


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points ``p`` to segments ``[a, b]``, all shaped (..., d) and broadcast.

    Returns shape (...); a zero-length segment is the point ``a``.
    """
    p, a, b = (np.asarray(v, dtype=float) for v in (p, a, b))
    ab, ap = b - a, p - a
    len2 = np.sum(ab * ab, axis=-1)
    u = np.divide(np.sum(ap * ab, axis=-1), len2, out=np.zeros(np.broadcast(len2, ap[..., 0]).shape),
                  where=len2 > 0.0)
    u = np.clip(u, 0.0, 1.0)
    return np.linalg.norm(ap - u[..., None] * ab, axis=-1)


def _subdivide(verts: np.ndarray) -> tuple[np.ndarray, float]:
    """Split segments longer than the median length (the same polyline, more vertices).

    Bounding the segment length keeps the exactness certificate of :meth:`_Polyline.distance`
    local; at most about ``4 M`` vertices are added.  Returns the vertices and half the
    longest remaining segment.
    """
    seg_len = np.linalg.norm(np.diff(verts, axis=0), axis=1)
    ell = max(float(np.median(seg_len)), float(seg_len.sum()) / (4.0 * seg_len.size))
    pieces = np.maximum(1, np.ceil(seg_len / ell - 1e-9)).astype(np.intp)
    seg = np.repeat(np.arange(seg_len.size), pieces)
    frac = (np.arange(seg.size) - np.repeat(np.cumsum(pieces) - pieces, pieces)) / pieces[seg]
    out = verts[seg] + frac[:, None] * (verts[seg + 1] - verts[seg])
    return np.vstack([out, verts[-1:]]), 0.5 * float(np.max(seg_len / pieces))


class _Polyline:
    """A polyline's segments and a vertex tree, for exact nearest-distance queries."""

    def __init__(self, verts: np.ndarray):
        self.verts, self.h = _subdivide(verts)
        self.tree = cKDTree(self.verts)
        self.start, self.ab = self.verts[:-1], np.diff(self.verts, axis=0)
        len2 = np.einsum("ij,ij->i", self.ab, self.ab)
        self.inv_len2 = np.divide(1.0, len2, out=np.zeros_like(len2), where=len2 > 0.0)

    def distance(self, pts: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Distance of ``pts`` over the segments adjacent to their ``k`` nearest vertices.

        Also returns a per-point exactness certificate: a left-out segment has both ends at
        least ``r_k`` (the k-th neighbour's distance) away and is at most ``2 h`` long, so it is
        at least ``sqrt(r_k^2 - h^2)`` away; if that is ``>= d`` (or ``d == 0``) ``d`` is exact.
        """
        m = self.verts.shape[0]
        r, idx = self.tree.query(pts, k=k)
        r, idx = r.reshape(pts.shape[0], k), idx.reshape(pts.shape[0], k)
        seg = np.concatenate([np.clip(idx - 1, 0, m - 2), np.clip(idx, 0, m - 2)], axis=1)
        ap, ab = pts[:, None, :] - self.start[seg], self.ab[seg]
        u = np.clip(np.einsum("ijk,ijk->ij", ap, ab) * self.inv_len2[seg], 0.0, 1.0)
        ap -= u[..., None] * ab
        d2 = np.einsum("ijk,ijk->ij", ap, ap).min(axis=1)
        return np.sqrt(d2), (k >= m) | (d2 == 0.0) | (r[:, -1] ** 2 >= d2 + self.h**2)


def contour_error(ref: np.ndarray, act: np.ndarray, k_neighbours: int = 8) -> np.ndarray:
    """Distance of each actual point from the reference polyline, shape (N,).

    ``ref`` (M, 3): the polyline's vertices in order (consecutive repeats merged); ``act``
    (N, 3): the points; M and N may differ; result in their unit.  The ``k_neighbours``
    vertices nearest each point (``cKDTree``) give candidate segments (both segments at each
    vertex), minimised over by exact point-to-segment distance.  Points whose answer is not
    certified exact (a left-out segment could be nearer, e.g. beside a dense slow stretch) are
    redone with four times as many neighbours, up to all vertices: the result is always exact.
    """
    ref, act = np.asarray(ref, dtype=float), np.asarray(act, dtype=float)
    if ref.ndim != 2 or act.ndim != 2 or ref.shape[1] != act.shape[1] or ref.shape[0] == 0:
        raise ValueError(f"ref (M, d) and act (N, d) must be 2-D with equal d; got {ref.shape}, {act.shape}")
    keep = np.ones(ref.shape[0], dtype=bool)
    keep[1:] = np.any(ref[1:] != ref[:-1], axis=1)
    verts = ref[keep]
    if verts.shape[0] == 1:
        return np.linalg.norm(act - verts[0], axis=1)
    line = _Polyline(verts)
    m = line.verts.shape[0]
    out = np.empty(act.shape[0])
    todo, k = np.arange(act.shape[0]), max(1, int(k_neighbours))
    while todo.size:
        k = min(k, m)
        chunk = max(16, _CHUNK_ELEMS // k)
        unsure = []
        for start in range(0, todo.size, chunk):
            sel = todo[start:start + chunk]
            out[sel], exact = line.distance(act[sel], k)
            unsure.append(sel[~exact])
        todo, k = np.concatenate(unsure), 4 * k
    return out


@dataclass(frozen=True)
class ErrorSummary:
    """Statistics of an error signal, in micrometres.

    Attributes
    ----------
    rms_um, p95_um, max_um : tuple of float, length k
        Per axis (k = 3 for an (N, 3) error, 1 for an (N,) one): RMS, 95th percentile of the
        absolute value, largest absolute value.
    rms_norm_um, p95_norm_um, max_norm_um : float
        The same for the Euclidean norm of each sample.
    n_samples : int
    """

    rms_um: tuple[float, ...]
    p95_um: tuple[float, ...]
    max_um: tuple[float, ...]
    rms_norm_um: float
    p95_norm_um: float
    max_norm_um: float
    n_samples: int

    def to_dict(self) -> dict:
        """Plain JSON-ready dict."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


def summarise(err: np.ndarray) -> ErrorSummary:
    """Summarise an error in metres, shape (N,) or (N, k), into an :class:`ErrorSummary` in um."""
    e = np.asarray(err, dtype=float) * UM_PER_M
    if e.ndim == 1:
        e = e[:, None]
    if e.ndim != 2 or e.shape[0] == 0:
        raise ValueError(f"err must have shape (N,) or (N, k) with N > 0, got {np.shape(err)}")
    a, norm = np.abs(e), np.linalg.norm(e, axis=1)

    def tup(v: np.ndarray) -> tuple[float, ...]:
        return tuple(float(x) for x in v)

    return ErrorSummary(
        rms_um=tup(np.sqrt(np.mean(e**2, axis=0))),
        p95_um=tup(np.percentile(a, 95.0, axis=0)),
        max_um=tup(a.max(axis=0)),
        rms_norm_um=float(np.sqrt(np.mean(norm**2))),
        p95_norm_um=float(np.percentile(norm, 95.0)),
        max_norm_um=float(norm.max()),
        n_samples=int(e.shape[0]),
    )


def error_spectrum(t_s: np.ndarray, err: np.ndarray,
                   window_s: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Amplitude spectrum of an error by Welch's method (Hann, 50 % overlap, mean removed).

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Uniform sample times in s.
    err : ndarray, shape (N,) or (N, k)
        Error in m.
    window_s : float, optional
        Segment length in s (capped at the record length): sets the resolution ``1/window_s``.

    Returns
    -------
    freq_hz : ndarray, shape (F,)
    amplitude : ndarray, shape (F,) or (F, k)
        Peak amplitude in m, ``sqrt(2 * power spectrum)``: a sinusoid of amplitude ``a`` centred
        on a bin shows ``a`` (Hann scalloping lowers off-bin peaks by up to ~15 %).
    """
    err = np.asarray(err, dtype=float)
    dt_s = _uniform_step_s(t_s, err.shape[0])
    nperseg = int(min(err.shape[0], max(8, round(window_s / dt_s))))
    freq_hz, pxx = signal.welch(err, fs=1.0 / dt_s, window="hann", nperseg=nperseg,
                                detrend="constant", scaling="spectrum", axis=0)
    return freq_hz, np.sqrt(2.0 * pxx)


@dataclass(frozen=True)
class WorstRegion:
    """Where on the bed the error is largest, and the map it was found on.

    Attributes
    ----------
    x_mm, y_mm, rms_um : float
        Centre of the worst cell (mm) and its RMS error (um).
    x_centres_mm, y_centres_mm : ndarray, shapes (nx,) and (ny,)
    cell_rms_um, cell_count : ndarray, shape (ny, nx)
        RMS error (um; NaN where no sample fell) and samples per cell, row = y.
    grid_mm : float
        Cell size in mm; cell edges lie on multiples of it.
    """

    x_mm: float
    y_mm: float
    rms_um: float
    x_centres_mm: np.ndarray
    y_centres_mm: np.ndarray
    cell_rms_um: np.ndarray
    cell_count: np.ndarray
    grid_mm: float

    def to_dict(self) -> dict:
        """Plain JSON-ready dict (NaN cells as None)."""
        rms = [[None if math.isnan(v) else float(v) for v in row] for row in self.cell_rms_um]
        return {"x_mm": self.x_mm, "y_mm": self.y_mm, "rms_um": self.rms_um,
                "grid_mm": self.grid_mm, "x_centres_mm": self.x_centres_mm.tolist(),
                "y_centres_mm": self.y_centres_mm.tolist(), "cell_rms_um": rms,
                "cell_count": self.cell_count.tolist()}


def worst_region(xyz_ref: np.ndarray, err_norm: np.ndarray, grid_mm: float = 20.0) -> WorstRegion:
    """Bin an error by the reference's bed position and find the cell with the largest RMS.

    Parameters
    ----------
    xyz_ref : ndarray, shape (N, 3)
        Reference positions in m (only x and y are used).
    err_norm : ndarray, shape (N,)
        Error magnitude per sample in m.
    grid_mm : float, optional
        Square cell size in mm.
    """
    xyz_ref = np.asarray(xyz_ref, dtype=float)
    err_um = np.asarray(err_norm, dtype=float) * UM_PER_M
    if xyz_ref.ndim != 2 or xyz_ref.shape[1] < 2 or err_um.shape != xyz_ref.shape[:1]:
        raise ValueError("xyz_ref must be (N, 3) and err_norm (N,) with the same N")
    if not grid_mm > 0.0:
        raise ValueError(f"grid_mm must be positive, got {grid_mm}")
    cell = np.floor(xyz_ref[:, :2] * MM_PER_M / grid_mm).astype(np.int64)
    lo = cell.min(axis=0)
    nx, ny = cell.max(axis=0) - lo + 1
    flat = (cell[:, 1] - lo[1]) * nx + (cell[:, 0] - lo[0])
    count = np.bincount(flat, minlength=nx * ny).reshape(ny, nx)
    sq = np.bincount(flat, weights=err_um**2, minlength=nx * ny).reshape(ny, nx)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.where(count > 0, np.sqrt(sq / np.maximum(count, 1)), np.nan)
    x_c = (lo[0] + np.arange(nx) + 0.5) * grid_mm
    y_c = (lo[1] + np.arange(ny) + 0.5) * grid_mm
    iy, ix = np.unravel_index(np.nanargmax(rms), rms.shape)
    return WorstRegion(float(x_c[ix]), float(y_c[iy]), float(rms[iy, ix]), x_c, y_c, rms, count,
                       float(grid_mm))


@dataclass(frozen=True)
class ErrorReport:
    """All tracking-error views of one simulated run.

    Attributes
    ----------
    time, lag, contour : ErrorSummary
        Time-aligned error, error after the best constant delay, and distance from the
        reference path (one "axis").
    lag_s, duration_s : float
        Best constant delay (positive: actual trails reference) and record length, in s.
    worst : WorstRegion
        Bed cell with the largest RMS contour error.
    """

    time: ErrorSummary
    lag: ErrorSummary
    contour: ErrorSummary
    lag_s: float
    duration_s: float
    worst: WorstRegion

    def to_dict(self) -> dict:
        """Plain JSON-ready nested dict."""
        return {"time": self.time.to_dict(), "lag": self.lag.to_dict(),
                "contour": self.contour.to_dict(), "lag_s": self.lag_s,
                "duration_s": self.duration_s, "worst": self.worst.to_dict()}


def evaluate(t_s: np.ndarray, ref: np.ndarray, act: np.ndarray, max_lag_s: float = 0.02,
             grid_mm: float = 20.0) -> ErrorReport:
    """Build the :class:`ErrorReport` of ``act`` against ``ref`` (both (N, 3) in m on ``t_s``)."""
    ref, act = _as_pair(ref, act)
    lag_err, lag_s = lag_aligned_error(t_s, ref, act, max_lag_s)
    return _report(t_s, ref, act, lag_err, lag_s, contour_error(ref, act), grid_mm)


def extruding_mask(xyz_m: np.ndarray, e_mm: np.ndarray, dt_s: float) -> np.ndarray:
    """Samples where a reference extrudes while it moves (the printed lines): E rises over the
    sample and the nozzle moves faster than 1 mm/s.  ``xyz_m`` (N, 3) in m, ``e_mm`` (N,) in mm."""
    speed = np.linalg.norm(np.gradient(np.asarray(xyz_m, float), axis=0), axis=1) / dt_s
    return (np.gradient(np.asarray(e_mm, float)) > 1e-6) & (speed > 1e-3)


def evaluate_masked(t_s: np.ndarray, ref: np.ndarray, act: np.ndarray, mask: np.ndarray, max_lag_s: float = 0.02,
                    grid_mm: float = 20.0) -> tuple[ErrorReport, tuple[float, float]]:
    """:func:`evaluate`, and the lag-aligned and contour RMS (um) over the samples ``mask`` selects
    (NaN if none), from one computation of each error (the lag is the whole record's)."""
    ref, act = _as_pair(ref, act)
    lag_err, lag_s = lag_aligned_error(t_s, ref, act, max_lag_s)
    contour = contour_error(ref, act)
    mask = np.asarray(mask, bool)
    if mask.any():
        sub = (float(np.sqrt(np.mean(np.sum(lag_err[mask] ** 2, axis=1)))) * UM_PER_M,
               float(np.sqrt(np.mean(contour[mask] ** 2))) * UM_PER_M)
    else:
        sub = (float("nan"), float("nan"))
    return _report(t_s, ref, act, lag_err, lag_s, contour, grid_mm), sub


def _report(t_s, ref, act, lag_err, lag_s, contour, grid_mm) -> ErrorReport:
    return ErrorReport(
        time=summarise(time_aligned_error(ref, act)),
        lag=summarise(lag_err),
        contour=summarise(contour),
        lag_s=lag_s,
        duration_s=float(np.asarray(t_s)[-1] - np.asarray(t_s)[0]),
        worst=worst_region(ref, contour, grid_mm),
    )
