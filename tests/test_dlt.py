"""DLT (thesis eqs. 2-10..2-18, 6-8..6-13): round trips on exact data, noise, bad input."""

import numpy as np
import pytest

from fringecal.calibration.dlt import DLTError, DLTEstimate
from fringecal.calibration.initial import initial_rig_from_dlt
from fringecal.rotation import rotation_matrix


def _points(rng, n=40, centre=(-150.0, 80.0, -650.0), half=(450.0, 300.0, 350.0)):
    return np.asarray(centre) + rng.uniform(-1, 1, (n, 3)) * np.asarray(half)


@pytest.mark.parametrize("index", [0, 1, 2, 3])
def test_round_trip_recovers_the_nine_parameters_of_every_thesis_sensor(thesis_rig, rng, index):
    sensor = thesis_rig.sensors[index]
    truth = np.r_[sensor.params[:9], np.zeros(5)]
    undistorted = sensor.with_params(truth)
    X = _points(rng)
    est = DLTEstimate.from_estimate(X, undistorted.project(X), near_angles=sensor.angles)
    np.testing.assert_allclose(est.params[:3], truth[:3], atol=1e-7)  # mm
    np.testing.assert_allclose(est.params[3:6], truth[3:6], atol=1e-10)  # rad
    np.testing.assert_allclose(est.params[6:9], truth[6:9], atol=1e-9)  # mm
    assert est.reprojection_rms_mm < 1e-10 and est.algebraic_residual < 1e-12
    assert abs(est.c_x - est.c_y) < 1e-9 and abs(est.skew) < 1e-12
    # the sign convention: the recovered sensor sees the points in front (z' > 0)
    assert np.all(undistorted.with_params(est.params14).to_sensor(X)[:, 2] > 0)


def test_round_trip_with_other_orientations_and_far_offsets(rng):
    """Arbitrary orientations (incl. both Euler branches near +-pi) and world coordinates
    10 m from the origin: normalisation keeps it exact."""
    for _ in range(20):
        angles = rng.uniform([-np.pi, -1.3, -np.pi], [np.pi, 1.3, np.pi])
        R = rotation_matrix(*angles)
        X0 = rng.uniform(-1e4, 1e4, 3)
        target = X0 + 3000.0 * R[2]  # in front: along the sensor's +z' axis
        X = target + rng.uniform(-400, 400, (30, 3))
        c, h = rng.uniform(20, 80), rng.uniform(-1, 1, 2)
        xs = (X - X0) @ R.T
        xy = h - c * xs[:, :2] / xs[:, 2:3]
        est = DLTEstimate.from_estimate(X, xy, near_angles=angles)
        np.testing.assert_allclose(est.params[:3], X0, atol=1e-5)
        np.testing.assert_allclose(rotation_matrix(*est.params[3:6]), R, atol=1e-9)
        np.testing.assert_allclose(est.params[3:6], angles, atol=1e-9)
        np.testing.assert_allclose(est.params[6:9], [*h, c], atol=1e-7)


def test_noise_gives_residuals_of_the_noise_level(thesis_rig, rng):
    cam = thesis_rig.sensors[0].with_params(np.r_[thesis_rig.sensors[0].params[:9], np.zeros(5)])
    X = _points(rng, n=200)
    noise = 0.002  # mm on the image plane (a quarter pixel)
    est = DLTEstimate.from_estimate(X, cam.project(X) + rng.normal(0, noise, (200, 2)))
    assert 0.8 * noise < est.reprojection_rms_mm / np.sqrt(2) < 1.2 * noise
    assert est.algebraic_residual > 0
    np.testing.assert_allclose(est.params[:3], cam.params[:3], atol=5.0)
    assert abs(est.params[8] - cam.params[8]) < 0.1
    r = est.residuals(X, cam.project(X))
    assert r.shape == (200, 2) and np.sqrt(np.mean(r**2)) < 0.003


def test_too_few_and_coplanar_points_are_refused(thesis_rig, rng):
    cam = thesis_rig.sensors[0]
    X = _points(rng, n=5)
    with pytest.raises(DLTError, match="at least 6 control points, got 5"):
        DLTEstimate.from_estimate(X, cam.project(X))
    plane = _points(rng, n=30)
    plane[:, 2] = -650.0
    with pytest.raises(DLTError, match="coplanar"):
        DLTEstimate.from_estimate(plane, cam.project(plane))
    with pytest.raises(DLTError, match=r"need points \(n, 3\)"):
        DLTEstimate.from_estimate(X[:, :2], cam.project(X))


def test_initial_rig_keeps_the_reference_cameras_external_parameters(thesis_rig, rng):
    # points in each sensor's field of view, where its (true) distortion is small
    pts = {s.name: s.pinhole + 3000.0 * s.R[2] + rng.uniform(-300, 300, (60, 3)) for s in thesis_rig.sensors}
    img = {s.name: s.project(pts[s.name]) + rng.normal(0, 0.001, (60, 2)) for s in thesis_rig.sensors}
    rig, est = initial_rig_from_dlt(thesis_rig, pts, img)
    assert set(est) == {"C1", "P1", "C2", "P2"}
    np.testing.assert_array_equal(rig.params[0, :6], thesis_rig.params[0, :6])
    assert np.all(rig.params[:, 9:] == 0)  # DLT: no distortion
    # distortion ignored by the DLT biases depth and c together (about 13 mm, 0.3 mm here)
    np.testing.assert_allclose(rig.params[1:, :3], thesis_rig.params[1:, :3], atol=20.0)
    np.testing.assert_allclose(rig.params[1:, 8], thesis_rig.params[1:, 8], atol=0.5)
    with pytest.raises(DLTError, match="sensor P2: no control points"):
        initial_rig_from_dlt(thesis_rig, {k: v for k, v in pts.items() if k != "P2"}, img)
