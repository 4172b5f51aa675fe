"""Validation figures (Bode overlays, error map over the bed, band chart) and the HTML report.

:func:`html_report` writes ONE self-contained page: tables inline, figures as base64 PNGs.
:func:`write_plots` writes the same figures as PNG files into a directory.
"""

from __future__ import annotations

import base64
import html
import io
import re
from pathlib import Path

import numpy as np

from .plots import _plt

__all__ = ["bode_overlay_png", "error_map_png", "band_chart_png", "write_plots", "html_report"]


def _save(fig, path=None) -> bytes:
    plt = _plt()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)  # a constrained layout is kept; others were tight_layout'ed
    plt.close(fig)
    data = buf.getvalue()
    if path is not None:
        Path(path).write_bytes(data)
    return data


class _BodeCanvas:
    """One reusable three-panel figure (magnitude, phase, relative residual versus frequency) whose
    lines are updated in place (creating figures and ticks dominates the cost of a report).  Model
    lines are drawn above the measured dots; the residual panel shows ``|H_pred - H_meas| / |H_meas|``
    smoothed over 5 points against the noise floor, which a dB plot hides."""

    N_CURVES = 4

    def __init__(self):
        plt = _plt()
        self.fig, (self.a1, self.a2, self.a3) = plt.subplots(
            3, 1, sharex=True, figsize=(7.5, 6.6), gridspec_kw={"height_ratios": [3, 2, 1.6]})
        self.fig.subplots_adjust(left=0.11, right=0.98, top=0.95, bottom=0.08, hspace=0.08)
        a1, a2, a3 = self.a1, self.a2, self.a3
        a1.set_xscale("log")
        self.meas = (a1.plot([], [], ".", ms=3, color="0.45", label="measured", zorder=2)[0],
                     a2.plot([], [], ".", ms=3, color="0.45", zorder=2)[0])
        self.lines = [(a1.plot([], [], lw=1.4, zorder=3)[0], a2.plot([], [], lw=1.4, zorder=3)[0],
                       a3.plot([], [], lw=1.2, zorder=3)[0]) for _ in range(self.N_CURVES)]
        for lm, _, lr in self.lines:
            lr.set_color(lm.get_color())
        self.noise_line = a3.axhline(np.nan, color="k", ls="--", lw=0.8, label="noise floor")
        a1.set_ylabel("magnitude (dB)")
        a2.set_ylabel("phase (deg)")
        a3.set_ylabel("rel. residual")
        a3.set_yscale("log")
        a3.set_xlabel("frequency (Hz)")
        for a in (a1, a2, a3):
            a.grid(True, which="both", alpha=0.3)

    def draw(self, meas, curves, title: str, noise: float | None = None) -> bytes:
        f = meas.freq_hz
        ph_m = np.rad2deg(np.unwrap(np.angle(meas.H)))
        self.meas[0].set_data(f, 20 * np.log10(np.abs(meas.H)))
        self.meas[1].set_data(f, ph_m)
        for k, (lm, lp, lr) in enumerate(self.lines):
            on = k < len(curves)
            lm.set_visible(on)
            lp.set_visible(on)
            lr.set_visible(on)
            if on:
                label, H = curves[k]
                ph = np.rad2deg(np.unwrap(np.angle(H)))
                lm.set_data(f, 20 * np.log10(np.abs(H)))
                lp.set_data(f, ph + 360.0 * np.round((ph_m[0] - ph[0]) / 360.0))
                lr.set_data(f, relative_residual(meas.H, H))
                lm.set_label(label)
        self.noise_line.set_ydata([noise if noise and np.isfinite(noise) else np.nan] * 2)
        for a in (self.a1, self.a2, self.a3):
            a.relim(visible_only=True)
            a.autoscale_view()
        self.a1.legend(handles=[self.meas[0]] + [lm for lm, _, _ in self.lines[:len(curves)]], fontsize=8)
        self.a1.set_title(title, fontsize=10)
        buf = io.BytesIO()
        self.fig.savefig(buf, format="png", dpi=90)
        return buf.getvalue()

    def close(self):
        _plt().close(self.fig)


def relative_residual(H_meas, H_pred, smooth: int = 5) -> np.ndarray:
    """``|H_pred - H_meas| / |H_meas|`` as an RMS over ``smooth`` neighbouring points (same length)."""
    e2 = np.abs(np.asarray(H_pred) - np.asarray(H_meas)) ** 2 / np.maximum(np.abs(H_meas), 1e-300) ** 2
    k = max(1, min(int(smooth), len(e2)))
    return np.sqrt(np.convolve(e2, np.ones(k) / k, mode="same"))


def bode_overlay_png(meas, curves, *, title: str = "", path=None, canvas: _BodeCanvas | None = None,
                     noise: float | None = None) -> bytes:
    """Measured FRF (dots) against predictions ``curves = [(label, H), ...]`` with the relative
    residual versus frequency (and the noise floor); returns PNG bytes."""
    cv = canvas or _BodeCanvas()
    data = cv.draw(meas, list(curves)[:_BodeCanvas.N_CURVES], title or meas.label, noise)
    if canvas is None:
        cv.close()
    if path is not None:
        Path(path).write_bytes(data)
    return data


def error_map_png(report, *, print_radius_mm: float | None = None, path=None, title: str = "") -> bytes:
    """Mean complex residual per pose over the bed, one panel per height."""
    plt = _plt()
    rows = report.by_pose()
    zs = sorted({round(r["position_mm"][2], 1) for r in rows})[:4]
    fig, axes = plt.subplots(1, len(zs), figsize=(4.6 * len(zs) + 1.0, 4.4), squeeze=False, layout="constrained")
    # the scale starts at zero and reaches at least 5x the noise floor: a model at the noise looks pale
    vmax = max(max((r["mean_residual"] for r in rows), default=1.0), 5 * report.noise_floor) or 1.0
    sc = None
    for ax, z in zip(axes[0], zs):
        pts = [r for r in rows if round(r["position_mm"][2], 1) == z]
        x = [r["position_mm"][0] for r in pts]
        y = [r["position_mm"][1] for r in pts]
        c = [r["mean_residual"] for r in pts]
        sc = ax.scatter(x, y, c=c, s=380, cmap="magma_r", vmin=0.0, vmax=vmax, edgecolors="k")
        for xi, yi, ci in zip(x, y, c):
            ax.annotate(f"{ci:.3f}", (xi, yi), textcoords="offset points", xytext=(0, 13), ha="center", fontsize=8)
        if print_radius_mm:
            th = np.linspace(0, 2 * np.pi, 200)
            ax.plot(print_radius_mm * np.cos(th), print_radius_mm * np.sin(th), "k-", lw=0.5)
            lim = print_radius_mm * 1.1
            ax.set_xlim(-lim, lim)
            ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.set_title(f"z = {z:g} mm", fontsize=10)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    if sc is not None:
        fig.colorbar(sc, ax=list(axes[0]), label="mean complex residual", shrink=0.85)
    fig.suptitle(title or f"{report.profile}: error over the bed (noise floor {report.noise_floor:.3f})", fontsize=10)
    return _save(fig, path)


def band_chart_png(reports, *, path=None) -> bytes:
    """Mean residual per frequency band for one or more reports (side by side) and the noise floor."""
    plt = _plt()
    reports = list(reports)
    bands = []
    for r in reports:
        for b in r.by_band():
            if b["band"] not in bands:
                bands.append(b["band"])
    order = ["below", "drive", "drive+mechanical", "mechanical", "mechanical 2", "above"]
    bands.sort(key=lambda b: order.index(b) if b in order else len(order))
    fig, ax = plt.subplots(figsize=(7, 3.6))
    w = 0.8 / max(len(reports), 1)
    for k, r in enumerate(reports):
        vals = {b["band"]: b["mean_residual"] for b in r.by_band()}
        ax.bar(np.arange(len(bands)) + (k - (len(reports) - 1) / 2) * w, [vals.get(b, np.nan) for b in bands],
               width=w, label=r.profile[:50])
    ax.axhline(reports[0].noise_floor, color="k", ls="--", lw=1, label="noise floor")
    ax.set_xticks(np.arange(len(bands)), bands)
    ax.set_ylabel("mean complex residual")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", text).strip("_")[:80]


def _curves(report, others, i):
    if not others:
        return [(f"predicted: {report.profile[:60]}", report.predictions[i])]
    return ([(f"before: {o.profile[:60]}", o.predictions[i]) for o in others]
            + [(f"after: {report.profile[:60]}", report.predictions[i])])


def write_plots(directory, report, *, others=(), print_radius_mm=None) -> list[Path]:
    """Every Bode overlay, the error map and the band chart as PNG files; returns the paths."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    paths = []
    cv = _BodeCanvas()
    for i, m in enumerate(report.measurements):
        p = d / (f"bode_{_slug(Path(m.path).stem)}.png" if m.path else f"bode_{i:02d}_{_slug(m.label)}.png")
        bode_overlay_png(m, _curves(report, others, i), title=f"{m.label}: residual {report.scores[i].residual:.3f}",
                         path=p, canvas=cv, noise=report.scores[i].noise)
        paths.append(p)
    cv.close()
    p = d / "error_map.png"
    error_map_png(report, print_radius_mm=print_radius_mm, path=p)
    paths.append(p)
    p = d / "bands.png"
    band_chart_png(list(others) + [report], path=p)
    paths.append(p)
    return paths


def _img(data: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def _f(v, nd=4) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def _table(head, rows, cls="") -> str:
    h = "".join(f"<th>{html.escape(str(x))}</th>" for x in head)
    b = "".join("<tr>" + "".join(f"<td>{html.escape(str(x))}</td>" for x in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{h}</tr></thead><tbody>{b}</tbody></table>'


def _table2(report) -> str:
    t2 = report.table2()
    if not t2:
        return "<p>No x->x, y->y, z->z sweeps in the data.</p>"
    top = "<tr><th rowspan=2>R<sup>2</sup></th>" + "".join(
        f"<th colspan=3>({', '.join(f'{v:g}' for v in p['position_mm'])}) mm</th>" for p in t2) + "</tr>"
    sub = "<tr>" + "<th>mag</th><th>phase</th><th>resid.</th>" * len(t2) + "</tr>"
    body = ""
    for a in ("x->x", "y->y", "z->z"):
        cells = ""
        for p in t2:
            r = p["rows"][a]
            cells += "<td>-</td>" * 3 if r is None else (
                f"<td>{_f(r['r2_mag'], 3)}</td><td>{_f(r['r2_phase'], 3)}</td><td>{_f(r['residual'], 3)}</td>")
        body += f"<tr><th>{html.escape(a.replace('->', '-to-'))}</th>{cells}</tr>"
    return f'<div class="wide"><table class="t2"><thead>{top}{sub}</thead><tbody>{body}</tbody></table></div>'


_CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1200px;color:#222}
table{border-collapse:collapse;margin:.6em 0 1.4em;font-size:13px}th,td{border:1px solid #ccc;padding:3px 7px;
text-align:right}th{background:#f2f2f2}td:first-child{text-align:left}.wide{overflow-x:auto}
img{max-width:100%;margin:.4em 0}.grid img{width:49%}h2{border-bottom:1px solid #ddd;padding-bottom:.2em}
.note{color:#555;font-size:13px}"""


def html_report(path, report, *, others=(), comparison: dict | None = None, print_radius_mm=None,
                max_bode: int = 12, data_name: str = "") -> Path:
    """Write one self-contained HTML page: summary, Table II, ranked failures, bands, poses, axes,
    the comparison (if any), the error map and the Bode overlays of the worst ``max_bode`` fits."""
    r = report
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>ffcomp validate: {html.escape(r.profile)}"
             f"</title><style>{_CSS}</style></head><body>",
             f"<h1>Model versus measurement</h1><p>Profile <b>{html.escape(r.profile)}</b>; data "
             f"<b>{html.escape(data_name)}</b>: {len(r.scores)} measurements.</p>"]
    summ = [["mean normalised complex residual (coherence-weighted)", _f(r.mean_residual)],
            ["noise floor (residual of a perfect model)", _f(r.noise_floor)],
            ["mean R² magnitude, linear (paper's Eq. 36)", _f(r.mean_r2_mag, 3)],
            ["mean R² magnitude, dB", _f(r.mean_r2_mag_db, 3)], ["mean R² phase", _f(r.mean_r2_phase, 3)]]
    parts.append("<h2>Summary</h2>" + _table(["quantity", "value"], summ))
    w = r.worst()
    if w["band"]:
        pose = ", ".join(f"{v:g}" for v in w["pose"]["position_mm"])
        parts.append(f"<p>Fails worst in the <b>{w['band']['band']}</b> band (mean residual "
                     f"{w['band']['mean_residual']:.3f}), at pose <b>({pose})"
                     f" mm</b> ({w['pose']['mean_residual']:.3f}), on <b>{w['axis']['axis']}</b> "
                     f"({w['axis']['mean_residual']:.3f}).</p>")
    if comparison:
        c = comparison
        parts.append("<h2>Before and after</h2>" + _table(
            ["", html.escape(c["before"][:50]), html.escape(c["after"][:50])],
            [["mean complex residual", _f(c["mean_residual_before"]), _f(c["mean_residual_after"])],
             ["mean R² magnitude (linear)", _f(c["mean_r2_mag_before"], 3), _f(c["mean_r2_mag_after"], 3)],
             ["mean R² phase", _f(c["mean_r2_phase_before"], 3), _f(c["mean_r2_phase_after"], 3)],
             ["noise floor", _f(c["noise_floor"]), _f(c["noise_floor"])]]))
        parts.append(_table(["measurement", "residual before", "residual after", "R² mag before", "R² mag after"],
                            [[x["label"], _f(x["residual_before"]), _f(x["residual_after"]), _f(x["r2_mag_before"], 3),
                              _f(x["r2_mag_after"], 3)] for x in c["rows"]]))
    parts.append("<h2>Goodness of fit, laid out like the paper's Table II</h2>"
                 "<p class='note'>R² of the linear magnitude and of the phase (Eq. 36) and the normalised "
                 "complex residual, per position.</p>" + _table2(r))
    parts.append("<h2>Failures ranked by complex residual</h2>" + _table(
        ["measurement", "residual", "x noise", "R² mag (lin)", "R² mag (dB)", "R² phase", "worst band"],
        [[s.label, _f(s.residual), _f(s.residual / s.noise if s.noise > 0 else np.inf, 1), _f(s.r2_mag, 3),
          _f(s.r2_mag_db, 3), _f(s.r2_phase, 3),
          f"{s.worst_band.name} ({s.worst_band.residual:.3f})" if s.worst_band else "-"] for s in r.ranked()]))
    parts.append("<h2>By frequency band</h2>" + _table(
        ["band", "measurements", "mean residual"], [[b["band"], b["n"], _f(b["mean_residual"])] for b in r.by_band()]))
    parts.append(_img(band_chart_png(list(others) + [r]), "band chart"))
    parts.append("<h2>By pose</h2>" + _table(
        ["position (mm)", "measurements", "mean residual", "worst axis"],
        [[", ".join(f"{v:g}" for v in p["position_mm"]), p["n"], _f(p["mean_residual"]), p["worst_axis"]]
         for p in r.by_pose()]))
    parts.append(_img(error_map_png(r, print_radius_mm=print_radius_mm), "error map"))
    parts.append("<h2>By axis</h2>" + _table(
        ["input->output", "measurements", "mean residual", "mean R² mag", "mean R² phase"],
        [[a["axis"], a["n"], _f(a["mean_residual"]), _f(a["mean_r2_mag"], 3), _f(a["mean_r2_phase"], 3)]
         for a in r.by_axis()]))
    idx = sorted(range(len(r.scores)), key=lambda i: -r.scores[i].residual)[:max_bode]
    parts.append(f"<h2>Bode overlays: the {len(idx)} worst fits</h2><div class='grid'>")
    cv = _BodeCanvas()
    for i in idx:
        m = r.measurements[i]
        parts.append(_img(bode_overlay_png(m, _curves(r, others, i), canvas=cv, noise=r.scores[i].noise,
                                           title=f"{m.label}: residual {r.scores[i].residual:.3f}"), m.label))
    cv.close()
    parts.append("</div></body></html>")
    p = Path(path)
    p.write_text("\n".join(parts), encoding="utf-8")
    return p
