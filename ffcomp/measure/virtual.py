"""Virtual measurements: FRFs of the LPV model with hidden effects, with complex noise and coherence.

The plan mirrors a validation campaign on a real printer:

* the paper's two identification sweeps at the bed centre: carriage A alone (``kind: carriage``,
  ``qA -> qA``) and the assembled vertical sweep ``z -> qA`` (Section IV-A);
* ``x -> x``, ``y -> y`` and ``z -> z`` sweeps at the centre, ``+-offset`` on x and y, two
  diagonal points, each at two heights (Table II, extended).

Noise is :func:`~ffcomp.measure.synthetic.add_complex_noise`: ``H (1 + rel n)``, coherence
``1 / (1 + rel^2)``.  The hidden effects are not written into the files (use ``truth`` for that).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kinematics import reachable
from ..model.lpv import LpvModel
from .frf_file import FrfMeasurement
from .predict import BatchPredictor
from .synthetic import add_complex_noise

__all__ = ["PlanItem", "measurement_plan", "virtual_measurements", "file_name"]


@dataclass(frozen=True)
class PlanItem:
    """One sweep: ``kind``, nozzle position (mm), commanded input, measured output."""

    kind: str
    position_mm: tuple
    input: str
    output: str


def measurement_plan(profile, *, offset_mm: float | None = None, heights_mm=(30.0, 130.0),
                     axes=("x", "y", "z"), all_carriages: bool = False) -> list[PlanItem]:
    """The default sweep plan for ``profile`` (unreachable poses are dropped).

    Parameters
    ----------
    offset_mm : float, optional
        Lateral offset of the off-centre poses, mm (default ``min(100, 0.75 print radius)``).
    heights_mm : sequence of float
        Nozzle heights of the task-space sweeps, mm (clipped into the profile's z range).
    all_carriages : bool
        Also the carriage sweeps of towers B and C (``qB -> qB``, ``qC -> qC``, effector detached),
        appended at the end (what ``ffcomp identify --sweep`` uses against unequal towers).
    """
    g = profile.geometry
    off = min(100.0, 0.75 * g.print_radius_mm) if offset_mm is None else float(offset_mm)
    d = off / np.sqrt(2.0)
    xy = [(0.0, 0.0), (off, 0.0), (-off, 0.0), (0.0, off), (0.0, -off), (d, d), (-d, -d)]
    z_id = float(np.clip(30.0, g.z_min_mm, g.z_max_mm))
    plan = [PlanItem("carriage", (0.0, 0.0, z_id), "qA", "qA"), PlanItem("assembled", (0.0, 0.0, z_id), "z", "qA")]
    geo = profile.geometry_si()
    for z in heights_mm:
        z = float(np.clip(z, g.z_min_mm, g.z_max_mm))
        for x, y in xy:
            x, y = round(x, 1), round(y, 1)
            if not reachable(geo, np.array([[x, y, z]]) * 1e-3)[0]:
                continue
            plan += [PlanItem("assembled", (x, y, z), a, a) for a in axes]
    if all_carriages:
        plan += [PlanItem("carriage", (0.0, 0.0, z_id), q, q) for q in ("qB", "qC")]
    return plan


def file_name(i: int, item: PlanItem) -> str:
    """File name of the ``i``-th sweep, e.g. ``05_assembled_x-x_x+100_y+0_z30.csv``."""
    x, y, z = item.position_mm
    return f"{i:02d}_{item.kind}_{item.input}-{item.output}_x{x:+.0f}_y{y:+.0f}_z{z:.0f}.csv"


def virtual_measurements(profile, effects=(), *, freq_hz=None, noise: float = 0.02, seed: int = 0,
                         plan=None, source: str | None = None, averages: int | None = None,
                         averages_key: bool = True) -> list[FrfMeasurement]:
    """Measurements of ``profile`` with ``effects`` (profile ``[[effects]]``-style dicts) added.

    Parameters
    ----------
    profile : PrinterProfile
        The printer; its own effects are kept and ``effects`` are appended.
    effects : sequence of dict
        Hidden effects, ``{"name": ..., param: value}``.
    freq_hz : array_like, optional
        Frequencies, Hz (default 250 log-spaced from 5 to 400 Hz).
    noise : float
        Relative complex noise ``rel`` (0.02 = 2 %).
    seed : int
        Random seed (deterministic output).
    averages : int, optional
        Write the coherence an H1 estimate from ``averages`` averages would have for this noise,
        ``1 / (1 + averages rel^2)`` (default: ``1 / (1 + rel^2)``, i.e. one average).
    averages_key : bool
        Write the ``averages`` header key (when ``averages`` is given).  ``False`` mimics a file
        whose coherence was computed from several averages without saying how many.

    Returns
    -------
    list of FrfMeasurement, in plan order.
    """
    f = np.geomspace(5.0, 400.0, 250) if freq_hz is None else np.asarray(freq_hz, float)
    hidden = profile.with_(effects=tuple(profile.effects) + tuple(dict(e) for e in effects))
    model = LpvModel.from_profile(hidden)
    plan = measurement_plan(profile) if plan is None else list(plan)
    rng = np.random.default_rng(seed)
    src = source or f"ffcomp virtual-measure (LPV model), {noise * 100:g}% complex noise, seed {seed}"
    stubs = [FrfMeasurement(f, np.zeros_like(f, complex), None, it.kind, np.asarray(it.position_mm, float),
                            it.input, it.output, src) for it in plan]
    out = []
    n_avg = 1 if averages is None else int(averages)
    if n_avg < 1:
        raise ValueError(f"averages must be >= 1, got {averages!r}")
    meta = {"averages": str(n_avg)} if averages is not None and averages_key else {}
    for m, H in zip(stubs, BatchPredictor(stubs)(model)):
        if noise > 0:
            Hn, _ = add_complex_noise(H, noise, rng)
            coh = np.full(np.shape(H), 1.0 / (1.0 + n_avg * noise**2))
        else:
            Hn, coh = H, np.ones_like(f)
        out.append(FrfMeasurement(f, Hn, coh, m.kind, m.position_mm, m.input, m.output, src, meta=dict(meta)))
    return out
