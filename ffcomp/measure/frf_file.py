"""Reader and writer for ffcomp FRF measurement files, version 1 (``shared/FRF_FORMAT.md``).

One FRF per file: ``#`` header lines ``key: value`` after the magic line ``# ffcomp-frf 1``, then a
CSV table with ``freq_hz`` and either ``real,imag`` or ``mag,phase_deg``, optionally ``coherence``.
Header keys ffcomp does not know are kept in :attr:`FrfMeasurement.meta` and written back, so the
format can be extended without breaking older readers.  Every error names the file and line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import MeasurementError

__all__ = ["FrfMeasurement", "load_frf", "save_frf", "load_frf_dir", "KINDS", "COORDS"]

MAGIC = "ffcomp-frf 1"
KINDS = ("carriage", "assembled")
COORDS = ("x", "y", "z", "qA", "qB", "qC")


@dataclass(frozen=True)
class FrfMeasurement:
    """One measured frequency response.

    Attributes
    ----------
    freq_hz : ndarray, shape (F,)
        Strictly increasing positive frequencies, Hz.
    H : ndarray, shape (F,), complex
        Output / commanded input (dimensionless for position-to-position FRFs).
    coherence : ndarray, shape (F,) or None
        0..1; ``None`` when the file has no coherence column.
    kind : {"carriage", "assembled"}
    position_mm : ndarray, shape (3,)
        Task-space point of the sweep, mm.
    input, output : str
        One of ``x, y, z, qA, qB, qC``.
    source : str
        Free text from the file.
    path : str or None
        File it was read from.
    meta : dict
        Extra header keys (kept verbatim).
    """

    freq_hz: np.ndarray
    H: np.ndarray
    coherence: np.ndarray | None
    kind: str
    position_mm: np.ndarray
    input: str
    output: str
    source: str = ""
    path: str | None = None
    meta: dict = field(default_factory=dict)

    @property
    def weights(self) -> np.ndarray:
        """Coherence (or ones) as least-squares weights."""
        return np.ones_like(self.freq_hz) if self.coherence is None else np.clip(self.coherence, 0.0, 1.0)

    @property
    def label(self) -> str:
        p = ",".join(f"{v:g}" for v in self.position_mm)
        return f"{self.kind} {self.input}->{self.output} @({p})"


def _parse_position(path, lineno, value, text):
    parts = [p.strip() for p in value.split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise MeasurementError(path, lineno, f"position_mm must be three numbers x, y, z, got {value!r}",
                               text) from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise MeasurementError(path, lineno, f"position_mm must be three finite numbers, got {value!r}", text)
    return np.array(vals)


def load_frf(path: str | Path) -> FrfMeasurement:
    """Read one FRF file; raises :class:`MeasurementError` naming the file, line and value."""
    path = str(path)
    try:
        with open(path, encoding="utf-8") as f:
            lines = f.read().splitlines()
    except OSError as e:
        raise MeasurementError(path, None, f"cannot read: {e.strerror or e}") from e
    except UnicodeDecodeError as e:
        raise MeasurementError(path, None, f"not a UTF-8 text file ({e.reason})") from e
    header: dict[str, tuple[int, str]] = {}
    magic_seen = False
    cols: list[str] | None = None
    col_line = 0
    rows: list[list[float]] = []
    for lineno, raw in enumerate(lines, 1):
        text = raw.strip()
        if not text:
            continue
        if text.startswith("#"):
            body = text[1:].strip()
            if body.startswith("ffcomp-frf"):
                if body != MAGIC:
                    raise MeasurementError(path, lineno, f"unsupported format version (expected '# {MAGIC}')",
                                           raw)
                magic_seen = True
                continue
            if ":" in body and cols is None:
                key, _, value = body.partition(":")
                # a comment after the value (two spaces or more then text) is allowed, as in the spec
                header[key.strip()] = (lineno, value.strip())
            continue
        if cols is None:
            cols = [c.strip() for c in text.split(",")]
            col_line = lineno
            allowed = {"freq_hz", "real", "imag", "mag", "phase_deg", "coherence"}
            bad = [c for c in cols if c not in allowed]
            if bad or "freq_hz" not in cols:
                raise MeasurementError(path, lineno, f"bad column header (unknown {bad}; need freq_hz and "
                                       "real,imag or mag,phase_deg, optional coherence)", raw)
            if not ({"real", "imag"} <= set(cols) or {"mag", "phase_deg"} <= set(cols)):
                raise MeasurementError(path, lineno, "need columns real,imag or mag,phase_deg", raw)
            continue
        parts = text.split(",")
        if len(parts) != len(cols):
            raise MeasurementError(path, lineno, f"expected {len(cols)} values, got {len(parts)}", raw)
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            bad = next(p for p in parts if not _isfloat(p))
            raise MeasurementError(path, lineno, f"not a number: {bad.strip()!r}", raw) from None
        if not all(math.isfinite(v) for v in vals):
            raise MeasurementError(path, lineno, "values must be finite", raw)
        rows.append(vals)
    if not magic_seen:
        raise MeasurementError(path, 1, f"missing magic line '# {MAGIC}' (is this an ffcomp FRF file?)",
                               lines[0] if lines else "")
    if cols is None or not rows:
        raise MeasurementError(path, col_line or len(lines), "no data rows")
    data = np.array(rows)
    c = {name: data[:, i] for i, name in enumerate(cols)}
    f = c["freq_hz"]
    for i in range(len(f)):
        if f[i] <= 0 or (i and f[i] <= f[i - 1]):
            raise MeasurementError(path, _data_line(lines, col_line, i),
                                   f"frequencies must be positive and strictly increasing, got {f[i]:g}")
    if "real" in c:
        H = c["real"] + 1j * c["imag"]
    else:
        if np.any(c["mag"] < 0):
            i = int(np.argmax(c["mag"] < 0))
            raise MeasurementError(path, _data_line(lines, col_line, i), f"negative magnitude {c['mag'][i]:g}")
        H = c["mag"] * np.exp(1j * np.deg2rad(c["phase_deg"]))
    coh = c.get("coherence")
    if coh is not None and (np.any(coh < 0) or np.any(coh > 1)):
        i = int(np.argmax((coh < 0) | (coh > 1)))
        raise MeasurementError(path, _data_line(lines, col_line, i), f"coherence {coh[i]:g} outside 0..1")

    def need(key, allowed=None):
        if key not in header:
            raise MeasurementError(path, None, f"missing header '# {key}: ...'")
        ln, v = header[key]
        v = v.split("  ")[0].strip()
        if allowed is not None and v not in allowed:
            raise MeasurementError(path, ln, f"{key} must be one of {', '.join(allowed)}, got {v!r}")
        return ln, v

    _, kind = need("kind", KINDS)
    ln, pos = need("position_mm")
    position = _parse_position(path, ln, pos.split("  ")[0], pos)
    _, inp = need("input", COORDS)
    _, out = need("output", COORDS)
    source = header.get("source", (0, ""))[1]
    known = {"kind", "position_mm", "input", "output", "source"}
    meta = {k: v for k, (_, v) in header.items() if k not in known}
    return FrfMeasurement(f, H, coh, kind, position, inp, out, source, path, meta)


def _isfloat(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _data_line(lines: list[str], col_line: int, i: int) -> int:
    """Line number of the i-th data row after the column header."""
    n = -1
    for k in range(col_line, len(lines)):
        t = lines[k].strip()
        if t and not t.startswith("#"):
            n += 1
            if n == i:
                return k + 1
    return col_line


def save_frf(meas: FrfMeasurement, path: str | Path, *, polar: bool = False) -> None:
    """Write an FRF file atomically (``real,imag`` columns unless ``polar``)."""
    from ..io_atomic import atomic_open

    pos = ", ".join(f"{v:g}" for v in meas.position_mm)
    head = [f"# {MAGIC}", f"# kind: {meas.kind}", f"# position_mm: {pos}", f"# input: {meas.input}",
            f"# output: {meas.output}"]
    if meas.source:
        head.append(f"# source: {meas.source}")
    head += [f"# {k}: {v}" for k, v in meas.meta.items()]
    cols = ["freq_hz"] + (["mag", "phase_deg"] if polar else ["real", "imag"])
    if meas.coherence is not None:
        cols.append("coherence")
    with atomic_open(path, "w") as f:
        f.write("\n".join(head) + "\n" + ",".join(cols) + "\n")
        for i in range(len(meas.freq_hz)):
            h = meas.H[i]
            a, b = (abs(h), math.degrees(np.angle(h))) if polar else (h.real, h.imag)
            row = f"{meas.freq_hz[i]:.10g},{a:.10g},{b:.10g}"
            if meas.coherence is not None:
                row += f",{meas.coherence[i]:.6g}"
            f.write(row + "\n")


def load_frf_dir(path: str | Path, pattern: str = "*.csv") -> list[FrfMeasurement]:
    """Every FRF file in a directory (sorted by name); a single file path is accepted too."""
    p = Path(path)
    if p.is_file():
        return [load_frf(p)]
    if not p.is_dir():
        raise MeasurementError(str(p), None, "no such file or directory")
    files = sorted(p.glob(pattern))
    if not files:
        raise MeasurementError(str(p), None, f"no measurement files matching {pattern!r}")
    return [load_frf(f) for f in files]
