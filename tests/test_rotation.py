import numpy as np
import pytest

from fringecal.frames import Frame
from fringecal.rotation import angles_from_matrix, rotation_derivatives, rotation_matrix, wrap_angle


def test_matrix_matches_eq_2_6_entries():
    o, p, k = 0.3, -0.4, 1.1
    R = rotation_matrix(o, p, k)
    so, co, sp, cp, sk, ck = np.sin(o), np.cos(o), np.sin(p), np.cos(p), np.sin(k), np.cos(k)
    expected = [[cp * ck, co * sk + so * sp * ck, so * sk - co * sp * ck],
                [-cp * sk, co * ck - so * sp * sk, so * ck + co * sp * sk],
                [sp, -so * cp, co * cp]]
    np.testing.assert_allclose(R, expected, atol=1e-15)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)


def test_eq_2_6_is_x_then_y_then_z_rotation():
    # R(omega, phi, kappa) = Rz(kappa) Ry(phi) Rx(omega) with passive (frame) rotations.
    o, p, k = 0.2, 0.5, -0.7
    Rx = np.array([[1, 0, 0], [0, np.cos(o), np.sin(o)], [0, -np.sin(o), np.cos(o)]])
    Ry = np.array([[np.cos(p), 0, -np.sin(p)], [0, 1, 0], [np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(k), np.sin(k), 0], [-np.sin(k), np.cos(k), 0], [0, 0, 1]])
    np.testing.assert_allclose(rotation_matrix(o, p, k), Rz @ Ry @ Rx, atol=1e-15)


def test_angles_round_trip_random(rng):
    a = np.stack([rng.uniform(-np.pi, np.pi, 5000), rng.uniform(-1.5, 1.5, 5000),
                  rng.uniform(-np.pi, np.pi, 5000)], axis=1)
    back = angles_from_matrix(rotation_matrix(*a.T))
    np.testing.assert_allclose(wrap_angle(back - a), 0, atol=1e-12)


@pytest.mark.parametrize("angles", [
    (-3.037, -0.264, 3.139), (-3.037, 0.099, -3.130), (-3.038, -0.263, -3.138),
    (-3.067, 0.057, -3.126), (-1.570, -0.0013, 1.646), (np.pi, 0.0, -np.pi + 1e-9),
])
def test_angles_round_trip_near_pi(angles):
    a = np.array(angles)
    R = rotation_matrix(*a)
    np.testing.assert_allclose(rotation_matrix(*angles_from_matrix(R)), R, atol=1e-14)
    # With a reference near the rig, the same branch comes back, no 2 pi jump.
    np.testing.assert_allclose(angles_from_matrix(R, near=a + 0.01), a, atol=1e-12)


def test_near_picks_continuous_branch_across_pi():
    a = np.array([3.14159, 0.2, -3.14159])
    R = rotation_matrix(*a)
    b = angles_from_matrix(R, near=[-3.14, 0.2, 3.14])
    assert abs(b[0] - (3.14159 - 2 * np.pi)) < 1e-12
    assert abs(b[2] - (-3.14159 + 2 * np.pi)) < 1e-12
    # The alternative triple (omega+pi, pi-phi, kappa+pi) is chosen when closer.
    alt = angles_from_matrix(R, near=[a[0] + np.pi, np.pi - a[1], a[2] + np.pi])
    np.testing.assert_allclose(rotation_matrix(*alt), R, atol=1e-14)
    assert abs(alt[1] - (np.pi - 0.2)) < 1e-12


def test_derivatives_match_finite_differences():
    a = np.array([-3.03, -0.26, 3.13])
    d = rotation_derivatives(*a)
    h = 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        fd = (rotation_matrix(*(a + e)) - rotation_matrix(*(a - e))) / (2 * h)
        np.testing.assert_allclose(d[i], fd, atol=1e-9)


def test_frame_convention_and_composition(rng):
    T_ab = Frame.from_params([10, -20, 30, 0.3, -0.2, 2.5])
    T_bc = Frame.from_params([-5, 7, 1, -1.0, 0.4, -2.9])
    x_c = rng.normal(size=(10, 3)) * 100
    np.testing.assert_allclose(T_ab.compose(T_bc).to_world(x_c), T_ab.to_world(T_bc.to_world(x_c)), atol=1e-10)
    np.testing.assert_allclose(T_ab.inverse().to_world(T_ab.to_world(x_c)), x_c, atol=1e-10)
    # docs/conventions.md: x_local = R (x_world - t)
    x_w = rng.normal(size=(4, 3))
    np.testing.assert_allclose(T_ab.to_local(x_w), (x_w - T_ab.t) @ T_ab.R.T, atol=1e-14)
