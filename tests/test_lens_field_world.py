"""The simulation's lens field (``simulate.errors.lens_field_rms_um``): every true camera
and projector gets a degree-6 correction field, and every observation path of the
simulator -- the renderer (camera rays, projector coordinates, decoded phases) and the
control-point simulator -- sees exactly what the truth sensors with that field predict,
while the rig the calibration starts from never holds it."""

import numpy as np
import pandas as pd
import pytest

from fringecal.fringe.decode import DecodeSettings, decode
from fringecal.fringe.sequence import FringeSequence
from fringecal.lens.field import format_grid
from fringecal.rig import scaled_scanner
from fringecal.simulate import RenderConfig, artefact_scene, backdrop, render_measurement
from fringecal.simulate import geometry as g
from fringecal.simulate.control_points import simulate_control_points
from fringecal.simulate.errors import REALISTIC, SimulationErrors
from fringecal.simulate.unmodelled import LENS_FIELD_DEGREE
from fringecal.simulate.world import render_errors, sensor_lens_field, with_lens_fields

RMS_UM = 3.0
ERRORS = SimulationErrors(lens_field_rms_um=RMS_UM, seed=2)
SEQ = FringeSequence()


@pytest.fixture(scope="module")
def scanner(thesis_rig):
    return scaled_scanner(thesis_rig.scanner("scanner1"), 96)


@pytest.fixture(scope="module")
def scene(thesis_artefact, pose1, scanner):
    return artefact_scene(thesis_artefact, None, pose1, background=backdrop(scanner, 3500.0))


@pytest.fixture(scope="module")
def rendered(scanner, scene):
    """(errors, with the field, without): noise-free renders, 16 bits, one sample per pixel."""
    cfg = RenderConfig(bit_depth=16).ideal()
    errs = render_errors(ERRORS, scanner)
    with_field = render_measurement(scanner, scene, cfg, np.random.default_rng(0), SEQ, errs)
    without = render_measurement(scanner, scene, cfg, np.random.default_rng(0), SEQ)
    return errs, with_field, without, cfg


def _rms_mm(field):
    f = field.value(format_grid(field.width_mm, field.height_mm))
    return float(np.sqrt(np.mean(np.sum(f ** 2, axis=-1))))


def test_each_true_sensor_gets_a_seeded_degree_6_field_of_the_stated_rms(thesis_rig):
    fields = {s.name: sensor_lens_field(ERRORS, s) for s in thesis_rig.sensors}
    for s in thesis_rig.sensors:
        f = fields[s.name]
        assert (f.degree, f.n_terms) == (LENS_FIELD_DEGREE, 45)
        assert (f.width_mm, f.height_mm) == (s.format.width_mm, s.format.height_mm)
        assert _rms_mm(f) == pytest.approx(RMS_UM * 1e-3, rel=1e-12)  # the basis is orthonormal on that grid
        # the same for the same seed and sensor, at any pixel count; another seed, another field
        np.testing.assert_array_equal(sensor_lens_field(ERRORS, scaled_scanner(
            thesis_rig.scanner("scanner1"), 96).camera).coefficients, fields["C1"].coefficients)
        assert not np.allclose(sensor_lens_field(SimulationErrors(lens_field_rms_um=RMS_UM, seed=3), s).coefficients,
                               f.coefficients)
    assert len({f.coefficients.tobytes() for f in fields.values()}) == len(fields)  # one field per sensor
    # equal variance over the 45 terms: on average 19/45 of the energy is the degree-4 model's
    share = np.mean([np.sum(f.coefficients[:19] ** 2) / np.sum(f.coefficients ** 2) for f in fields.values()])
    assert 0.15 < share < 0.75  # 4 draws of a ratio with mean 0.42
    assert sensor_lens_field(SimulationErrors(), thesis_rig.sensors[0]) is None
    assert not SimulationErrors(lens_field_rms_um=0.5).is_ideal
    assert REALISTIC["lens_field_rms_um"] == 0.0  # not in the realistic preset: its lens error is the thin prism


def test_the_calibration_rig_never_gets_the_field(thesis_rig, scanner):
    assert not any(s.has_field for s in thesis_rig.sensors)
    truth = with_lens_fields(thesis_rig, ERRORS)
    assert all(s.has_field for s in truth.sensors)
    assert not any(s.has_field for s in thesis_rig.sensors)  # a new rig, the given one untouched
    assert with_lens_fields(thesis_rig, SimulationErrors()) is thesis_rig
    errs = render_errors(ERRORS, scanner)
    assert not scanner.camera.has_field and errs.camera_field is not None and errs.projector_field is not None


def test_kernel_pack_projects_and_casts_rays_exactly_as_the_sensor(thesis_rig):
    """The compiled sensor model with a field (geometry.sensor_pack) against
    Sensor.project / Sensor.rays, at 200 points over the native formats."""
    rng = np.random.default_rng(7)
    for s in thesis_rig.scanner("scanner2").sensors:
        sf = s.with_field(sensor_lens_field(ERRORS, s))
        pack = g.sensor_pack(sf)
        assert len(g.sensor_pack(s)) == g.PACK_SIZE and len(pack) > g.PACK_SIZE
        m = s.format.pixel_to_mm(rng.uniform(0, [s.format.width_px - 1, s.format.height_px - 1], (200, 2)))
        o, d = sf.rays(m)
        X = o + 2600.0 * d
        kernel = np.array([g.project_point(*x, pack)[:2] for x in X])
        np.testing.assert_allclose(kernel, m, rtol=0, atol=1e-12)  # mm: the fixed point returns to m
        np.testing.assert_allclose(kernel, sf.project(X), rtol=0, atol=1e-12)
        for x, mm in zip(X[:40], m[:40]):
            dx, dy, dz, ok, _, _ = g.image_ray(mm[0], mm[1], pack, 0.0, 0.0)
            v = (x - s.pinhole) / np.linalg.norm(x - s.pinhole)
            assert ok and np.linalg.norm(np.cross(v, [dx, dy, dz])) < 1e-11
        # and the field is what the 14 parameters alone get wrong: micrometres
        shift = np.linalg.norm(s.project(X) - m, axis=1)
        assert 1e-4 < np.sqrt(np.mean(shift ** 2)) < 1e-2


def test_rendered_and_decoded_phases_follow_the_truth_sensors_with_the_field(rendered, scanner):
    errs, m, ideal, cfg = rendered
    cam, prj = errs.sensors(scanner)
    lit = m.truth.light == 1
    assert lit.sum() > 2000
    rows, cols = np.nonzero(lit)
    pixels_mm = cam.format.pixel_to_mm(np.stack([cols, rows], axis=1).astype(float))
    P = m.truth.point[lit]
    # the camera ray of each pixel, corrected by the camera's field, hits the rendered point
    o, d = cam.rays(pixels_mm)
    miss = np.linalg.norm(np.cross(P - o, d), axis=1)
    assert miss.max() < 1e-6  # mm, at ~2.6 m
    # without the camera's field the same point images m - f(m) (micrometres away)
    np.testing.assert_allclose(scanner.camera.project(P), cam.field.corrected(pixels_mm), rtol=0, atol=1e-9)
    # the rendered projector coordinates are the truth projector's measured ones
    rendered_tau = np.stack([m.truth.tau_x_centre[lit], m.truth.tau_y_centre[lit]], axis=1)
    np.testing.assert_allclose(rendered_tau, prj.measured(prj.project(P)), rtol=0, atol=1e-10)
    # ... which differ from the 14-parameter projector's by its field there, ~ the field's size
    plain = prj.image_mm(prj.measured(scanner.projector.project(P)))
    diff = prj.image_mm(rendered_tau) - plain
    np.testing.assert_allclose(diff, prj.field.value(prj.image_mm(rendered_tau)), rtol=0, atol=1e-9)
    rms_um = 1e3 * np.sqrt(np.mean(np.sum(diff ** 2, axis=1)))
    assert 0.3 * RMS_UM < rms_um < 3 * RMS_UM
    # the whole world moved: against the render without the field, the same pixels'
    # projector coordinates moved by micrometres on the SLM (both fields together)
    both = lit & (ideal.truth.light == 1) & (ideal.truth.centre_object_index == m.truth.centre_object_index)
    moved = prj.image_mm(np.stack([m.truth.tau_x_centre[both] - ideal.truth.tau_x_centre[both],
                                   m.truth.tau_y_centre[both] - ideal.truth.tau_y_centre[both]], axis=1))
    moved_um = 1e3 * np.sqrt(np.mean(np.sum(moved ** 2, axis=1)))
    assert 0.3 * RMS_UM < moved_um < 10 * RMS_UM
    # decoded phases of the noise-free frames: the truth with the field, well within its size
    dec = decode(m.frames, SEQ, DecodeSettings(phase_ripple="off"), full_scale=cfg.max_dn)
    pure = lit & dec.valid & (m.truth.purity == 1)
    assert pure.sum() > 2000
    err = np.stack([dec.tau["x"][pure] - m.truth.tau_x[pure], dec.tau["y"][pure] - m.truth.tau_y[pure]], axis=1)
    field_rad = np.stack([m.truth.tau_x[pure] - ideal.truth.tau_x[pure],
                          m.truth.tau_y[pure] - ideal.truth.tau_y[pure]], axis=1)
    rms_err, rms_field = np.sqrt(np.mean(err ** 2)), np.sqrt(np.nanmean(field_rad ** 2))
    assert rms_err < 2e-6  # rad (16-bit, noise-free: ~4e-7); the field moves tau by ~1e-3 rad
    assert rms_field > 100 * rms_err


def test_control_points_follow_the_truth_sensors_with_the_field(thesis_rig, thesis_artefact, thesis_dir):
    poses = pd.read_csv(thesis_dir / "poses_scanner1_table6-1.csv").iloc[:2]
    truth = with_lens_fields(thesis_rig, ERRORS)
    sim = simulate_control_points(truth, thesis_artefact, poses, spacing_px=20, noise_eps1_mm=0.0)
    plain = simulate_control_points(thesis_rig, thesis_artefact, poses, spacing_px=20, noise_eps1_mm=0.0)
    cp = sim.control_points
    assert len(cp) > 400
    for name in ("scanner1", "scanner2"):
        sel = (cp["scanner"] == name).to_numpy()
        cam, prj = truth.scanner(name).sensors
        uv = cp.loc[sel, ["u_px", "v_px"]].to_numpy(float)
        tau = cp.loc[sel, ["tau_x_rad", "tau_y_rad"]].to_numpy(float)
        X = sim.points_world[sel]
        np.testing.assert_allclose(tau, prj.measured(prj.project(X)), rtol=0, atol=1e-12)
        o, d = cam.rays(cam.image_mm(uv))
        assert np.linalg.norm(np.cross(X - o, d), axis=1).max() < 1e-6
        # the plain rig's control points at the same pixels: moved by both fields
        key = ["measurement", "sphere_id", "u_px", "v_px"]
        psel = plain.control_points["scanner"] == name
        joined = cp[sel].merge(plain.control_points[psel], on=key, suffixes=("", "_plain"))
        assert len(joined) > 0.9 * sel.sum()
        moved = prj.image_mm(joined[["tau_x_rad", "tau_y_rad"]].to_numpy()) \
            - prj.image_mm(joined[["tau_x_rad_plain", "tau_y_rad_plain"]].to_numpy())
        moved_um = 1e3 * np.sqrt(np.mean(np.sum(moved ** 2, axis=1)))
        assert 0.3 * RMS_UM < moved_um < 10 * RMS_UM
