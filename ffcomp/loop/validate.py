"""Model versus measurement: goodness of fit per measurement, per band, per pose and per axis.

For each measurement the prediction is the profile's model at the measurement's pose, in the
frame its input/output imply (:func:`ffcomp.measure.predict.predict`).  Reported:

* ``r2_mag``: the paper's Eq. 36 on the **linear** magnitude ``|H|`` (as in its Table II);
  ``r2_mag_db``: the same on ``20 log10 |H|``; ``r2_phase``: on the unwrapped phase in degrees.
  R^2 is unweighted, as in the paper.
* ``residual``: the normalised complex residual ``||H_pred - H_meas|| / ||H_meas||``, weighted by
  coherence when the file has it; unlike R^2 it sees phase and every mode at once.  Compare it to
  ``noise``, the residual a perfect model would leave (:mod:`ffcomp.measure.noise`).
* band residuals: the same within bands set by the model's resonances at that pose: ``below``
  (under 0.7x the lowest resonance), ``drive`` (the electrical resonance ``sqrt(d0)``),
  ``mechanical`` (the coupled carriage modes at the pose), ``drive+mechanical`` where they
  coincide, ``above`` (over 1.4x the highest); see :func:`band_edges`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..measure.noise import below_floor_note, noise_floors
from ..measure.predict import BatchPredictor, check_measurements, detached
from ..model.lpv import LpvModel
from ..model.modes import modes
from .metrics import complex_residual, r2_magnitude, r2_phase

__all__ = ["BandScore", "MeasurementScore", "ValidationReport", "validate", "compare", "band_edges",
           "TABLE2_AXES"]

TABLE2_AXES = ("x->x", "y->y", "z->z")


@dataclass(frozen=True)
class BandScore:
    """Normalised complex residual within one frequency band ``[lo_hz, hi_hz)``."""

    name: str
    lo_hz: float
    hi_hz: float
    residual: float
    n_points: int

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class MeasurementScore:
    """Goodness of fit of one measurement (see the module docstring for each number)."""

    label: str
    path: str | None
    kind: str
    input: str
    output: str
    position_mm: tuple
    n_points: int
    f_lo_hz: float
    f_hi_hz: float
    r2_mag: float
    r2_mag_db: float
    r2_phase: float
    residual: float
    noise: float
    noise_source: str
    bands: tuple

    @property
    def axis(self) -> str:
        return f"{self.input}->{self.output}"

    @property
    def worst_band(self) -> BandScore | None:
        """The band with the largest residual (None if no band has two points)."""
        b = [x for x in self.bands if np.isfinite(x.residual)]
        return max(b, key=lambda x: x.residual) if b else None

    def to_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "bands"}
        d["position_mm"] = list(self.position_mm)
        d["axis"] = self.axis
        d["bands"] = [b.to_dict() for b in self.bands]
        return d


def _mean(v) -> float:
    v = [x for x in v if np.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


@dataclass(frozen=True)
class ValidationReport:
    """All scores of one profile against one data set; arrays for plots in ``measurements`` and
    ``predictions`` (not part of :meth:`to_dict`)."""

    profile: str
    scores: tuple
    measurements: tuple = field(repr=False, default=())
    predictions: tuple = field(repr=False, default=())
    #: where the floor came from (``coherence``, ``data``, ``given``) and why, if the estimates disagreed
    noise_source: str = ""
    noise_note: str = ""

    @property
    def below_floor(self) -> str:
        """A warning when the mean residual sits well below the noise floor (else empty)."""
        return below_floor_note(self.mean_residual, self.noise_floor, self.noise_source)

    @property
    def mean_residual(self) -> float:
        """Mean normalised complex residual over measurements (coherence-weighted), dimensionless."""
        return _mean(s.residual for s in self.scores)

    @property
    def noise_floor(self) -> float:
        """Mean noise floor (the residual a perfect model would leave), dimensionless."""
        return _mean(s.noise for s in self.scores)

    @property
    def mean_r2_mag(self) -> float:
        """Mean R^2 (Eq. 36) of the linear magnitude."""
        return _mean(s.r2_mag for s in self.scores)

    @property
    def mean_r2_mag_db(self) -> float:
        return _mean(s.r2_mag_db for s in self.scores)

    @property
    def mean_r2_phase(self) -> float:
        return _mean(s.r2_phase for s in self.scores)

    def ranked(self) -> list[MeasurementScore]:
        """Measurements from the worst fit (largest complex residual) to the best."""
        return sorted(self.scores, key=lambda s: -s.residual)

    def by_pose(self) -> list[dict]:
        """Mean residual per pose, worst first: ``position_mm``, ``mean_residual``, ``n``, ``worst_axis``."""
        groups: dict = {}
        for s in self.scores:
            groups.setdefault(tuple(round(v, 1) for v in s.position_mm), []).append(s)
        out = [{"position_mm": list(k), "mean_residual": _mean(x.residual for x in v),
                "noise": _mean(x.noise for x in v), "n": len(v),
                "worst_axis": max(v, key=lambda x: x.residual).axis} for k, v in groups.items()]
        return sorted(out, key=lambda d: -d["mean_residual"])

    def by_axis(self) -> list[dict]:
        """Per input->output pair (and kind): mean residual and R^2, worst first."""
        groups: dict = {}
        for s in self.scores:
            key = s.axis if s.kind == "assembled" else f"{s.axis} (carriage)"
            groups.setdefault(key, []).append(s)
        out = [{"axis": k, "n": len(v), "mean_residual": _mean(x.residual for x in v),
                "mean_r2_mag": _mean(x.r2_mag for x in v), "mean_r2_phase": _mean(x.r2_phase for x in v)}
               for k, v in groups.items()]
        return sorted(out, key=lambda d: -d["mean_residual"])

    def by_band(self) -> list[dict]:
        """Mean band residual over measurements, worst first."""
        groups: dict = {}
        for s in self.scores:
            for b in s.bands:
                if np.isfinite(b.residual):
                    groups.setdefault(b.name, []).append(b.residual)
        out = [{"band": k, "n": len(v), "mean_residual": float(np.mean(v))} for k, v in groups.items()]
        return sorted(out, key=lambda d: -d["mean_residual"])

    def worst(self) -> dict:
        """Where the model fails worst: band, pose, axis and measurement."""
        bp, ba, bb, r = self.by_pose(), self.by_axis(), self.by_band(), self.ranked()
        return {"band": bb[0] if bb else None, "pose": bp[0] if bp else None, "axis": ba[0] if ba else None,
                "measurement": r[0].label if r else None}

    def table2(self) -> list[dict]:
        """The paper's Table II layout: per position, rows x->x, y->y, z->z with R^2 mag (linear),
        R^2 phase and the complex residual (None where not measured)."""
        pos: dict = {}
        for s in self.scores:
            if s.kind == "assembled" and s.axis in TABLE2_AXES:
                pos.setdefault(tuple(round(v, 1) for v in s.position_mm), {})[s.axis] = s
        keys = sorted(pos, key=lambda p: (p[2], np.hypot(p[0], p[1]) > 0.5, np.arctan2(p[1], p[0]) % (2 * np.pi)))
        return [{"position_mm": list(k), "rows": {a: ({"r2_mag": pos[k][a].r2_mag, "r2_phase": pos[k][a].r2_phase,
                                                      "r2_mag_db": pos[k][a].r2_mag_db,
                                                      "residual": pos[k][a].residual} if a in pos[k] else None)
                                                  for a in TABLE2_AXES}} for k in keys]

    def to_dict(self) -> dict:
        return {
            "profile": self.profile,
            "summary": {"n_measurements": len(self.scores), "mean_residual": self.mean_residual,
                        "noise_floor": self.noise_floor, "noise_source": self.noise_source,
                        "noise_note": self.noise_note, "below_floor": self.below_floor,
                        "mean_r2_mag_linear": self.mean_r2_mag,
                        "mean_r2_mag_db": self.mean_r2_mag_db, "mean_r2_phase": self.mean_r2_phase},
            "worst": self.worst(),
            "table2": self.table2(),
            "by_band": self.by_band(),
            "by_pose": self.by_pose(),
            "by_axis": self.by_axis(),
            "measurements": [s.to_dict() for s in self.ranked()],
        }


def band_edges(f_drive_hz: float, f_mech_hz) -> tuple[list[str], list[float]]:
    """Band names and edges (Hz; ``len(names) + 1`` values, the last ``inf``) for given resonances.

    The drive resonance and the mechanical modes are sorted and grouped into clusters (neighbours
    within a factor 1.25); each cluster is a band named by what it holds (``drive``,
    ``mechanical``, ``drive+mechanical``; ``mechanical 2`` for a second mechanical-only cluster),
    split from the next at the geometric mean; ``below`` ends at 0.7x the lowest resonance,
    ``above`` starts at 1.4x the highest.
    """
    fm = np.asarray(f_mech_hz, float)
    pts = sorted([(float(f_drive_hz), "drive")] + [(float(f), "mechanical") for f in fm[np.isfinite(fm) & (fm > 0)]])
    clusters = [[pts[0]]]
    for f, k in pts[1:]:
        if f <= 1.25 * clusters[-1][-1][0]:
            clusters[-1].append((f, k))
        else:
            clusters.append([(f, k)])
    names, edges = ["below"], [0.0, 0.7 * clusters[0][0][0]]
    seen: dict = {}
    for i, c in enumerate(clusters):
        kinds = sorted({k for _, k in c})
        name = "+".join(kinds)
        seen[name] = seen.get(name, 0) + 1
        names.append(name if seen[name] == 1 else f"{name} {seen[name]}")
        if i + 1 < len(clusters):
            edges.append(float(np.sqrt(c[-1][0] * clusters[i + 1][0][0])))
    names.append("above")
    edges += [1.4 * clusters[-1][-1][0], np.inf]
    return names, edges


def _bands(meas, Hp, names, edges) -> tuple:
    out = []
    f, w = meas.freq_hz, meas.weights
    for i, name in enumerate(names):
        sel = (f >= edges[i]) & (f < edges[i + 1])
        res = complex_residual(meas.H[sel], Hp[sel], w[sel]) if sel.sum() >= 2 else float("nan")
        out.append(BandScore(name, float(edges[i]), float(edges[i + 1]), res, int(sel.sum())))
    return tuple(out)


def _resonances(model, measurements) -> list[tuple[float, np.ndarray]]:
    """(drive frequency, mechanical mode frequencies) at each measurement's pose, Hz."""
    f_d = float(np.sqrt(np.mean(model.carriage.d0)) / (2 * np.pi))
    out = []
    cache: dict = {}
    for m in measurements:
        key = (m.kind, tuple(np.round(m.position_mm, 6)))
        if key not in cache:
            mdl = detached(model) if m.kind == "carriage" else model
            ms = modes(mdl, np.asarray(m.position_mm, float)[None] * 1e-3)
            fm = ms.freq_hz[0]
            if m.kind == "carriage" and m.output.startswith("q"):
                fm = fm[[int(np.argmax(np.abs(ms.shape_joint[0, "ABC".index(m.output[1])])))]]
            cache[key] = fm
        out.append((f_d, cache[key]))
    return out


def validate(profile_or_model, measurements, *, name: str | None = None,
             noise_floor: float | None = None) -> ValidationReport:
    """Score a profile (or :class:`LpvModel`) against measurements.

    Parameters
    ----------
    profile_or_model : PrinterProfile or LpvModel
        With a profile its ``[[effects]]`` are included.
    measurements : sequence of FrfMeasurement
    name : str, optional
        Label of the model in reports (default: the profile's name).
    noise_floor : float, optional
        Use this noise floor instead of the estimates (:func:`~ffcomp.measure.noise.noise_floors`).

    Returns
    -------
    ValidationReport
    """
    if isinstance(profile_or_model, LpvModel):
        model, label = profile_or_model, name or "model"
    else:
        model, label = LpvModel.from_profile(profile_or_model), name or profile_or_model.name
    measurements = list(measurements)
    check_measurements(model, measurements)
    preds = BatchPredictor(measurements)(model)
    res = _resonances(model, measurements)
    scores = []
    nfs = noise_floors(measurements, override=noise_floor, predictions=preds)
    for m, Hp, (fd, fm), nf, src in zip(measurements, preds, res, nfs.values, nfs.sources):
        names, edges = band_edges(fd, fm)
        scores.append(MeasurementScore(
            label=m.label, path=m.path, kind=m.kind, input=m.input, output=m.output,
            position_mm=tuple(float(v) for v in m.position_mm), n_points=len(m.freq_hz),
            f_lo_hz=float(m.freq_hz[0]), f_hi_hz=float(m.freq_hz[-1]),
            r2_mag=r2_magnitude(m.H, Hp), r2_mag_db=r2_magnitude(m.H, Hp, db=True), r2_phase=r2_phase(m.H, Hp),
            residual=complex_residual(m.H, Hp, m.weights), noise=float(nf), noise_source=src,
            bands=_bands(m, Hp, names, edges)))
    return ValidationReport(label, tuple(scores), tuple(measurements), tuple(preds), nfs.source, nfs.note)


def compare(before: ValidationReport, after: ValidationReport) -> dict:
    """Side-by-side numbers of two reports on the same measurements (matched by label)."""
    b = {s.label: s for s in before.scores}
    rows = []
    for s in after.scores:
        if s.label in b:
            o = b[s.label]
            rows.append({"label": s.label, "axis": s.axis, "position_mm": list(s.position_mm),
                         "residual_before": o.residual, "residual_after": s.residual,
                         "r2_mag_before": o.r2_mag, "r2_mag_after": s.r2_mag,
                         "r2_phase_before": o.r2_phase, "r2_phase_after": s.r2_phase, "noise": s.noise})
    rows.sort(key=lambda r: -r["residual_before"])
    return {"before": before.profile, "after": after.profile,
            "mean_residual_before": before.mean_residual, "mean_residual_after": after.mean_residual,
            "mean_r2_mag_before": before.mean_r2_mag, "mean_r2_mag_after": after.mean_r2_mag,
            "mean_r2_phase_before": before.mean_r2_phase, "mean_r2_phase_after": after.mean_r2_phase,
            "noise_floor": after.noise_floor, "rows": rows}
