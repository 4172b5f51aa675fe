"""Model flow: profile -> LPV model -> responses, modes, summaries (plain objects for the CLI)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.lpv import AXES, LpvModel, frequency_response
from ..model.modes import ModalSummary, drive_modes, modes, workspace_grid
from ..model.submodels import derived_modal

__all__ = ["ModelFrf", "model_frf", "model_modes", "model_summary", "frame_for", "COORDS"]

COORDS = tuple(AXES)
_TASK = ("x", "y", "z")


def frame_for(input_: str, output: str) -> str:
    """Response frame for an input/output coordinate pair (``x,y,z`` task; ``qA,qB,qC`` joint)."""
    for name, v in (("input", input_), ("output", output)):
        if v not in AXES:
            raise ValueError(f"{name} must be one of {', '.join(AXES)}, got {v!r}")
    tin, tout = input_ in _TASK, output in _TASK
    return {(True, True): "task", (False, False): "joint", (True, False): "task_to_joint",
            (False, True): "joint_to_task"}[(tin, tout)]


@dataclass(frozen=True)
class ModelFrf:
    """Predicted FRF at one pose: ``H`` shape (F,), complex, output per unit commanded input."""

    position_mm: np.ndarray
    input: str
    output: str
    freq_hz: np.ndarray
    H: np.ndarray

    def peaks(self, n: int = 4) -> list[tuple[float, float]]:
        """Local maxima of |H| as (freq_hz, magnitude), largest first."""
        a = np.abs(self.H)
        idx = [i for i in range(1, len(a) - 1) if a[i] >= a[i - 1] and a[i] > a[i + 1]]
        idx.sort(key=lambda i: -a[i])
        return [(float(self.freq_hz[i]), float(a[i])) for i in idx[:n]]

    def to_dict(self) -> dict:
        return {
            "position_mm": self.position_mm.tolist(), "input": self.input, "output": self.output,
            "freq_hz": self.freq_hz.tolist(), "real": self.H.real.tolist(), "imag": self.H.imag.tolist(),
            "magnitude": np.abs(self.H).tolist(), "phase_deg": np.rad2deg(np.angle(self.H)).tolist(),
            "peaks": [{"freq_hz": f, "magnitude": m} for f, m in self.peaks()],
        }


def model_frf(profile, at_mm, input_: str, output: str, freq_hz) -> ModelFrf:
    """Model FRF from ``input_`` to ``output`` at ``at_mm`` (x, y, z in mm)."""
    model = LpvModel.from_profile(profile)
    pos = np.asarray(at_mm, float)
    H = frequency_response(model, pos[None] * 1e-3, freq_hz, frame=frame_for(input_, output))
    return ModelFrf(pos, input_, output, np.asarray(freq_hz, float), H[0, AXES[output], AXES[input_]])


def model_modes(profile, poses_mm) -> ModalSummary:
    """Coupled modes at poses given in mm."""
    model = LpvModel.from_profile(profile)
    return modes(model, np.atleast_2d(np.asarray(poses_mm, float)) * 1e-3)


def mode_map(profile, z_mm: float = 30.0, step_mm: float = 10.0) -> ModalSummary:
    """Coupled modes on a grid over the print disc at height ``z_mm``."""
    model = LpvModel.from_profile(profile)
    return modes(model, workspace_grid(model.geometry, z_mm * 1e-3, step_mm * 1e-3))


def model_summary(profile) -> dict:
    """Everything ``ffcomp model show`` prints, as plain data."""
    model = LpvModel.from_profile(profile)
    dyn = profile.dynamics
    per = {n: list(getattr(dyn, n)) for n in ("m", "c", "b", "k", "d0", "d1", "d2")}
    derived = [derived_modal(dyn.m[i], dyn.c[i], dyn.b[i], dyn.k[i], dyn.m_nt, dyn.b_nt) for i in range(3)]
    centre = modes(model, np.array([[0.0, 0.0, max(profile.geometry.z_min_mm, 30.0) * 1e-3]]))
    return {
        "name": profile.name,
        "source": profile.source,
        "geometry": profile.to_dict()["geometry"],
        "limits": profile.to_dict()["limits"],
        "dynamics": {**per, "m_n": dyn.m_n, "m_f": dyn.m_f, "b_nt": dyn.b_nt, "m_nt": dyn.m_nt},
        "derived": [
            {"tower": "ABC"[i], "w_n_rad_s": d["w_n"], "f_n_hz": d["w_n"] / (2 * np.pi), "zeta": d["zeta"],
             "w_n_loaded_rad_s": d["w_n_p"], "f_n_loaded_hz": d["w_n_p"] / (2 * np.pi), "zeta_loaded": d["zeta_p"]}
            for i, d in enumerate(derived)
        ],
        "drive": [dm.__dict__ for dm in drive_modes(model)],
        "centre_modes": centre.to_dict()["poses"][0],
        "effects": [dict(e) for e in profile.effects],
    }
