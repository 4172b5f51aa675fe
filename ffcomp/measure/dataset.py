"""A measurement data set: a directory (or a file) of FRF_FORMAT files and/or UFF files.

``*.csv``, ``*.frf`` and ``*.txt`` files whose ``#`` header holds the FRF_FORMAT magic line are read
with :func:`~ffcomp.measure.frf_file.load_frf` (a malformed one is an error naming the file and
line); other CSV files (notes, raw time series) are skipped and reported; other file types
(README, profiles, reports) are ignored.  ``*.uff`` and
``*.unv`` files are read with :func:`~ffcomp.measure.uff.load_uff` (needs ``pyuff``).  Files
may use different frequency grids, with or without coherence, carriage or assembled kinds.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import MeasurementError
from .frf_file import MAGIC, FrfMeasurement, load_frf

__all__ = ["load_dataset", "FRF_SUFFIXES", "UFF_SUFFIXES"]

FRF_SUFFIXES = (".csv", ".frf", ".txt")
UFF_SUFFIXES = (".uff", ".unv")


def _is_frf(p: Path) -> bool:
    try:
        with open(p, encoding="utf-8", errors="replace") as f:
            for line in f:
                t = line.strip()
                if not t:
                    continue
                if not t.startswith("#"):
                    return False
                if "ffcomp-frf" in t or MAGIC in t:
                    return True
    except OSError:
        return False
    return False


def load_dataset(path, *, skipped: list | None = None) -> list[FrfMeasurement]:
    """Load every measurement in ``path`` (a directory, an FRF file or a UFF file), sorted by name.

    Parameters
    ----------
    skipped : list, optional
        Receives ``(path, reason)`` for each file that was not read.
    """
    p = Path(path)
    if not p.exists():
        raise MeasurementError(str(p), None, "no such file or directory")
    files = [p] if p.is_file() else sorted(x for x in p.iterdir() if x.is_file())
    out: list[FrfMeasurement] = []
    for f in files:
        suf = f.suffix.lower()
        if suf in UFF_SUFFIXES:
            from .uff import load_uff

            out.extend(load_uff(f))
        elif suf in FRF_SUFFIXES or p.is_file():
            if _is_frf(f):
                out.append(load_frf(f))
            elif skipped is not None:
                skipped.append((str(f), "not an ffcomp FRF file (no '# ffcomp-frf 1' first line)"))
    if not out:
        raise MeasurementError(str(p), None, "no measurements found (FRF_FORMAT *.csv files or UFF *.uff/*.unv "
                               "dataset 58 files)")
    return out
