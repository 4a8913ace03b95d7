"""Map triangulation agrees with the reference triangulation and with the true surface."""

import numpy as np
import pytest

from fringecal.pointcloud import (
    STATUS_INVALID,
    STATUS_OK,
    STATUS_PARALLEL,
    STATUS_UNDISTORT_FAILED,
    CameraRayCache,
    camera_ray_cache,
    triangulate_maps,
    triangulate_rows,
)
from fringecal.sensor import Sensor, SensorFormat, distort
from fringecal.spheres.synthetic import Sphere
from fringecal.triangulation import triangulate


def small_camera(camera: Sensor, n: int = 192) -> Sensor:
    """The same lens and chip size with fewer pixels (fast tests, same geometry)."""
    f = camera.format
    return Sensor(camera.name, "camera", SensorFormat(n, n, f.width_mm, f.height_mm), camera.params)


@pytest.mark.parametrize("scanner", [0, 1])
def test_agrees_with_reference_triangulation_on_random_pixels(thesis_rig, scanner):
    """Full 2048 x 2048 thesis cameras, distortion on both sensors: random pixels see
    random points of the measurement volume, whose projector phases are then disturbed
    (so eps1 is millimetres, not zero): points and signed eps1 within 1e-9 mm."""
    s = thesis_rig.scanners[scanner]
    rng = np.random.default_rng(scanner)
    h, w = s.camera.format.shape
    rows = rng.integers(0, h, 4000)
    cols = rng.integers(0, w, 4000)
    uv = np.stack([cols, rows], axis=-1).astype(float)
    o, d = s.camera.rays(s.camera.image_mm(uv))
    depth = rng.uniform(2000, 3200, (len(d), 1))  # the thesis stand-off is ~2.5 m
    tau = s.projector.measured(s.projector.project(o + depth * d)) + rng.normal(0, 0.002, (len(d), 2))
    inside = np.all(np.abs(tau) < np.pi, axis=1)
    rows, cols, uv, tau = rows[inside], cols[inside], uv[inside], tau[inside]
    tx = np.full((h, w), np.nan)
    ty = np.full((h, w), np.nan)
    tx[rows, cols], ty[rows, cols] = tau[:, 0], tau[:, 1]
    tau = np.stack([tx[rows, cols], ty[rows, cols]], axis=-1)  # duplicates: the last one wins
    maps = triangulate_maps(s.camera, s.projector, tx, ty)
    ref, eps_ref = triangulate(s.camera, s.projector, uv, tau)
    got = np.stack([maps.x[rows, cols], maps.y[rows, cols], maps.z[rows, cols]], axis=-1)
    assert np.abs(got - ref).max() < 1e-9
    assert np.abs(maps.eps1[rows, cols] - eps_ref).max() < 1e-9
    assert 0.3 < np.abs(eps_ref).max() < 20  # eps1 is exercised in sign and size
    assert maps.n_points == len(set(zip(rows.tolist(), cols.tolist()))) > 2000
    assert maps.counts()["invalid"] == h * w - maps.n_points


def test_points_lie_on_the_true_sphere_and_eps1_vanishes(thesis_rig):
    """Analytic scan of a sphere: camera ray -> surface point -> projector phases -> maps."""
    s = thesis_rig.scanners[0]
    cam = small_camera(s.camera)
    centre, radius = np.array([-100.0, 80.0, 0.0]), 250.0
    cache = CameraRayCache.for_camera(cam)
    ideal = np.moveaxis(cache.ideal, 0, -1)
    d = np.concatenate([-ideal, np.full(ideal.shape[:2] + (1,), cam.c)], axis=-1) @ cam.R
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    t, _ = Sphere(centre, radius).intersect(np.broadcast_to(cam.pinhole, (d.size // 3, 3)), d.reshape(-1, 3))
    surface = cam.pinhole + np.where(np.isfinite(t), t, np.nan)[:, None] * d.reshape(-1, 3)
    tau = s.projector.measured(s.projector.project(surface)).reshape(ideal.shape[:2] + (2,))
    on = np.all(np.abs(tau) < np.pi, axis=-1)
    maps = triangulate_maps(cam, s.projector, tau[..., 0], tau[..., 1], valid=on, cache=cache)
    assert maps.n_points == on.sum() > 5000
    pts = maps.points()
    assert np.abs(np.linalg.norm(pts - centre, axis=1) - radius).max() < 1e-9
    assert np.nanmax(np.abs(maps.eps1)) < 1e-9
    assert np.all(np.isnan(maps.x[~on]))


def test_chunks_row_blocks_and_float32_agree(thesis_rig):
    s = thesis_rig.scanners[1]
    cam = small_camera(s.camera, 100)
    rng = np.random.default_rng(3)
    tx = rng.uniform(-3, 3, (100, 100))
    ty = rng.uniform(-3, 3, (100, 100))
    whole = triangulate_maps(cam, s.projector, tx, ty, row_chunk=100)
    chunked = triangulate_maps(cam, s.projector, tx, ty, row_chunk=7)
    for a in ("x", "y", "z", "eps1", "status"):
        np.testing.assert_array_equal(getattr(whole, a), getattr(chunked, a))
    block = triangulate_rows(cam, s.projector, tx[40:55], ty[40:55], np.ones((15, 100), bool), row0=40)
    np.testing.assert_array_equal(block.z, whole.z[40:55])
    single = triangulate_maps(cam, s.projector, tx.astype(np.float32), ty.astype(np.float32), dtype=np.float32)
    again = triangulate_maps(cam, s.projector, tx.astype(np.float32), ty.astype(np.float32))
    assert single.z.dtype == np.float32
    np.testing.assert_array_equal(single.z, again.z.astype(np.float32))


def test_invalid_pixels_fold_over_and_parallel_rays_are_flagged(thesis_rig):
    s = thesis_rig.scanners[0]
    cam = small_camera(s.camera, 16)
    tx = np.zeros((16, 16))
    ty = np.zeros((16, 16))
    valid = np.ones((16, 16), bool)
    tx[0, 0] = np.nan
    valid[0, 1] = False
    # a projector whose lens folds over beyond ~2 mm: the phase corner cannot be inverted
    bad = s.projector.with_params(np.r_[s.projector.params[:9], -0.2, 0, 0, 0, 0])
    tx[1, :] = np.pi
    ty[1, :] = np.pi
    maps = triangulate_maps(cam, bad, tx, ty, valid)
    assert maps.status[0, 0] == maps.status[0, 1] == STATUS_INVALID
    assert np.all(maps.status[1] == STATUS_UNDISTORT_FAILED)
    assert np.all(maps.status[2:] == STATUS_OK)
    assert np.all(np.isnan(maps.x[:2, :2])) and np.all(np.isnan(maps.eps1[1]))
    assert maps.counts() == {"triangulated": 256 - 2 - 16, "invalid": 2, "undistort_failed": 16, "parallel_rays": 0}
    # a "projector" that is the camera moved sideways: its rays through the same ideal
    # coordinates are parallel to the camera's
    twin_params = np.array(cam.params)
    twin_params[0] += 500.0
    twin = Sensor("twin", "projector", s.projector.format, twin_params)
    ideal = np.moveaxis(camera_ray_cache(cam).ideal, 0, -1)
    phases = twin.measured(distort(ideal, cam.k, cam.p) + cam.principal_point)
    maps = triangulate_maps(cam, twin, phases[..., 0], phases[..., 1])
    assert np.all(maps.status == STATUS_PARALLEL) and np.all(np.isnan(maps.z))


def test_bad_shapes_and_foreign_cache_are_refused(thesis_rig):
    s = thesis_rig.scanners[0]
    cam = small_camera(s.camera, 32)
    with pytest.raises(ValueError, match="tau_y has shape"):
        triangulate_rows(cam, s.projector, np.zeros((4, 32)), np.zeros((4, 31)), np.ones((4, 32), bool))
    with pytest.raises(ValueError, match="do not fit camera"):
        triangulate_rows(cam, s.projector, np.zeros((4, 32)), np.zeros((4, 32)), np.ones((4, 32), bool), row0=30)
    other = small_camera(thesis_rig.scanners[1].camera, 32)
    with pytest.raises(ValueError, match="another interior orientation"):
        triangulate_rows(cam, s.projector, np.zeros((4, 32)), np.zeros((4, 32)), np.ones((4, 32), bool),
                         cache=CameraRayCache.for_camera(other))


def test_ray_cache_depends_on_interior_only(thesis_rig):
    cam = small_camera(thesis_rig.scanners[0].camera, 32)
    moved = cam.with_params(np.r_[cam.params[:3] + 100, cam.params[3:6] + 0.1, cam.params[6:]])
    assert camera_ray_cache(cam) is camera_ray_cache(moved)
    refocused = cam.with_params(np.r_[cam.params[:8], cam.params[8] + 1, cam.params[9:]])
    assert CameraRayCache.for_camera(cam).matches(refocused)  # c is applied in the kernel
    shifted = cam.with_params(np.r_[cam.params[:6], cam.params[6] + 0.01, cam.params[7:]])
    assert not CameraRayCache.for_camera(cam).matches(shifted)
    redistorted = cam.with_params(np.r_[cam.params[:9], cam.params[9] * 1.01, cam.params[10:]])
    assert not CameraRayCache.for_camera(cam).matches(redistorted)


def test_region_fit_of_a_rendered_sphere_with_edge_flags(thesis_rig):
    """A 25 mm sphere 2.6 m away, every pixel triangulated: the region fit finds the true
    sphere, flags its rim as edge, and keeps the pixels of what it kept."""
    import json

    from fringecal.pointcloud import provenance
    from fringecal.schemas import SphereFitsTable, validate_table
    from fringecal.spheres.regions import boundary_flags, fit_region

    s = thesis_rig.scanners[0]
    cam = small_camera(s.camera, 512)
    centre, radius = np.array([50.0, -30.0, 0.0]), 25.0
    ideal = np.moveaxis(camera_ray_cache(cam).ideal, 0, -1)
    d = (np.concatenate([-ideal, np.full(ideal.shape[:2] + (1,), cam.c)], axis=-1) @ cam.R).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, _ = Sphere(centre, radius).intersect(np.broadcast_to(cam.pinhole, d.shape), d)
    surface = cam.pinhole + np.where(np.isfinite(t), t, np.nan)[:, None] * d
    tau = s.projector.measured(s.projector.project(surface)).reshape(512, 512, 2)
    valid = np.isfinite(tau).all(axis=-1)
    maps = triangulate_maps(cam, s.projector, tau[..., 0], tau[..., 1], valid)
    edge = boundary_flags(valid, 1)
    rf = fit_region(maps, valid, expected_radius=radius, flag_maps={"edge": edge},
                    viewpoints=[s.camera.pinhole, s.projector.pinhole])
    assert 500 < len(rf.pixels) == valid.sum()
    assert rf.fit.rejected["edge"] == edge.sum() > 50
    assert np.abs(rf.fit.model.centre - centre).max() < 1e-6 and abs(rf.fit.model.radius - radius) < 1e-6
    rows, cols = rf.kept_pixels
    assert not edge[rows, cols].any() and len(rows) == rf.fit.model.n_points
    np.testing.assert_allclose(np.c_[maps.x[rows, cols], maps.y[rows, cols], maps.z[rows, cols]],
                               rf.pixels.points[rf.fit.kept])
    row = rf.row("m1", "scanner1", "0")
    u0, v0, u1, v1 = row["u_min_px"], row["v_min_px"], row["u_max_px"], row["v_max_px"]
    vr, vc = np.nonzero(valid)
    assert (u0, v0, u1, v1) == (vc.min(), vr.min(), vc.max(), vr.max())
    assert u0 < cols.min() and u1 > cols.max()  # the rim (edge) lies outside what is kept
    validate_table(__import__("pandas").DataFrame([row]), SphereFitsTable)
    attrs = provenance(cam, s.projector)
    assert json.loads(json.dumps(attrs)) == attrs and attrs["projector"]["params"]["c"] == s.projector.c
