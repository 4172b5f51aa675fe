"""Figures of simulated runs: error over time, error over the bed, bench bars.  Each writes a PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["error_time_png", "error_bed_png", "bench_bars_png"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def error_time_png(path, t_s: np.ndarray, runs: list[tuple[str, np.ndarray, np.ndarray]], *,
                   title: str = "") -> Path:
    """Lag-aligned error per axis and contour error over time, one colour per run.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
    runs : list of (label, err_lag_m (N, 3), contour_m (N,))
    """
    plt = _plt()
    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(10, 8))
    for label, err, cont in runs:
        for j, ax in enumerate(axes[:3]):
            ax.plot(t_s, err[:, j] * 1e6, lw=0.7, label=label)
        axes[3].plot(t_s, cont * 1e6, lw=0.7, label=label)
    for j, name in enumerate(("x", "y", "z")):
        axes[j].set_ylabel(f"{name} err (um)")
    axes[3].set_ylabel("contour (um)")
    axes[3].set_xlabel("time (s)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8, loc="upper right")
    axes[0].set_title(f"lag-aligned tracking error: {title}" if title else "lag-aligned tracking error")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def error_bed_png(path, xyz_ref_m: np.ndarray, runs: list[tuple[str, np.ndarray]], *, title: str = "",
                  print_radius_mm: float | None = None) -> Path:
    """Contour error over the bed (reference x, y coloured by the error), one panel per run."""
    plt = _plt()
    n = len(runs)
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 4.4), squeeze=False)
    vmax = max(float(np.max(c)) for _, c in runs) * 1e6 if runs else 1.0
    xy = xyz_ref_m[:, :2] * 1e3
    for ax, (label, cont) in zip(axes[0], runs, strict=True):
        order = np.argsort(cont)
        sc = ax.scatter(xy[order, 0], xy[order, 1], c=cont[order] * 1e6, s=3, cmap="inferno",
                        vmin=0, vmax=vmax)
        if print_radius_mm:
            th = np.linspace(0, 2 * np.pi, 200)
            ax.plot(print_radius_mm * np.cos(th), print_radius_mm * np.sin(th), "k--", lw=0.5)
        ax.set_aspect("equal")
        ax.set_title(label)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        fig.colorbar(sc, ax=ax, label="contour error (um)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def bench_bars_png(path, variants: list[str], cases: list[str], values_um: np.ndarray, *,
                   ylabel: str = "lag-aligned RMS error (um)") -> Path:
    """Grouped bars: one group per case, one bar per variant (``values_um`` shape (V, C))."""
    plt = _plt()
    V, C = values_um.shape
    fig, ax = plt.subplots(figsize=(max(8, 1.1 * C + 4), 5))
    width = 0.8 / V
    x = np.arange(C)
    cmap = plt.get_cmap("tab20")
    for k in range(V):
        ax.bar(x + (k - (V - 1) / 2) * width, values_um[k], width, label=variants[k], color=cmap(k % 20))
    ax.set_xticks(x)
    ax.set_xticklabels(cases, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
