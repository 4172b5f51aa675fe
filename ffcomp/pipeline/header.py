"""The header and footer of a compensated G-code file: the firmware settings it must run with."""

from __future__ import annotations

import os

from .. import __version__

__all__ = ["header_accel", "header_lines"]


def header_accel(profile, opts) -> float:
    """The ACCEL the output sets (and the writer's timing assumes), mm/s^2."""
    return float(max(1e5, opts.accel_factor * profile.limits.max_accel_mm_s2))


def header_lines(profile, opts, src: str, accel: float) -> tuple[list[str], list[str]]:
    lim = profile.limits
    settings = (f"method={opts.method} tol_um={opts.tol_um:g} z_mode={opts.z_mode} "
                f"knots={opts.inverse.knot_samples / lim.sample_rate_hz * 1e3:g}ms "
                f"degree={opts.inverse.degree} sample_rate={lim.sample_rate_hz:g}Hz")
    head = [
        f"; ffcomp {__version__}: model-based feedforward vibration compensation (delta)",
        f"; source: {os.path.basename(src)}",
        f"; profile: {profile.name}",
        f"; settings: {settings}",
        "; The timing of every move below is baked in: run it with the firmware settings that follow",
        "; (limit and mode commands of the source are kept as '; ffcomp (baked in):' comments).",
    ]
    if lim.planner == "klipper":
        head += [
            f"; requires [printer] max_z_accel >= {profile.limits.max_z_accel_mm_s2:g} mm/s^2 and "
            f"max_z_velocity >= {profile.limits.max_z_velocity_mm_s:g} mm/s as in the profile",
            f"SET_VELOCITY_LIMIT ACCEL={accel:.0f} MINIMUM_CRUISE_RATIO=0 "
            f"SQUARE_CORNER_VELOCITY={opts.corner_velocity_mm_s:g}",
        ]
        foot = [f"SET_VELOCITY_LIMIT ACCEL={lim.max_accel_mm_s2:g} MINIMUM_CRUISE_RATIO={lim.minimum_cruise_ratio:g} "
                f"SQUARE_CORNER_VELOCITY={lim.square_corner_velocity_mm_s:g} ; ffcomp: restore the profile's limits"]
    else:
        head += [f"M204 P{accel:.0f} T{accel:.0f}", f"M201 X{accel:.0f} Y{accel:.0f} Z{accel:.0f}"]
        # restore every limit the header raised: M204 and M201 (Z: the profile's max_z_accel)
        foot = [f"M204 P{lim.max_accel_mm_s2:g} T{lim.max_accel_mm_s2:g} ; ffcomp: restore the profile's limits",
                f"M201 X{lim.max_accel_mm_s2:g} Y{lim.max_accel_mm_s2:g} Z{lim.max_z_accel_mm_s2:g} "
                "; ffcomp: restore the profile's limits"]
    head += ["G90 ; ffcomp: absolute positions (machine coordinates)", "M83 ; ffcomp: relative extrusion"]
    return head, foot
