"""Universal File Format (UFF/UNV) dataset 58 in and out, through the optional ``pyuff`` package.

Install with ``pip install ffcomp[uff]`` (``pyuff``); it is imported only when a UFF file is read
or written.

Reading (:func:`load_uff`): every dataset 58 record with ``func_type`` 4 (frequency response
function) becomes one :class:`FrfMeasurement`; a ``func_type`` 6 (coherence) record with the same
response/reference node and direction and the same length supplies its coherence.  UFF has no
notion of printer poses, so ffcomp metadata is read from an ID line (``id1`` .. ``id5``)::

    ffcomp: kind=assembled; position_mm=0,0,30; input=x; output=x

Without it, ``ref_dir``/``rsp_dir`` 1, 2, 3 (or -1, -2, -3, which flip the sign) give the input
and output ``x, y, z`` and ``position_mm``/``kind`` must be supplied by the caller.  The ordinate
may be displacement (8), velocity (11) or acceleration (12) over displacement (8): velocity and
acceleration are converted to displacement by dividing by ``j w`` and ``(j w)^2``; length units of
numerator and denominator must agree (e.g. mm/mm or m/m).

Writing (:func:`save_uff`) produces exactly that layout (ASCII, uneven abscissa).
"""

from __future__ import annotations

import numpy as np

from ..errors import MeasurementError
from .frf_file import COORDS, KINDS, FrfMeasurement

__all__ = ["load_uff", "save_uff", "pyuff_available"]

_DIRS = {1: "x", 2: "y", 3: "z"}
_NODES = {"x": (1, 1), "y": (1, 2), "z": (1, 3), "qA": (2, 3), "qB": (3, 3), "qC": (4, 3)}


def _pyuff(path):
    try:
        import pyuff
    except ImportError:
        raise MeasurementError(str(path), None, "reading/writing UFF files needs the optional package pyuff: "
                               "pip install 'ffcomp[uff]' (or pip install pyuff)") from None
    return pyuff


def pyuff_available() -> bool:
    """Whether the optional ``pyuff`` package can be imported."""
    try:
        import pyuff  # noqa: F401
    except ImportError:
        return False
    return True


def _meta(rec) -> dict:
    for k in ("id1", "id2", "id3", "id4", "id5"):
        text = str(rec.get(k, ""))
        if text.strip().lower().startswith("ffcomp:"):
            out = {}
            for part in text.split(":", 1)[1].split(";"):
                if "=" in part:
                    a, b = part.split("=", 1)
                    out[a.strip()] = b.strip()
            return out
    return {}


def load_uff(path, *, kind: str | None = None, position_mm=None) -> list[FrfMeasurement]:
    """Every FRF (dataset 58, ``func_type`` 4) in a UFF file, with coherence where present."""
    pyuff = _pyuff(path)
    path = str(path)
    try:
        recs = pyuff.UFF(path).read_sets()
    except Exception as e:  # pyuff raises bare Exceptions on malformed files
        raise MeasurementError(path, None, f"not a readable UFF file: {e}") from e
    recs = [recs] if isinstance(recs, dict) else list(recs)
    recs = [r for r in recs if r.get("type") == 58]
    coh = {}
    for r in recs:
        if r.get("func_type") == 6:
            coh[(r["rsp_node"], r["rsp_dir"], r["ref_node"], r["ref_dir"], len(r["data"]))] = np.real(r["data"])
    out = []
    for n, r in enumerate(recs):
        if r.get("func_type") != 4:
            continue
        where = f"{path} (dataset 58 record {n})"
        f = np.asarray(r["x"], float)
        H = np.asarray(r["data"], complex)
        md = _meta(r)
        sign = 1.0
        if "input" in md:
            inp, outp = md["input"], md["output"]
        else:
            rd, sd = int(r.get("ref_dir", 0)), int(r.get("rsp_dir", 0))
            if abs(rd) not in _DIRS or abs(sd) not in _DIRS:
                raise MeasurementError(where, None, f"no ffcomp metadata and directions ref {rd}, rsp {sd} are not "
                                       "+-1..3 (x, y, z)")
            inp, outp, sign = _DIRS[abs(rd)], _DIRS[abs(sd)], float(np.sign(rd) * np.sign(sd))
        k = md.get("kind", kind or "assembled")
        pos = md.get("position_mm")
        if pos is None and position_mm is None:
            raise MeasurementError(where, None, "no position: add an ID line 'ffcomp: kind=assembled; "
                                   "position_mm=X,Y,Z; input=x; output=x' or pass position_mm")
        pos = np.array([float(v) for v in pos.split(",")]) if pos is not None else np.asarray(position_mm, float)
        if k not in KINDS or inp not in COORDS or outp not in COORDS or pos.shape != (3,):
            raise MeasurementError(where, None, f"bad ffcomp metadata {md}")
        num, den = int(r.get("ordinate_spec_data_type", 8)), int(r.get("orddenom_spec_data_type", 8))
        if den not in (0, 8) or num not in (0, 1, 8, 11, 12):
            raise MeasurementError(where, None, f"not a position-to-position FRF (ordinate type {num} over {den}; "
                                   "need displacement, velocity or acceleration over displacement)")
        c = coh.get((r["rsp_node"], r["rsp_dir"], r["ref_node"], r["ref_dir"], len(H)))
        keep = f > 0
        f, H = f[keep], H[keep] * sign
        c = None if c is None else np.clip(c[keep], 0.0, 1.0)
        jw = 2j * np.pi * f
        if num == 11:
            H = H / jw
        elif num == 12:
            H = H / jw**2
        if len(f) < 2 or np.any(np.diff(f) <= 0):
            raise MeasurementError(where, None, "frequencies must be positive and strictly increasing")
        src = str(r.get("id1", "")).strip()
        out.append(FrfMeasurement(f, H, c, k, pos, inp, outp, "" if src == "NONE" else src, path,
                                  {"uff_record": str(n)}))
    if not out:
        raise MeasurementError(path, None, "no dataset 58 FRF records (func_type 4)")
    return out


def save_uff(measurements, path) -> None:
    """Write measurements as UFF dataset 58 records (FRF, plus coherence where present)."""
    pyuff = _pyuff(path)
    sets = []
    for m in measurements:
        pos = ",".join(f"{v:g}" for v in m.position_mm)
        rn, rd = _NODES[m.output]
        fn, fd = _NODES[m.input]
        common = dict(rsp_node=rn, rsp_dir=rd, ref_node=fn, ref_dir=fd, x=np.asarray(m.freq_hz, float),
                      id1=(m.source or "ffcomp")[:80], id2="ffcomp FRF",
                      id4=f"ffcomp: kind={m.kind}; position_mm={pos}; input={m.input}; output={m.output}",
                      abscissa_spacing=0, binary=0, abscissa_spec_data_type=18, orddenom_spec_data_type=8)
        sets.append(pyuff.prepare_58(func_type=4, data=np.asarray(m.H, complex), ord_data_type=6,
                                     ordinate_spec_data_type=8, **common))
        if m.coherence is not None:
            sets.append(pyuff.prepare_58(func_type=6, data=np.asarray(m.coherence, float), ord_data_type=4,
                                         ordinate_spec_data_type=0, **common))
    pyuff.UFF(str(path)).write_sets(sets, mode="overwrite")
