"""Example effect plug-in: a compliant motor mount (an extra lightly damped mode in every drive).

A user who finds (``ffcomp diagnose``) an unexplained resonance near 250 Hz at every pose and in
the carriage sweep can describe it here and fit it, without editing ffcomp::

    ffcomp fit DATA --profile printer.toml --plugin docs/effects_example_motor_mount.py \\
        --add motor_mount -o printer_mm.toml

The fitted profile keeps ``plugin = "/abs/path/docs/effects_example_motor_mount.py"`` in its
``[[effects]]`` entry, so every later command (validate, compensate, simulate) loads it again.  A plug-in may also
be an installed module: ``plugin = "mypackage.effects"``.

Physics
-------
The motor sits on a compliant mount (rubber dampers, a flexible printed bracket).  Its housing,
with the mount's stiffness and the motor's inertia, forms a lightly damped mode between the
commanded rotor position and the belt.  Seen from the belt, the drive gains a pole pair at the
mount's resonance ``f_hz`` and a zero pair below it (the anti-resonance where the mount and the
belt load balance):

    F_mount(s) = (1 + mu) (s^2 + 2 zeta_zero wz s + wz^2) / (s^2 + 2 zeta wp s + wp^2),
    wp = 2 pi f_hz,  wz = wp / sqrt(1 + mu),

unit gain at low frequency (the mount does not lose steps), ``1 + mu`` far above the mode.  With
``mu < 0`` the zero pair lies above the pole pair (a mode seen through a stiffer path first).  It acts
on every tower, at every pose, and in the carriage sweep too (effector detached): the signature
that no effect of the library has.

Limitation: ``drive_tf`` is honoured by the LPV frequency response and state space (validate,
diagnose, fit, virtual-measure), not yet by the nonlinear simulator or the compensation kernels.

The interface
-------------
Subclass :class:`ffcomp.model.effects.Effect`, give it a ``name``, its ``params``
(:class:`~ffcomp.model.effects.Param`: default, unit, admissible range, meaning, ``search`` = the
range a fit starts from and is bounded by), implement ``apply(mats, model)`` returning modified
:class:`~ffcomp.model.lpv.PoseMatrices` (``M, C, K, B_c, B_k`` per pose, drive ``d0, d1, d2``,
``delay_s``, ``lag_s``, ``drive_tf``: extra transfer functions in series with every drive), and
register it with ``@register``.  Optional: ``fit`` (parameters fitted by default), ``explain``.
"""

from __future__ import annotations

import numpy as np

from ffcomp.model.effects import Effect, Param, register


@register
class MotorMount(Effect):
    """Compliant motor mount: a pole/zero pair in series with every drive (see the module)."""

    name = "motor_mount"
    summary = "compliant motor mount: an extra lightly damped mode in every drive (plug-in example)"
    params = {
        "f_hz": Param(200.0, "Hz", 1.0, 5000.0, "mount resonance", search=(120.0, 400.0)),
        "zeta": Param(0.05, "", 0.001, 1.0, "damping ratio of the mount mode", search=(0.005, 0.2)),
        "mu": Param(0.3, "", -0.9, 10.0, "mount compliance ratio (high-frequency gain 1 + mu)", search=(-0.5, 1.5)),
        "zeta_zero": Param(0.05, "", 0.001, 1.0, "damping ratio of the anti-resonance", search=(0.005, 0.2)),
    }

    def apply(self, mats, model):
        """Append ``F_mount`` to the drives' extra transfer functions."""
        wp = 2.0 * np.pi * self.values["f_hz"]
        mu, z, zz = self.values["mu"], self.values["zeta"], self.values["zeta_zero"]
        if mu == 0.0 and z == zz:
            return mats
        wz = wp / np.sqrt(1.0 + mu)
        num = (1.0 + mu) * np.array([1.0, 2.0 * zz * wz, wz**2])
        den = np.array([1.0, 2.0 * z * wp, wp**2])
        return mats.replace(drive_tf=tuple(mats.drive_tf) + ((num, den),))

    def explain(self, model) -> str:
        v = self.values
        return (f"motor mount mode at {v['f_hz']:.1f} Hz (damping {v['zeta']:.3f}, anti-resonance "
                f"{v['f_hz'] / np.sqrt(1 + v['mu']):.1f} Hz): in every drive, at every pose and in the carriage sweep")
