"""The compensation honours the profile's physical effects (they act on the same pose matrices)."""

from dataclasses import replace

import numpy as np
import pytest
from trajectories import square, trapezoid_path

from ffcomp.compensate.inverse import invert
from ffcomp.compensate.predict import predict_lpv
from ffcomp.kinematics import inverse, jacobian
from ffcomp.model import LpvModel

EFFECTS = [
    {"name": "belt_span", "l1_ref_mm": 320, "loop_mm": 1300},
    {"name": "tower_scale", "k_scale_B": 0.8},
    {"name": "forearm_inertia", "scale": 1.0},
    {"name": "frame_coupling", "coupling": 0.05},
    {"name": "drive_delay", "delay_ms": 0.6},
]


@pytest.mark.parametrize("effect", EFFECTS, ids=[e["name"] for e in EFFECTS])
def test_effect_aware_compensation(profile, effect):
    with_eff = LpvModel.from_profile(replace(profile, effects=(effect,)))
    base = LpvModel.from_profile(profile)
    X = trapezoid_path(square(80, 0, side=40, z=60))
    q = inverse(with_eff.geometry, X)
    J = jacobian(with_eff.geometry, X)

    def rms(q_cmd):  # judged by the model WITH the effect
        e = np.einsum("nij,nj->ni", J, predict_lpv(with_eff, q_cmd, X, 1e-3) - q)
        return float(np.sqrt(np.mean(np.sum(e**2, 1)))) * 1e6

    none, aware, blind = rms(q), rms(invert(with_eff, q, X, 1e-3).q_cmd), rms(invert(base, q, X, 1e-3).q_cmd)
    assert aware < 0.02 * none, (none, aware)
    assert aware <= blind + 0.05, (aware, blind)
