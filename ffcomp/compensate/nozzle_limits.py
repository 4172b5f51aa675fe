"""What Klipper's delta rule bounds, in terms of the carriages' accelerations.

Klipper caps a segment's acceleration at ``max_z_accel * d/|dz|``.  The streaming inverse keeps its
command within that cap where the reference comes near it: :func:`nozzle_components` maps the
carriages' accelerations to the nozzle's along and across the path with their limits, and
:func:`nozzle_z_accel` says where the reference's own z acceleration is (where the bound applies).
"""

from __future__ import annotations

import numpy as np

from ..kinematics import jacobian
from ..linalg3 import cross3

__all__ = ["nozzle_components", "nozzle_z_accel"]


def nozzle_components(geom, xyz_m: np.ndarray, qd: np.ndarray, qdd: np.ndarray, z_limit: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """What Klipper's delta rule bounds, per sample, in terms of the carriages' accelerations.

    Klipper caps a segment's acceleration at ``a_seg = max_z_accel * d/|dz| = z_limit / |u_z|``
    for the path direction ``u``: along the path the nozzle accelerates at most ``a_seg``; across
    it, the junction rule (the centripetal ``v^2 <= d a tan(theta/2) / 2`` of short segments)
    keeps the turning acceleration within ``a_seg`` too.  To first order the nozzle's acceleration
    is ``J q''`` (``J = dX/dq``); the components are taken along and across the reference's
    direction (the command's differs from it by the small correction).

    Parameters
    ----------
    geom : DeltaGeometry
    xyz_m : (N, 3) reference nozzle positions, m
    qd, qdd : (N, 3) reference carriage velocities (m/s) and accelerations (m/s^2)
    z_limit : float
        max_z_accel, m/s^2.

    Returns
    -------
    M : (N, 3, 3) rows mapping carriage accelerations to the nozzle's acceleration along the path
        and across it (two normals)
    L : (N, 3) their limits, m/s^2: ``z_limit / |u_z|``, at most 1000 m/s^2
    """
    n = len(xyz_m)
    if n == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    J = jacobian(geom, xyz_m)
    v = np.einsum("nij,nj->ni", J, qd)
    acc = np.einsum("nij,nj->ni", J, qdd)
    sp_ = np.linalg.norm(v, axis=1)
    am = np.linalg.norm(acc, axis=1)
    # the path direction: the velocity's, at rest the acceleration's, else z
    u = np.where((sp_ > 2e-3)[:, None], v / np.maximum(sp_, 1e-300)[:, None],
                 np.where((am > 0.05)[:, None], acc / np.maximum(am, 1e-300)[:, None], [0.0, 0.0, 1.0]))
    e = np.where((np.abs(u[:, 2]) < 0.9)[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    n1 = cross3(u, e)
    n1 /= np.linalg.norm(n1, axis=1)[:, None]
    n2 = cross3(u, n1)
    a_seg = np.minimum(z_limit / np.maximum(np.abs(u[:, 2]), 1e-9), 1000.0)
    M = np.einsum("nki,nij->nkj", np.stack([u, n1, n2], axis=1), J)
    L = np.repeat(a_seg[:, None], 3, axis=1)
    return M, L


def nozzle_z_accel(geom, xyz_m: np.ndarray, qdd: np.ndarray, stride: int = 8) -> np.ndarray:
    """The nozzle's z acceleration (m/s^2) from the carriages' ``qdd`` (N, 3) at the poses
    ``xyz_m`` (N, 3), m: ``sum_i w_i q_i''`` with ``w`` the z row of ``J = dX/dq``, taken every
    ``stride`` samples (it changes slowly with the pose; this only decides where the z bound
    applies)."""
    n = len(xyz_m)
    if n == 0:
        return np.zeros(0)
    w = np.repeat(jacobian(geom, xyz_m[::stride])[:, 2, :], stride, axis=0)[:n]
    return np.einsum("ni,ni->n", w, qdd)
