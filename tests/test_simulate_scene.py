"""Scene geometry of the virtual scanner, checked against the definitions of the solids."""

import numpy as np
import pandas as pd
import pytest

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.fringe.sequence import FringeSequence
from fringecal.simulate import (
    SPHERE_PLATE_SEPARATION_MM,
    ArtefactHardware,
    Box,
    Cylinder,
    Plane,
    RenderConfig,
    Scene,
    SceneObject,
    Sphere,
    artefact_scene,
    render_measurement,
    scaled_rig,
    scaled_scanner,
    sphere_plate_pose,
    sphere_plate_scene,
)
from fringecal.simulate.visibility import pixel_centre_rays


def random_rays_towards(rng, target, spread, n, origin_distance=500.0):
    """Rays from random origins ~origin_distance away, aimed near ``target``."""
    target = np.asarray(target, float)
    origins = target + _random_unit(rng, n) * origin_distance
    aim = target + rng.uniform(-spread, spread, size=(n, 3))
    d = aim - origins
    return origins, d / np.linalg.norm(d, axis=1, keepdims=True)


def _random_unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def inside_cylinder(p, start, end, r):
    a = (end - start) / np.linalg.norm(end - start)
    h = (p - start) @ a
    radial = np.linalg.norm((p - start) - h[:, None] * a, axis=1)
    return (h >= 0) & (h <= np.linalg.norm(end - start)) & (radial <= r)


def inside_box(p, centre, axes, half):
    local = (p - centre) @ np.asarray(axes).T
    return np.all(np.abs(local) <= half, axis=1)


@pytest.mark.parametrize("solid", ["sphere", "cylinder", "box"])
def test_first_hit_lies_on_the_surface_with_nothing_before_it(rng, solid):
    centre = np.array([10.0, -20.0, 30.0])
    axes = Frame([0, 0, 0], [0.3, -0.5, 1.1]).R
    if solid == "sphere":
        prim, r, spread = Sphere(centre, 25.0), 25.0, 30.0
        inside = lambda p: np.linalg.norm(p - centre, axis=1) <= r  # noqa: E731
        on_surface = lambda p: np.abs(np.linalg.norm(p - centre, axis=1) - r)  # noqa: E731
    elif solid == "cylinder":
        start, end, r = centre - 120 * axes[2], centre + 120 * axes[2], 10.9
        prim, spread = Cylinder(start, end, r), 60.0  # 240 mm long: packed as several pieces
        inside = lambda p: inside_cylinder(p, start, end, r)  # noqa: E731

        def on_surface(p):
            a = axes[2]
            h = (p - start) @ a
            radial = np.linalg.norm((p - start) - h[:, None] * a, axis=1)
            return np.minimum(np.abs(radial - r), np.minimum(np.abs(h), np.abs(h - 240.0)))
    else:
        half = np.array([80.0, 40.0, 5.0])
        prim, spread = Box(centre, axes, half), 60.0
        inside = lambda p: inside_box(p, centre, axes, half)  # noqa: E731
        on_surface = lambda p: np.abs(np.abs((p - centre) @ axes.T) - half).min(axis=1)  # noqa: E731
    scene = Scene((SceneObject("solid", solid, "sphere", (prim,)),))
    o, d = random_rays_towards(rng, centre, spread, 4000)
    hits = scene.cast(o, d)
    hit = hits.object_index == 0
    assert 0.2 < hit.mean() < 0.99  # both hits and misses are exercised
    p = hits.point[hit]
    assert on_surface(p).max() < 1e-9
    # outward unit normal: facing the ray, and stepping along it leaves the solid
    n = hits.normal[hit]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert np.all(np.einsum("ij,ij->i", n, d[hit]) < 1e-12)
    assert not inside(p + 1e-6 * n).any() and inside(p - 1e-6 * n).all()
    # nothing of the solid lies on the ray before the hit; missed rays never enter it
    for frac in np.linspace(0.0, 0.999999, 40):
        assert not inside(o[hit] + frac * hits.t[hit][:, None] * d[hit]).any()
    far = o[~hit][:, None, :] + np.linspace(0, 1000, 400)[None, :, None] * d[~hit][:, None, :]
    assert not inside(far.reshape(-1, 3)).any()


def test_plane_is_two_sided_and_nearest_object_wins():
    scene = Scene((
        SceneObject("front", "sphere", "sphere", (Sphere([0, 0, 100], 10),), "1"),
        SceneObject("back", "background", "background", (Plane([0, 0, 200], [0, 0, 1]),)),
    ))
    d = np.array([[0, 0, 1.0], [0.3, 0, 1.0], [0, 0, -1.0]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hits = scene.cast(np.array([0.0, 0, 0]), d)
    assert hits.object_index.tolist() == [0, 1, -1]
    np.testing.assert_allclose(hits.normal[1], [0, 0, -1])  # faces the ray
    hits = scene.cast(np.array([0.0, 0, 300]), np.array([[0, 0, -1.0]]))
    assert hits.object_index.tolist() == [1]
    np.testing.assert_allclose(hits.normal[0], [0, 0, 1])


def two_sphere_artefact():
    art = Artefact(("A", "B"), [[0, 0, 0], [600, 0, 0]], [50.0, 50.0])
    rods = pd.DataFrame({"rod_id": ["r"], "sphere_a": ["A"], "sphere_b": ["B"]})
    return art, rods


def test_end_caps_and_tube_dimensions_from_materials(thesis_dir):
    hw = ArtefactHardware.from_materials(thesis_dir / "materials.yaml")
    assert (hw.tube_diameter_mm, hw.end_cap_diameter_mm, hw.end_cap_length_mm) == (21.8, 21.8, 25.0)
    art, rods = two_sphere_artefact()
    scene = artefact_scene(art, rods, Frame([0, 0, 0], [0, 0, 0]), hw)
    by_name = {o.name: o for o in scene.objects}
    assert set(by_name) == {"sphere:A", "sphere:B", "end_cap:r:A", "end_cap:r:B", "rod:r"}
    cap = by_name["end_cap:r:A"].primitives[0]
    seat = np.sqrt(25**2 - 10.9**2)
    np.testing.assert_allclose(cap.start, [seat, 0, 0])
    np.testing.assert_allclose(cap.end, [50, 0, 0])  # 25 mm out from the sphere surface
    tube = by_name["rod:r"].primitives[0]
    np.testing.assert_allclose([tube.start, tube.end], [[50, 0, 0], [550, 0, 0]])
    assert tube.radius == cap.radius == 10.9
    assert by_name["end_cap:r:B"].sphere_id == "B" and scene.sphere_ids == ("A", "B")


def test_end_cap_hides_the_sphere_surface_it_encloses(rng):
    art, rods = two_sphere_artefact()
    pose = Frame([100.0, -50.0, 20.0], [0.2, -0.4, 0.7])
    scene = artefact_scene(art, rods, pose)
    centre, other = pose.to_world(art.centres)
    axis = (other - centre) / np.linalg.norm(other - centre)
    # sphere surface points around the rod axis: inside the cap's radius or just outside
    u = np.cross(axis, [0, 0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    ang = rng.uniform(0, 2 * np.pi, 400)
    radial = rng.uniform(0.5, 16.0, 400)
    along = np.sqrt(25.0**2 - radial**2)
    surface = centre + along[:, None] * axis + radial[:, None] * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v)
    # look at each point from outside, square to the rod axis
    out = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v
    origins = surface + 400.0 * out
    hits = scene.cast(origins, -out)
    names = np.array(scene.names)[hits.object_index]
    under_cap = radial < 10.9
    assert np.all(names[under_cap] == "end_cap:r:A")
    assert np.all(names[~under_cap & (radial > 10.95)] == "sphere:A")
    # without the cap the same rays reach the sphere
    bare = scene.without("end_cap", "rod").cast(origins, -out)
    np.testing.assert_allclose(bare.point[under_cap], surface[under_cap], atol=1e-9)


def test_sphere_plate_pose_and_geometry(thesis_rig):
    scanner = thesis_rig.scanner("scanner1")
    centre = scanner.camera.pinhole + 2500.0 * scanner.camera.R[2]  # on the optical axis
    to_cam = scanner.camera.pinhole - centre
    to_prj = scanner.projector.pinhole - centre
    bisector = to_cam / np.linalg.norm(to_cam) + to_prj / np.linalg.norm(to_prj)
    bisector /= np.linalg.norm(bisector)
    plane_normal_of_axes = np.cross(to_cam, to_prj)
    plane_normal_of_axes /= np.linalg.norm(plane_normal_of_axes)
    for tilt, rot in [(0, 0), (np.radians(30), np.radians(-45)), (np.radians(70), np.radians(20))]:
        T = sphere_plate_pose(scanner, centre, tilt, rot)
        n = T.R[2]
        assert np.dot(n, bisector) == pytest.approx(np.cos(tilt) * np.cos(rot), abs=1e-12)
        assert abs(np.dot(n, plane_normal_of_axes)) == pytest.approx(np.sin(tilt), abs=1e-12)
        scene = sphere_plate_scene(T)
        sphere = scene.objects[0].primitives[0]
        np.testing.assert_allclose(sphere.centre, centre, atol=1e-12)
        assert sphere.radius == 10.0
        # the sphere centre is 50.645 mm from the plate's front face
        plate = scene.objects[1].primitives[0]
        front = plate.centre + plate.half_size[2] * n
        assert np.dot(centre - front, n) == pytest.approx(SPHERE_PLATE_SEPARATION_MM, abs=1e-12)
    # the camera sees sphere, plate and stalk at tilt 0
    small = scaled_scanner(scanner, 96)
    o, d = pixel_centre_rays(small)
    T = sphere_plate_pose(scanner, centre, 0.0, np.radians(20))
    seen = np.unique(sphere_plate_scene(T).cast(o, d).object_index, return_counts=True)
    assert dict(zip(*seen)).keys() == {-1, 0, 1, 2}


def test_scaled_cameras_keep_the_field_of_view(thesis_rig):
    rig = scaled_rig(thesis_rig, 256)
    for big, small in zip(thesis_rig.scanners, rig.scanners):
        assert small.camera.format.shape == (256, 256) and small.projector == big.projector
        np.testing.assert_array_equal(small.camera.params, big.camera.params)
        for corner_small, corner_big in (((0, 0), (0, 0)), ((255, 255), (2047, 2047)), ((127.5, 0), (1023.5, 0))):
            np.testing.assert_allclose(small.camera.image_mm(np.array(corner_small, float)),
                                       big.camera.image_mm(np.array(corner_big, float)), atol=1e-12)
    assert rig.reference == thesis_rig.reference


def test_an_empty_scene_renders_black(thesis_rig):
    m = render_measurement(scaled_scanner(thesis_rig.scanner("scanner2"), 32), Scene(()), RenderConfig().noise_free(),
                           np.random.default_rng(0), FringeSequence(fringe_counts=(8, 7), n_steps=3))
    assert m.frames.shape == (12, 32, 32) and not m.frames.any()
    assert (m.truth.object_index == -1).all() and np.isnan(m.truth.point).all()
