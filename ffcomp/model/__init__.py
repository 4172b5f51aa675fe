"""The printer's dynamic model: sub-models, receptance-coupled LPV model, modes, effects."""

from .lpv import FRAMES, LpvModel, PoseMatrices, frequency_response, state_space, state_space_arrays
from .submodels import CarriageParams, carriage_tf, derived_modal

__all__ = [
    "FRAMES",
    "LpvModel",
    "PoseMatrices",
    "frequency_response",
    "state_space",
    "state_space_arrays",
    "CarriageParams",
    "carriage_tf",
    "derived_modal",
]
