"""Delta kinematics: inverse, forward, Jacobian J and its time derivative, all vectorised.

Pure numpy kernel, SI units (metres).  Conventions follow the paper (Eqs. 3-13):

* task space ``X = (x, y, z)``: the nozzle tip, origin at the bed centre;
* joint space ``q = (q_A, q_B, q_C)``: carriage heights;
* tower ``i`` has its (effective) carriage joint line at ``(i_x, i_y)``; the forearm joint plane of
  the effector lies ``H_ez`` above the nozzle tip, so the constraint reads
  ``(x - i_x)^2 + (y - i_y)^2 + (z + H_ez - q_i)^2 = L_i^2`` (Eqs. 3-5);
* ``J = dX/dq`` (Eq. 12), so ``X_dot = J q_dot``;
* ``J_dot = -S^-1 (S_dot J + K)`` (Eq. 13 with the sign the paper drops).

Arrays of poses have shape ``(N, 3)``; Jacobians ``(N, 3, 3)``.  Arm lengths and tower positions
are per tower, so a printer with unequal arms is described exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import KinematicsError
from .linalg3 import cross3, inv3, matvec3, sq_norm3

__all__ = [
    "DeltaGeometry",
    "inverse",
    "forward",
    "jacobian",
    "jacobian_dot",
    "carriage_rates",
    "velocity_product",
    "joint_velocity",
    "reachable",
    "check_reachable",
    "condition_number",
]


@dataclass(frozen=True)
class DeltaGeometry:
    """Delta geometry in SI units.

    Attributes
    ----------
    arm_length_m : ndarray, shape (3,)
        Forearm (diagonal rod) length ``L_i`` of each tower, m.
    tower_xy_m : ndarray, shape (3, 2)
        Horizontal position of each carriage's effective joint line, m (delta radius already
        reduced by the effector and carriage offsets, as Klipper's ``delta_radius``).
    effector_offset_z_m : float
        ``H_ez``: height of the effector's forearm-joint plane above the nozzle tip, m.
    print_radius_m : float
        Radius of the printable disc, m.
    z_min_m, z_max_m : float
        Printable height range of the nozzle tip, m.
    min_arm_angle_deg : float
        Smallest forearm angle above horizontal that counts as reachable (degrees); Klipper
        slows moves far out for the same reason: J blows up as arms flatten.
    """

    arm_length_m: np.ndarray
    tower_xy_m: np.ndarray
    effector_offset_z_m: float = 0.0
    print_radius_m: float = 0.1
    z_min_m: float = 0.0
    z_max_m: float = 0.3
    min_arm_angle_deg: float = 15.0

    @classmethod
    def from_radius(
        cls,
        arm_length_m,
        delta_radius_m,
        tower_angles_deg=(0.0, 120.0, 240.0),
        **kw,
    ) -> "DeltaGeometry":
        """Build from delta radius and tower angles (scalars broadcast to all towers)."""
        L = np.broadcast_to(np.asarray(arm_length_m, float), (3,)).copy()
        R = np.broadcast_to(np.asarray(delta_radius_m, float), (3,))
        ang = np.deg2rad(np.broadcast_to(np.asarray(tower_angles_deg, float), (3,)))
        xy = np.stack([R * np.cos(ang), R * np.sin(ang)], axis=1)
        return cls(arm_length_m=L, tower_xy_m=xy, **kw)

    @property
    def delta_radius_m(self) -> np.ndarray:
        return np.hypot(self.tower_xy_m[:, 0], self.tower_xy_m[:, 1])

    @property
    def tower_angles_deg(self) -> np.ndarray:
        return np.rad2deg(np.arctan2(self.tower_xy_m[:, 1], self.tower_xy_m[:, 0])) % 360.0


def _as_poses(a) -> tuple[np.ndarray, bool]:
    a = np.asarray(a, dtype=float)
    single = a.ndim == 1
    a = np.atleast_2d(a)
    if a.shape[-1] != 3:
        raise ValueError(f"poses must have shape (N, 3) or (3,), got {a.shape}")
    return a, single


def arm_heights(geom: DeltaGeometry, xyz) -> np.ndarray:
    """Vertical extent ``h_i = q_i - z - H_ez`` of each forearm, shape (N, 3); NaN where unreachable.

    Tower by tower on the poses' columns (1-D passes: broadcasting over the short axes of (N, 3)
    is several times slower on long stacks)."""
    xyz, _ = _as_poses(xyz)
    L2 = geom.arm_length_m ** 2
    t = geom.tower_xy_m
    x, y = xyz[:, 0], xyz[:, 1]
    h = np.empty((xyz.shape[0], 3))
    with np.errstate(invalid="ignore"):
        for i in range(3):
            dx = x - t[i, 0]
            dy = y - t[i, 1]
            h2 = L2[i] - (dx * dx + dy * dy)  # arm length^2 - squared horizontal distance to tower i
            ok = h2 > 0
            h[:, i] = np.where(ok, np.sqrt(np.where(ok, h2, 0.0)), np.nan)
    return h


def inverse(geom: DeltaGeometry, xyz) -> np.ndarray:
    """Carriage heights for nozzle positions.

    Parameters
    ----------
    geom : DeltaGeometry
    xyz : array_like, shape (N, 3) or (3,)
        Nozzle positions, m.

    Returns
    -------
    q : ndarray, shape (N, 3) or (3,)
        Carriage heights, m.  NaN where a forearm cannot reach (use :func:`check_reachable`).
    """
    xyz_a, single = _as_poses(xyz)
    h = arm_heights(geom, xyz_a)
    zo = xyz_a[:, 2] + geom.effector_offset_z_m
    for i in range(3):
        h[:, i] = zo + h[:, i]  # q_i = (z + H_ez) + h_i, in place
    return h[0] if single else h


def forward(geom: DeltaGeometry, q) -> np.ndarray:
    """Nozzle positions for carriage heights, by trilateration (the lower intersection).

    Parameters
    ----------
    q : array_like, shape (N, 3) or (3,)
        Carriage heights, m.

    Returns
    -------
    xyz : ndarray, same shape as ``q``
        Nozzle positions, m.  NaN where the three spheres do not intersect.
    """
    q_a, single = _as_poses(q)
    n = q_a.shape[0]
    # sphere centres (the carriage joints, shifted down by H_ez so the answer is the nozzle tip)
    P = np.empty((n, 3, 3))
    P[:, :, :2] = geom.tower_xy_m[None]
    P[:, :, 2] = q_a - geom.effector_offset_z_m
    L = geom.arm_length_m
    p1, p2, p3 = P[:, 0], P[:, 1], P[:, 2]
    ex = p2 - p1
    d = np.linalg.norm(ex, axis=1)
    ex /= d[:, None]
    t = p3 - p1
    i = np.einsum("ni,ni->n", ex, t)
    ey = t - i[:, None] * ex
    j = np.linalg.norm(ey, axis=1)
    ey /= j[:, None]
    ez = cross3(ex, ey)
    xs = (L[0] ** 2 - L[1] ** 2 + d**2) / (2 * d)
    ys = (L[0] ** 2 - L[2] ** 2 + i**2 + j**2 - 2 * i * xs) / (2 * j)
    z2 = L[0] ** 2 - xs**2 - ys**2
    with np.errstate(invalid="ignore"):
        zs = np.where(z2 >= 0, np.sqrt(np.where(z2 >= 0, z2, 0.0)), np.nan)
    base = p1 + xs[:, None] * ex + ys[:, None] * ey
    # pick the intersection below the carriages (nozzle hangs under the joints)
    sgn = np.where(ez[:, 2] > 0, -1.0, 1.0)
    out = base + (sgn * zs)[:, None] * ez
    return out[0] if single else out


def _s_matrix(geom: DeltaGeometry, xyz: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rows ``s_i^T`` of Eq. 7, shape (N, 3, 3)."""
    S = np.empty((xyz.shape[0], 3, 3))
    t = geom.tower_xy_m
    x, y = xyz[:, 0], xyz[:, 1]
    zo = xyz[:, 2] + geom.effector_offset_z_m
    for i in range(3):  # tower by tower on 1-D columns (faster than broadcasting over (N, 3))
        S[:, i, 0] = x - t[i, 0]
        S[:, i, 1] = y - t[i, 1]
        S[:, i, 2] = zo - q[:, i]
    return S


def jacobian(geom: DeltaGeometry, xyz, *, q=None) -> np.ndarray:
    """Jacobian ``J = dX/dq`` at nozzle positions (Eq. 12); ``q``, the carriage heights there, may
    be passed when known.

    Returns
    -------
    J : ndarray, shape (N, 3, 3) or (3, 3)
        Dimensionless.
    """
    xyz_a, single = _as_poses(xyz)
    q = inverse(geom, xyz_a) if q is None else np.atleast_2d(q)
    S = _s_matrix(geom, xyz_a, q)
    J = inv3(S)
    for j in range(3):  # J = -S^-1 diag(h), column by column
        h = q[:, j] - xyz_a[:, 2] - geom.effector_offset_z_m  # = s_j^T p with p = (0, 0, -1)
        for i in range(3):
            J[:, i, j] = -J[:, i, j] * h
    return J[0] if single else J


def joint_velocity(geom: DeltaGeometry, xyz, xyz_dot) -> np.ndarray:
    """Carriage velocities ``q_dot = J^-1 X_dot``, shape like ``xyz_dot``."""
    xyz_a, single = _as_poses(xyz)
    v = np.atleast_2d(np.asarray(xyz_dot, float))
    J = jacobian(geom, xyz_a)
    qd = np.einsum("nij,nj->ni", inv3(J), v)
    return qd[0] if single else qd


def jacobian_dot(geom: DeltaGeometry, xyz, xyz_dot) -> np.ndarray:
    """Time derivative of J along a motion, ``J_dot = -S^-1 (S_dot J + K)`` (Eq. 13, sign fixed).

    Parameters
    ----------
    xyz : array_like, shape (N, 3)
        Nozzle positions, m.
    xyz_dot : array_like, shape (N, 3)
        Nozzle velocities, m/s.

    Returns
    -------
    J_dot : ndarray, shape (N, 3, 3), 1/s.
    """
    xyz_a, single = _as_poses(xyz)
    v = np.atleast_2d(np.asarray(xyz_dot, float))
    q = inverse(geom, xyz_a)
    S = _s_matrix(geom, xyz_a, q)
    h = q - xyz_a[:, 2:3] - geom.effector_offset_z_m
    Sinv = inv3(S)
    J = -Sinv * h[:, None, :]
    qd = np.einsum("nij,nj->ni", inv3(J), v)
    # s_i_dot = X_dot + p q_i_dot, p = (0, 0, -1)
    Sd = np.repeat(v[:, None, :], 3, axis=1)
    Sd[:, :, 2] -= qd
    K = -Sd[:, :, 2]  # s_i_dot^T p
    rhs = Sd @ J + K[:, :, None] * np.eye(3)[None]
    Jd = -Sinv @ rhs
    return Jd[0] if single else Jd


def carriage_rates(geom: DeltaGeometry, xyz, xyz_dot, xyz_ddot) -> tuple[np.ndarray, np.ndarray]:
    """Carriage velocities and accelerations of a nozzle motion, in closed form.

    Differentiating the arm constraints ``|s_i|^2 = L_i^2`` (``s_i`` of Eq. 7) once and twice gives
    ``q_dot_i = s_i . X_dot / s_iz`` and ``q_ddot_i = (s_i . X_ddot + |s_i_dot|^2) / s_iz`` with
    ``s_i_dot = X_dot - e_z q_dot_i``: the same as ``J^-1 X_dot`` and ``J^-1 (X_ddot - J_dot
    q_dot)`` without a matrix inverse.

    Parameters
    ----------
    xyz, xyz_dot, xyz_ddot : array_like, shape (N, 3)
        Nozzle positions (m), velocities (m/s) and accelerations (m/s^2).

    Returns
    -------
    qd, qdd : ndarray, shape (N, 3)
        Carriage velocities (m/s) and accelerations (m/s^2).
    """
    X, _ = _as_poses(xyz)
    v = np.atleast_2d(np.asarray(xyz_dot, float))
    a = np.atleast_2d(np.asarray(xyz_ddot, float))
    q = inverse(geom, X)
    S = _s_matrix(geom, X, q)
    sz = S[:, :, 2]
    qd = matvec3(S, v) / sz
    qdd = (matvec3(S, a) + _arm_rate_sq(v, qd)) / sz
    return qd, qdd


def velocity_product(geom: DeltaGeometry, xyz, qd, *, q=None, J=None) -> np.ndarray:
    """``J_dot q_dot`` (N, 3), m/s^2: the nozzle acceleration the carriage velocities alone make.

    With ``q_ddot = 0`` the twice differentiated constraint reads ``S X_ddot = -w``, ``w_i = |X_dot -
    e_z q_dot_i|^2``, so ``J_dot q_dot = -S^-1 w`` (one 3x3 solve instead of :func:`jacobian_dot`'s
    matrix products).  ``q`` and ``J`` at the poses may be passed when known.
    """
    X, _ = _as_poses(xyz)
    qd = np.atleast_2d(np.asarray(qd, float))
    q = inverse(geom, X) if q is None else q
    S = _s_matrix(geom, X, q)
    h = -S[:, :, 2]
    # J = -S^-1 diag(h)  =>  S^-1 = -J diag(1/h)
    Sinv = inv3(S) if J is None else -J / h[:, None, :]
    Xd = -matvec3(Sinv, h * qd)
    return -matvec3(Sinv, _arm_rate_sq(Xd, qd))


def _arm_rate_sq(xyz_dot: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """``|s_i_dot|^2 = |X_dot - e_z q_dot_i|^2`` of each arm, shape (N, 3)."""
    return sq_norm3(xyz_dot)[:, None] - 2.0 * xyz_dot[:, 2:3] * qd + qd * qd


def reachable(geom: DeltaGeometry, xyz, *, tol_m: float = 1e-9) -> np.ndarray:
    """Boolean mask, shape (N,): inside the print radius and z range, arms above the minimum angle."""
    xyz_a, _ = _as_poses(xyz)
    r = np.hypot(xyz_a[:, 0], xyz_a[:, 1])
    h = arm_heights(geom, xyz_a)
    with np.errstate(invalid="ignore"):
        steep = np.all(h >= geom.arm_length_m * np.sin(np.deg2rad(geom.min_arm_angle_deg)), axis=1)
    return (
        (r <= geom.print_radius_m + tol_m)
        & (xyz_a[:, 2] >= geom.z_min_m - tol_m)
        & (xyz_a[:, 2] <= geom.z_max_m + tol_m)
        & steep
    )


def check_reachable(geom: DeltaGeometry, xyz, *, what: str = "position") -> None:
    """Raise :class:`KinematicsError` naming the first unreachable pose (in mm)."""
    xyz_a, _ = _as_poses(xyz)
    ok = reachable(geom, xyz_a)
    if not np.all(ok):
        k = int(np.argmin(ok))
        p = xyz_a[k] * 1e3
        r = float(np.hypot(p[0], p[1]))
        raise KinematicsError(
            f"{what} #{k} ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) mm is unreachable: radius {r:.3f} mm "
            f"(print radius {geom.print_radius_m * 1e3:.3f} mm), z range "
            f"[{geom.z_min_m * 1e3:.3f}, {geom.z_max_m * 1e3:.3f}] mm, "
            f"min arm angle {geom.min_arm_angle_deg:.1f} deg"
        )


def condition_number(geom: DeltaGeometry, xyz) -> np.ndarray:
    """2-norm condition number of J at each pose, shape (N,); 1 would be isotropic."""
    return np.linalg.cond(np.atleast_3d(jacobian(geom, np.atleast_2d(xyz))))
