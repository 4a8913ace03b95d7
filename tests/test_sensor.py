import numpy as np
import pytest

from fringecal.sensor import Sensor, SensorFormat, UndistortError, distort, undistort
from fringecal.triangulation import closest_approach, triangulate


def full_image_grid(sensor: Sensor, n: int = 41) -> np.ndarray:
    """Measured coordinates (pixels or phases) over the whole image, corners included."""
    f = sensor.format
    if sensor.role == "camera":
        u, v = np.meshgrid(np.linspace(0, f.width_px - 1, n), np.linspace(0, f.height_px - 1, n))
    else:
        u, v = np.meshgrid(np.linspace(-np.pi, np.pi, n), np.linspace(-np.pi, np.pi, n))
    return np.stack([u.ravel(), v.ravel()], axis=1)


def test_pixel_and_phase_conversions_eq_2_21_2_22():
    cam = SensorFormat(2048, 2048, 15.1, 15.1)
    # eq. 2-21 with 1-based U: xi = ((U-1)/(M-1) - 0.5) N_x
    U, V = 1025, 1
    xy = cam.pixel_to_mm([U - 1, V - 1])
    assert xy[0] == pytest.approx(((U - 1) / 2047 - 0.5) * 15.1, abs=1e-15)
    assert xy[1] == pytest.approx(-7.55, abs=1e-15)
    np.testing.assert_allclose(cam.mm_to_pixel(cam.pixel_to_mm([[3.5, 2000.25]])), [[3.5, 2000.25]], atol=1e-10)
    prj = SensorFormat(1400, 1050, 19.0, 14.3)
    np.testing.assert_allclose(prj.phase_to_mm([np.pi, -np.pi]), [9.5, -7.15], atol=1e-15)
    np.testing.assert_allclose(prj.mm_to_phase(prj.phase_to_mm([[0.3, -2.0]])), [[0.3, -2.0]], atol=1e-15)


def test_projection_then_back_projection_whole_image_every_sensor(thesis_rig):
    """Image -> ray -> point at 2-4 m -> image, distortion included: < 1e-6 mm."""
    worst = 0.0
    for sensor in thesis_rig.sensors:
        measured = full_image_grid(sensor)
        image = sensor.image_mm(measured)
        origin, d = sensor.rays(image)
        depth = np.linspace(2000, 4000, len(d))[:, None]
        points = origin + depth * d
        back = sensor.project(points)
        worst = max(worst, np.abs(back - image).max())
        # and world -> image -> ray passes through the world point
        o, d2 = sensor.rays(sensor.project(points))
        dist = np.linalg.norm(np.cross(points - o, d2), axis=1)
        assert dist.max() < 1e-6, sensor.name
        np.testing.assert_allclose(sensor.measured(back), measured, atol=1e-6)
    assert worst < 1e-6


def test_distortion_is_significant_and_inverted(thesis_rig):
    cam = thesis_rig.sensors[0]
    corner = np.array([[7.0, 7.0]])
    shifted = distort(corner, cam.k, cam.p)
    assert np.abs(shifted - corner).max() > 0.01  # tens of micrometres at the corner
    np.testing.assert_allclose(undistort(shifted, cam.k, cam.p), corner, atol=1e-13)


def test_tangential_terms_follow_brown():
    x, y = 3.0, -2.0
    p1, p2 = 1e-4, -2e-4
    d = distort([[x, y]], (0, 0, 0), (p1, p2))[0]
    r2 = x * x + y * y
    assert d[0] - x == pytest.approx(p1 * (r2 + 2 * x * x) + 2 * p2 * x * y, abs=1e-15)
    assert d[1] - y == pytest.approx(p2 * (r2 + 2 * y * y) + 2 * p1 * x * y, abs=1e-15)


def test_undistort_refuses_fold_over():
    # A strong negative k1 folds the model over beyond r ~ 1/sqrt(3|k1|).
    with pytest.raises(UndistortError, match="did not converge"):
        undistort(np.array([[50.0, 0.0]]), (-1e-2, 0, 0), (0, 0))


def test_points_behind_the_sensor_are_nan(thesis_rig):
    cam = thesis_rig.sensors[0]
    behind = cam.pinhole + 100 * (np.array([0, 0, -1.0]) @ cam.R)  # along -z'
    assert np.isnan(cam.project(behind[None])).all()


def test_exact_ray_pairs_triangulate_to_the_point(thesis_rig, thesis_artefact):
    """Project true points into camera and projector, triangulate back: < 1e-9 mm."""
    from fringecal.frames import Frame

    scanner = thesis_rig.scanners[0]
    pose = Frame.from_params([200.047, -94.194, -457.935, -1.56998, -0.00128, 1.64601])
    rng = np.random.default_rng(1)
    pts = pose.to_world(thesis_artefact.centres)[[4, 5, 7, 8]]  # spheres 5, 6, 8, 9
    pts = (pts[:, None, :] + rng.normal(size=(4, 250, 3)) * 20).reshape(-1, 3)
    uv = scanner.camera.measured(scanner.camera.project(pts))
    tau = scanner.projector.measured(scanner.projector.project(pts))
    s, eps1 = triangulate(scanner.camera, scanner.projector, uv, tau)
    assert np.abs(s - pts).max() < 1e-9
    assert np.abs(eps1).max() < 1e-9


def test_eps1_is_signed_closest_distance():
    s, e = closest_approach([0, 0, 0], [1, 0, 0], [5, 2, -3], [0, 0, 1])
    np.testing.assert_allclose(s, [5, 1, 0])
    assert abs(e) == pytest.approx(2.0)
    _, e_swapped = closest_approach([5, 2, -3], [0, 0, 1], [0, 0, 0], [1, 0, 0])
    assert e_swapped == pytest.approx(e)  # (o2-o1).(d1 x d2) is symmetric under swapping
    _, e_other_side = closest_approach([0, 0, 0], [1, 0, 0], [5, -2, -3], [0, 0, 1])
    assert e_other_side == pytest.approx(-e)


def test_sensor_rejects_bad_role():
    with pytest.raises(ValueError, match="role"):
        Sensor("X", "lidar", SensorFormat(2, 2, 1, 1), np.zeros(14))
