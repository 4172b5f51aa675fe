"""Matplotlib figures: Bode plots, mode maps.  Every function writes a PNG and returns its path."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["bode_png", "mode_map_png", "fit_overlay_png"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def bode_png(path, freq_hz, curves: list[tuple[str, np.ndarray]], *, title: str = "",
             measured: list[tuple[str, np.ndarray, np.ndarray]] | None = None) -> Path:
    """Bode plot of complex responses ``curves = [(label, H), ...]`` (dB and degrees).

    ``measured``: optional ``[(label, freq_hz, H), ...]`` drawn as markers.
    """
    plt = _plt()
    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
    for label, H in curves:  # lines above the dots
        ax1.semilogx(freq_hz, 20 * np.log10(np.abs(H)), label=label, zorder=3)
        ax2.semilogx(freq_hz, np.rad2deg(np.unwrap(np.angle(H))), label=label, zorder=3)
    for label, f, H in measured or []:
        ax1.semilogx(f, 20 * np.log10(np.abs(H)), ".", ms=3, label=label, zorder=2, alpha=0.6)
        ax2.semilogx(f, np.rad2deg(np.unwrap(np.angle(H))), ".", ms=3, label=label, zorder=2, alpha=0.6)
    ax1.set_ylabel("magnitude (dB)")
    ax2.set_ylabel("phase (deg)")
    ax2.set_xlabel("frequency (Hz)")
    ax1.grid(True, which="both", alpha=0.3)
    ax2.grid(True, which="both", alpha=0.3)
    return _save(fig, ax1, title, path)


def mode_map_png(path, xy_mm: np.ndarray, freq_hz: np.ndarray, *, title: str = "",
                 labels=("mode 1", "mode 2", "mode 3"), print_radius_mm: float | None = None) -> Path:
    """Scatter maps of each mode's natural frequency over the bed (one panel per mode)."""
    plt = _plt()
    n = freq_hz.shape[1]
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 4))
    for j, ax in enumerate(np.atleast_1d(axes)):
        sc = ax.scatter(xy_mm[:, 0], xy_mm[:, 1], c=freq_hz[:, j], s=18, cmap="viridis", marker="s")
        fig.colorbar(sc, ax=ax, label="Hz")
        ax.set_aspect("equal")
        ax.set_title(labels[j] if j < len(labels) else f"mode {j + 1}")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        if print_radius_mm:
            th = np.linspace(0, 2 * np.pi, 200)
            ax.plot(print_radius_mm * np.cos(th), print_radius_mm * np.sin(th), "k-", lw=0.5)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def fit_overlay_png(path, fits, *, title: str = "") -> Path:
    """Measured sweeps (dots) with their fits (lines drawn above), and the relative residual
    ``|H_fit - H_meas| / |H_meas|`` versus frequency against each sweep's noise floor.

    ``fits = [(label, FrfMeasurement, H_fit), ...]`` (``H_fit`` on the measurement's grid).
    """
    from ..measure.noise import noise_floors
    from .validate_report import relative_residual

    plt = _plt()
    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, sharex=True, figsize=(8, 7.5), gridspec_kw={"height_ratios": [3, 2, 1.6]})
    nus = noise_floors([m for _, m, _ in fits]).values
    for (label, m, Hf), nu in zip(fits, nus):
        ph_m = np.rad2deg(np.unwrap(np.angle(m.H)))
        ph_f = np.rad2deg(np.unwrap(np.angle(Hf)))
        ph_f = ph_f + 360.0 * np.round((ph_m[0] - ph_f[0]) / 360.0)
        pts = ax1.semilogx(m.freq_hz, 20 * np.log10(np.abs(m.H)), ".", ms=3, alpha=0.5, zorder=2,
                           label=f"{label} data")[0]
        col = pts.get_color()
        ax1.semilogx(m.freq_hz, 20 * np.log10(np.abs(Hf)), "-", color=col, lw=1.6, zorder=3, label=f"{label} fit")
        ax2.semilogx(m.freq_hz, ph_m, ".", ms=3, alpha=0.5, color=col, zorder=2)
        ax2.semilogx(m.freq_hz, ph_f, "-", color=col, lw=1.6, zorder=3)
        ax3.semilogx(m.freq_hz, relative_residual(m.H, Hf), "-", color=col, lw=1.2, label=f"{label} residual")
        ax3.axhline(nu, color=col, ls="--", lw=0.8)
    ax3.set_yscale("log")
    ax1.set_ylabel("magnitude (dB)")
    ax2.set_ylabel("phase (deg)")
    ax3.set_ylabel("rel. residual")
    ax3.set_xlabel("frequency (Hz)  (dashed: noise floor)")
    for a in (ax1, ax2, ax3):
        a.grid(True, which="both", alpha=0.3)
    return _save(fig, ax1, title, path)


def _save(fig, ax, title: str, path, dpi: int = 110) -> Path:
    """Legend and title on ``ax``, then write ``fig`` to ``path`` and close it."""
    import matplotlib.pyplot as plt

    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)
