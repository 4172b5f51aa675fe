"""Extra drive delay and first-order lag (step generation, driver, motor electrical time constant).

Physics
-------
Between the commanded position and the belt there is more than the paper's fitted electrical
filter ``(d1 s + d0) / (s^2 + d2 s + d0)``: the firmware's step queue and a fixed transport delay
(``delay_ms``), and the motor's electrical time constant ``L/R`` or a driver's current filter,
which act as a first-order lag (``lag_ms``).  Each tower's drive filter becomes

    F(s) = (d1 s + d0) / (s^2 + d2 s + d0) * exp(-s tau_d) / (1 + s tau_l)

set through :class:`~ffcomp.model.lpv.PoseMatrices` ``delay_s`` / ``lag_s``, the same for all
towers; :func:`~ffcomp.model.lpv.frequency_response` evaluates the delay exactly, the state space
uses a Pade approximant.

Signature in the FRFs
---------------------
A delay leaves every magnitude alone and adds a phase lag ``-360 f tau_d`` degrees that grows
linearly with frequency, the same at every pose and on every axis; a lag adds
``-atan(2 pi f tau_l)`` and lowers the magnitude by ``1 / sqrt(1 + (2 pi f tau_l)^2)`` above
``1 / (2 pi tau_l)``.

Parameters
----------
delay_ms : extra pure delay, ms.
lag_ms : first-order lag time constant, ms.
"""

from __future__ import annotations

import numpy as np

from . import Effect, Param, register

__all__ = ["DriveDelay"]


@register
class DriveDelay(Effect):
    """Extra delay and first-order lag of every drive (``delay_s``, ``lag_s``; see module)."""

    name = "drive_delay"
    summary = "extra drive delay exp(-s tau) and/or first-order lag 1/(1 + s tau) on every tower"
    params = {
        "delay_ms": Param(0.0, "ms", 0.0, 100.0, "extra pure delay of each drive", search=(0.0, 5.0)),
        "lag_ms": Param(0.0, "ms", 0.0, 100.0, "first-order lag time constant of each drive", search=(0.0, 5.0)),
    }
    fit = ("delay_ms", "lag_ms")
    evidence_keys = ("delay", "lag")

    def apply(self, mats, model):
        """Add ``delay_ms`` to ``delay_s`` and ``lag_ms`` to ``lag_s`` of every tower."""
        d, lag = self.values["delay_ms"] * 1e-3, self.values["lag_ms"] * 1e-3
        if d == 0 and lag == 0:
            return mats
        # two lags in series are not one lag; adding the time constants is the low-frequency equivalent
        return mats.replace(delay_s=mats.delay_s + d, lag_s=mats.lag_s + lag)

    def explain(self, model) -> str:
        """Delay and lag with the phase lag they add at 100 Hz."""
        d, lag = self.values["delay_ms"], self.values["lag_ms"]
        f = 100.0
        ph = 360 * f * d * 1e-3 + np.degrees(np.arctan(2 * np.pi * f * lag * 1e-3))
        parts = []
        if d > 1e-4:
            parts.append(f"extra delay {d:.3f} ms")
        if lag > 1e-4:
            parts.append(f"first-order lag {lag:.3f} ms (corner {1e3 / (2 * np.pi * lag):.0f} Hz)")
        if not parts:
            return "no extra delay or lag"
        return " and ".join(parts) + f": {ph:.1f} deg more phase lag at {f:g} Hz, on every axis and pose"
