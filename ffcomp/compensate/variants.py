"""Bench rows for the simulator (:data:`ffcomp.sim.bench.VARIANTS`): the compensation variants.

Imported by :func:`ffcomp.sim.bench.load_providers`; each row maps a planned trajectory to carriage
commands with :func:`ffcomp.compensate.inverse.invert`.
"""

from __future__ import annotations

import numpy as np

from ..model.lpv import LpvModel
from ..sim.bench import register_variant
from .inverse import FINE, InverseConfig, invert
from .limit import limit_for_profile

__all__ = ["compensate_rows"]


def _row(method: str, cfg: InverseConfig | None = None):
    def fn(profile, t_s, xyz_ref_m, q_ref_m):
        model = LpvModel.from_profile(profile)
        dt = float(np.median(np.diff(t_s)))
        return invert(model, np.asarray(q_ref_m, float), np.asarray(xyz_ref_m, float), dt,
                      cfg or InverseConfig(method=method)).q_cmd

    fn.__doc__ = f"Feedforward compensation, inverse variant {method!r}."
    return fn


def compensate_rows() -> dict:
    """The rows this module registers: name -> inverse method."""
    return {"lti-centre": "lti-centre", "lpv": "lpv"}


for _name, _method in compensate_rows().items():
    register_variant(_name, _row(_method))

#: the accuracy setting (cubic spline, a knot per sample; :data:`~ffcomp.compensate.inverse.FINE`)
register_variant("lpv-fine", _row("lpv", FINE))
#: the physical limit of the model (:mod:`ffcomp.compensate.limit`); every table compares with it
register_variant("limit", limit_for_profile)
