"""Geometry and frame as suspects: delta radius, arm length and tower-angle frame as fit entries.

A wrong geometry bends every prediction off the centre and looks like a physical effect (a wrong
delta radius is blamed on ``tower_scale``).  :mod:`ffcomp.loop.diagnose` therefore also tries

* ``delta_radius_mm`` and ``arm_length_mm`` (tower means; per-tower differences kept) as fitted
  parameters within +-15 % of the profile's, with the base dynamics refitted alongside;
* the tower-angle frame: the profile's tower angles rotated by multiples of 30 deg (the firmware
  frame, tower A at 210 deg, is the paper's rotated by 210 deg), scored without fitting.

The entry ``{"name": "geometry", "delta_radius_mm": .., "arm_length_mm": .., "rotation_deg": ..}``
acts on the model's :class:`~ffcomp.kinematics.DeltaGeometry`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..model.effects import Param

__all__ = ["GEOM", "geometry_spec", "geometry_table", "apply_geometry", "profile_geometry_change"]

GEOM = "geometry"


def _radius_angles(geo):
    xy = np.asarray(geo.tower_xy_m, float)
    return np.hypot(xy[:, 0], xy[:, 1]), np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))


def geometry_spec(model) -> dict:
    """The model's geometry as a fit entry (means, mm; rotation 0)."""
    r, _ = _radius_angles(model.geometry)
    return {"name": GEOM, "delta_radius_mm": float(np.mean(r)) * 1e3,
            "arm_length_mm": float(np.mean(model.geometry.arm_length_m)) * 1e3, "rotation_deg": 0.0}


def geometry_table(spec: dict) -> dict[str, Param]:
    """Fit ranges: +-15 % around the starting radius and arm length; rotation -180..180 deg."""
    R, L = spec["delta_radius_mm"], spec["arm_length_mm"]
    return {"delta_radius_mm": Param(R, "mm", 0.85 * R, 1.15 * R, "delta radius (tower mean)",
                                     search=(0.85 * R, 1.15 * R)),
            "arm_length_mm": Param(L, "mm", 0.85 * L, 1.15 * L, "arm length (tower mean)",
                                   search=(0.85 * L, 1.15 * L)),
            "rotation_deg": Param(0.0, "deg", -180.0, 180.0, "rotation of the tower angles", search=(-180.0, 180.0))}


def apply_geometry(model, spec: dict, ref: dict | None = None):
    """``model`` with the geometry of ``spec`` (relative to ``ref``, default the model's own)."""
    ref = ref or geometry_spec(model)
    geo = model.geometry
    r, ang = _radius_angles(geo)
    r = r * (spec["delta_radius_mm"] / ref["delta_radius_mm"])
    ang = np.radians(ang + spec["rotation_deg"] - ref["rotation_deg"])
    xy = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
    arms = np.asarray(geo.arm_length_m, float) * (spec["arm_length_mm"] / ref["arm_length_mm"])
    return replace(model, geometry=replace(geo, tower_xy_m=xy, arm_length_m=arms))


def profile_geometry_change(profile, key: str, value: float) -> tuple[str, str]:
    """``(profile set command argument, words)`` for a geometry change of ``profile``."""
    g = profile.geometry
    if key == "rotation_deg":
        new = [float((a + value) % 360.0) for a in g.tower_angles_deg]
        txt = "/".join(f"{a:g}" for a in new)
        frame = (" (the paper frame: tower A on +x)" if np.allclose(new, [0, 120, 240], atol=1e-6) else
                 " (the firmware frame: tower A at 210 deg)" if np.allclose(new, [210, 330, 90], atol=1e-6) else "")
        return (f"geometry.tower_angles_deg={','.join(f'{a:g}' for a in new)}",
                f"the data fit the tower angles {txt} deg{frame}, the profile's "
                f"{'/'.join(f'{a:g}' for a in g.tower_angles_deg)} rotated by {value:g} deg")
    cur = float(np.mean(getattr(g, key)))
    name = {"delta_radius_mm": "delta radius", "arm_length_mm": "arm length"}[key]
    return (f"geometry.{key}={value:.1f}", f"{name} {value:.1f} mm fits better than the profile's {cur:g} mm")
