"""Thin-prism terms (OpenCV's s1..s4) through the sensor model, the bundle kernels and
the point clouds."""

from dataclasses import replace

import numpy as np
import pytest

from fringecal.calibration.model import BundleProblem, Evaluator
from fringecal.pointcloud import triangulate_image_points
from fringecal.sensor import distort, undistort
from fringecal.simulate.control_points import simulate_control_points, thesis_truth
from test_bundle_kernels import _dense_jacobian, _jacobian_errors

#: thin-prism terms of a few tenths of a pixel at the corner of the thesis cameras
PRISM = np.array([[3e-6, -2e-9, -2e-6, 1e-9], [-1e-6, 1e-9, 2.5e-6, -2e-9]] * 2)


@pytest.fixture(scope="module")
def small():
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, spacing_px=40, rng=7)
    return rig, art, poses, sim


def test_undistort_inverts_distort_with_thin_prism_terms():
    k, p, s = (-2.74e-5, 1.11e-7, -1.04e-9), (-3.04e-5, 1.46e-5), (3e-5, -1e-7, -2e-5, 2e-7)
    u = np.random.default_rng(1).uniform(-7.5, 7.5, (500, 2))
    m = distort(u, k, p, s)
    assert np.abs(m - distort(u, k, p)).max() > 1e-3  # the terms move the image
    np.testing.assert_allclose(undistort(m, k, p, prism=s), u, atol=1e-12, rtol=0)


def test_prism_jacobian_matches_finite_differences(small):
    """Every free parameter, thin-prism terms included, with prism terms non-zero (the
    non-symmetric undistortion Jacobian) and away from the truth."""
    rig, art, poses, sim = small
    cp = sim.control_points.iloc[::23]
    rng = np.random.default_rng(5)
    p = rig.params.copy()
    p[:, :3] += rng.normal(0, 2, (4, 3))
    p[:, 9:12] *= 2.0
    start = replace(rig, free=np.ones((4, 14), bool)).with_params(p, prism=PRISM).with_prism_free(True)
    pr = BundleProblem.from_tables(start, art, cp, poses)
    ev = Evaluator(pr, chunk_size=7)
    assert ev.n_local == 42
    x = ev.layout.pack(pr.rig.params, pr.poses, pr.rig.prism)
    res, Jd = _dense_jacobian(ev, x)
    steps = {"k1": 1e-8, "k2": 1e-10, "k3": 1e-12, "p1": 1e-8, "p2": 1e-8, "s1": 1e-8, "s2": 1e-10,
             "s3": 1e-8, "s4": 1e-10}
    checked = 0
    for name, err in _jacobian_errors(ev, x, Jd, steps):
        assert err < 1e-5, f"{name}: relative difference {err:.2e}"
        checked += name.split(".")[-1] in ("s1", "s2", "s3", "s4")
    assert checked == 16
    # the normal equations of the 42-slot kernel are the dense products
    e = ev.evaluate(x, True)
    np.testing.assert_allclose(e.N1, np.einsum("ni,nj->ij", Jd[:, 0], Jd[:, 0]), rtol=1e-9,
                               atol=1e-12 * np.abs(e.N1).max())
    np.testing.assert_allclose(e.N2, np.einsum("ni,nj->ij", Jd[:, 1], Jd[:, 1]), rtol=1e-9,
                               atol=1e-12 * np.abs(e.N2).max())
    np.testing.assert_allclose(e.b, np.einsum("n,ni->i", res[:, 0], Jd[:, 0])
                               + np.einsum("n,ni->i", res[:, 1], Jd[:, 1]), rtol=1e-8, atol=1e-12 * np.abs(e.b).max())


def test_triangulation_uses_the_thin_prism_terms(small):
    """A point imaged through sensors with thin-prism terms triangulates back to itself
    (point-cloud kernel and Sensor.rays alike), and misses by the terms' effect without them."""
    rig, _, _, _ = small
    sc = rig.with_params(rig.params, prism=PRISM).scanners[0]
    X = np.array([[-100.0, 50.0, 0.0], [250.0, -300.0, 80.0]])
    cam_mm = sc.camera.project(X)
    prj_mm = sc.projector.project(X)
    np.testing.assert_allclose(triangulate_image_points(sc.camera, sc.projector, cam_mm, prj_mm), X, atol=1e-7)
    plain = rig.scanners[0]
    miss = np.abs(triangulate_image_points(plain.camera, plain.projector, cam_mm, prj_mm) - X).max()
    assert miss > 1e-3


def test_opencv_carries_the_thin_prism_terms_exactly(small):
    """Export as OpenCV's 12 coefficients (k4..k6 zero, s1..s4) and import back: the
    same projection to 1e-6 px and the same terms."""
    from fringecal.interop.opencv import from_opencv, to_opencv

    rig, _, _, _ = small
    cam = rig.with_params(rig.params, prism=PRISM).sensors[0]
    ocv = to_opencv(cam)
    assert ocv.dist.shape == (12,) and ocv.worst_px < 1e-6
    back = from_opencv(ocv.K, ocv.dist, ocv.R, ocv.t, ocv.image_size, name="C1", role="camera", fmt=cam.format,
                       near=cam.angles)
    assert not back.fitted and back.worst_px < 1e-6
    np.testing.assert_allclose(back.sensor.prism, cam.prism, rtol=1e-9)
