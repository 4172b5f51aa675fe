"""Delta kinematics against closed forms, round trips and finite differences."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ffcomp.errors import KinematicsError
from ffcomp.kinematics import (
    DeltaGeometry,
    carriage_rates,
    check_reachable,
    condition_number,
    forward,
    inverse,
    jacobian,
    jacobian_dot,
    reachable,
    velocity_product,
)
from ffcomp.profile import default_profile

GEOM = default_profile().geometry_si()
# an asymmetric printer: unequal arms, skewed towers, Klipper's frame
SKEW = DeltaGeometry.from_radius([0.331, 0.329, 0.3305], [0.161, 0.1595, 0.160], [210.5, 329.0, 90.3],
                                 effector_offset_z_m=0.02, print_radius_m=0.12, z_max_m=0.28)


def poses_in(geom):
    r = geom.print_radius_m

    @st.composite
    def strat(draw):
        rho = draw(st.floats(0.0, 0.999)) ** 0.5 * r
        th = draw(st.floats(0.0, 2 * np.pi))
        z = draw(st.floats(geom.z_min_m, geom.z_max_m))
        return np.array([rho * np.cos(th), rho * np.sin(th), z])

    return strat()


@settings(max_examples=300, deadline=None)
@given(poses_in(GEOM))
def test_ik_fk_round_trip_default(x):
    q = inverse(GEOM, x)
    assert np.all(np.isfinite(q))
    assert np.max(np.abs(forward(GEOM, q) - x)) < 1e-12  # 1e-9 mm


@settings(max_examples=300, deadline=None)
@given(poses_in(SKEW))
def test_ik_fk_round_trip_asymmetric(x):
    assert np.max(np.abs(forward(SKEW, inverse(SKEW, x)) - x)) < 1e-12


def test_ik_satisfies_sphere_constraints():
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-0.09, 0.09, 50), rng.uniform(-0.09, 0.09, 50), rng.uniform(0, 0.25, 50)])
    q = inverse(SKEW, X)
    for i in range(3):
        d = np.column_stack([X[:, 0] - SKEW.tower_xy_m[i, 0], X[:, 1] - SKEW.tower_xy_m[i, 1],
                             X[:, 2] + SKEW.effector_offset_z_m - q[:, i]])
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), SKEW.arm_length_m[i], rtol=0, atol=1e-13)


def test_centre_jacobian_closed_form():
    # at the centre, z motion is the common carriage motion; the z row of J is 1/3 each
    J = jacobian(GEOM, [0, 0, 0.03])
    np.testing.assert_allclose(J[2], [1 / 3] * 3, atol=1e-14)
    np.testing.assert_allclose(J @ np.ones(3), [0, 0, 1], atol=1e-14)
    # and by symmetry x motion does not move carriages B and C differently
    qd = np.linalg.solve(J, [1.0, 0, 0])
    assert abs(qd[1] - qd[2]) < 1e-12


@pytest.mark.parametrize("geom", [GEOM, SKEW])
def test_jacobian_matches_finite_differences(geom):
    rng = np.random.default_rng(1)
    for _ in range(20):
        x = np.array([*rng.uniform(-0.08, 0.08, 2), rng.uniform(0.01, 0.2)])
        q = inverse(geom, x)
        J = jacobian(geom, x)
        h = 1e-6
        Jfd = np.column_stack([(forward(geom, q + h * e) - forward(geom, q - h * e)) / (2 * h) for e in np.eye(3)])
        np.testing.assert_allclose(J, Jfd, atol=1e-8)


@pytest.mark.parametrize("geom", [GEOM, SKEW])
def test_jacobian_dot_matches_finite_differences(geom):
    rng = np.random.default_rng(2)
    X = np.column_stack([rng.uniform(-0.08, 0.08, 20), rng.uniform(-0.08, 0.08, 20), rng.uniform(0.01, 0.2, 20)])
    V = rng.normal(0, 0.2, (20, 3))
    dt = 1e-6
    Jd_fd = (jacobian(geom, X + V * dt) - jacobian(geom, X - V * dt)) / (2 * dt)
    np.testing.assert_allclose(jacobian_dot(geom, X, V), Jd_fd, atol=1e-7)


def test_jacobian_dot_gives_task_acceleration():
    # X_ddot = J q_ddot + J_dot q_dot (Eq. 13) along an arbitrary joint-space path
    t = np.linspace(0, 0.1, 2001)
    q0 = inverse(GEOM, [0.02, -0.03, 0.05])
    q = q0 + np.column_stack([0.01 * np.sin(30 * t), 0.008 * np.cos(21 * t), 0.005 * t**2])
    X = forward(GEOM, q)
    dt = t[1] - t[0]
    qd, qdd = np.gradient(q, dt, axis=0), np.gradient(np.gradient(q, dt, axis=0), dt, axis=0)
    Xd = np.gradient(X, dt, axis=0)
    Xdd = np.gradient(Xd, dt, axis=0)
    k = slice(10, -10)
    J = jacobian(GEOM, X[k])
    Jd = jacobian_dot(GEOM, X[k], Xd[k])
    pred = np.einsum("nij,nj->ni", J, qdd[k]) + np.einsum("nij,nj->ni", Jd, qd[k])
    np.testing.assert_allclose(pred, Xdd[k], atol=2e-5 * np.max(np.abs(Xdd)) + 1e-6)


@pytest.mark.parametrize("geom", [GEOM, SKEW])
def test_closed_form_rates_match_the_jacobian_route(geom):
    # q' = J^-1 X', q'' = J^-1 (X'' - J_dot q'), and J_dot q' itself, without matrix products
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-0.08, 0.08, 40), rng.uniform(-0.08, 0.08, 40), rng.uniform(0.01, 0.2, 40)])
    V, A = rng.normal(0, 0.3, (40, 3)), rng.normal(0, 30.0, (40, 3))
    Jinv = np.linalg.inv(jacobian(geom, X))
    Jd = jacobian_dot(geom, X, V)
    qd = np.einsum("nij,nj->ni", Jinv, V)
    qdd = np.einsum("nij,nj->ni", Jinv, A - np.einsum("nij,nj->ni", Jd, qd))
    qd2, qdd2 = carriage_rates(geom, X, V, A)
    np.testing.assert_allclose(qd2, qd, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(qdd2, qdd, rtol=1e-9, atol=1e-11)
    vp = np.einsum("nij,nj->ni", Jd, qd)
    np.testing.assert_allclose(velocity_product(geom, X, qd), vp, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(velocity_product(geom, X, qd, q=inverse(geom, X), J=jacobian(geom, X)), vp,
                               rtol=1e-10, atol=1e-13)


def test_reachability_and_errors():
    assert reachable(GEOM, [0, 0, 0.0]).all()
    assert not reachable(GEOM, [0.136, 0, 0.01]).any()  # outside the print radius
    assert not reachable(GEOM, [0, 0, 0.31]).any()  # above z_max
    with pytest.raises(KinematicsError, match=r"136\.000, 0\.000, 10\.000"):
        check_reachable(GEOM, [[0, 0, 0.01], [0.136, 0, 0.01]])
    far = inverse(GEOM, [1.0, 0, 0])
    assert np.isnan(far).any()


def test_condition_number_grows_towards_the_rim():
    c0 = condition_number(GEOM, [0, 0, 0.03])[0]
    c1 = condition_number(GEOM, [-0.13, 0, 0.03])[0]
    assert c1 > c0 >= 1.0
