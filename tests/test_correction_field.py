"""The smooth correction field over each image plane (fringecal/lens/field.py) and the
sensor model ``field`` that adjusts it (calibration/models.py).

One simulated thesis rig (control points every 20 px at 2048 px, the thesis's noise;
about 3,150 points) whose truth sensors carry a degree-4 field of 0.7 um per term (3 um
RMS over the image, 0.4 camera pixels: a coefficient of the size the model's prior
expects, ``FIELD_PRIOR_MM``), and the same rig without.
"""

import json
from dataclasses import replace

import numpy as np
import pytest

from fringecal.calibration.bundle import BundleOptions
from fringecal.calibration.file import CalibrationFileError, read_calibration_xml, rig_from_dict, rig_to_dict, xml_text
from fringecal.calibration.model import BundleProblem, Evaluator
from fringecal.calibration.candidates import fit_model
from fringecal.calibration.models import choose_sensor_model
from fringecal.lens.field import CorrectionField, _absorbed, _monomials, field_terms, format_grid
from fringecal.pointcloud import triangulate_image_points
from fringecal.rig import Rig, Scanner
from fringecal.simulate.control_points import simulate_control_points, thesis_truth
from fringecal.triangulation import closest_approach

TERM_MM = 3e-3 / np.sqrt(19)
OPTIONS = BundleOptions(bootstrap_draws=0, start="given")


def _with_fields(rig, degree, scale, seed=3):
    rng = np.random.default_rng(seed)
    sensors = [s.with_field(CorrectionField.zero(s.format.width_mm, s.format.height_mm, degree)
                            .with_coefficients(rng.normal(size=field_terms(degree)) * scale)) for s in rig.sensors]
    return replace(rig, scanners=tuple(Scanner(sc.name, sensors[2 * i], sensors[2 * i + 1])
                                       for i, sc in enumerate(rig.scanners)))


def _problem(scale):
    rig, art, poses = thesis_truth()
    truth = _with_fields(rig, 4, scale)
    sim = simulate_control_points(truth, art, poses, spacing_px=20, rng=1)
    return BundleProblem.from_tables(rig, art, sim.control_points, poses), truth


@pytest.fixture(scope="module")
def field_fits():
    problem, truth = _problem(TERM_MM)
    first = fit_model(problem, OPTIONS, "brown14")
    richer = fit_model(problem.with_start(first.rig, first.poses), OPTIONS, "field")
    return problem, truth, first, richer


def test_basis_is_orthonormal_over_the_format_and_free_of_what_the_14_parameters_absorb():
    for w, h in ((15.1, 15.1), (19.0, 14.3)):
        f = CorrectionField.zero(w, h, 4)
        grid = format_grid(w, h)
        phi = f.basis(grid).reshape(-1, f.n_terms) / np.sqrt(len(grid))
        assert f.n_terms == 19
        np.testing.assert_allclose(phi.T @ phi, np.eye(19), atol=1e-12)
        absorbed = _monomials(grid / f.radius_mm, 4).reshape(-1, 30) @ _absorbed(4) / np.sqrt(len(grid))
        assert np.abs(absorbed.T @ phi).max() < 1e-10
        six = CorrectionField.zero(w, h, 6)
        assert six.n_terms == 45
        np.testing.assert_allclose(six.basis(grid)[..., :19], f.basis(grid), atol=1e-12)


def test_sensor_with_a_field_projects_and_back_projects_consistently():
    rig, _, _ = thesis_truth()
    cam = _with_fields(rig, 6, 5e-3).sensors[0]  # 34 um RMS: large, to test the inverse
    X = np.random.default_rng(1).normal(size=(200, 3)) * 150
    m = cam.project(X)
    o, d = cam.rays(m)
    assert np.abs(np.cross(X - o, d)).max() < 1e-9
    moved = np.linalg.norm(m - cam.with_field(None).project(X), axis=1)
    assert moved.max() > 0.02  # the field moved the image by tens of micrometres
    np.testing.assert_allclose(cam.field.corrected(cam.field.measured(m)), m, atol=1e-12)
    # the compiled 14-parameter kernels see the same rays through brown_image_mm
    sc = _with_fields(rig, 4, 5e-3).scanners[0]
    S = np.random.default_rng(2).normal(size=(50, 3)) * 100
    cam_mm, prj_mm = sc.camera.project(S), sc.projector.project(S)
    np.testing.assert_allclose(triangulate_image_points(sc.camera, sc.projector, cam_mm, prj_mm), S, atol=1e-8)
    o1, d1 = sc.camera.rays(cam_mm)
    o2, d2 = sc.projector.rays(prj_mm)
    np.testing.assert_allclose(closest_approach(o1, d1, o2, d2)[0], S, atol=1e-8)


def test_field_slots_of_the_kernels_match_finite_differences(field_fits):
    problem, _, _, richer = field_fits
    pr = replace(problem.thinned(7), rig=richer.rig)
    ev = Evaluator(pr, chunk_size=5)
    x = ev.layout.pack_rig(pr.rig, richer.poses)
    _, J, _ = ev.jacobian_rows(x)
    cols = ev.global_columns()
    worst = 0.0
    for i in np.flatnonzero([".field." in n for n in ev.layout.names])[::7]:
        h = 1e-6
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        fd = (ev.evaluate(xp, False).res - ev.evaluate(xm, False).res) / (2 * h)
        an = np.zeros_like(fd)
        for s in range(cols.shape[1]):
            sel = cols[:, s] == i
            an[sel] += J[sel, :, s]
        err = np.abs(fd - an).max() / np.abs(fd).max()
        worst = max(worst, err)
        assert err < 1e-6, f"{ev.layout.names[i]}: relative difference {err:.2e}"
    assert worst > 0


def test_field_model_recovers_the_truth_within_its_stated_u(field_fits):
    _, truth, first, richer = field_fits
    assert richer.rig.field_free.all() and richer.layout.n_field_terms == 19
    z = (richer.rig.fields - truth.fields) / richer.rig.field_uncertainty
    # 76 coefficients: RMS of z near 1, none beyond 4.5 (a 1-in-10,000 event for 76 normals)
    assert 0.7 < np.sqrt(np.mean(z ** 2)) < 1.5, z
    assert np.abs(z).max() < 4.5, z
    # the field takes a quarter of the residual the 14 parameters leave (the rest is noise)
    assert richer.after.rms_f_mm < 0.8 * first.after.rms_f_mm, (first.after.rms_f_mm, richer.after.rms_f_mm)


def test_held_out_measurements_choose_the_field_only_where_the_images_have_one(field_fits):
    problem, _, first, _ = field_fits
    opts = BundleOptions(bootstrap_draws=0, model_selection="always")
    _, record = choose_sensor_model(problem, opts, candidates=("brown14", "field"), first=first)
    assert record["model"] == "field", record["comparisons"]
    (cmp,) = record["comparisons"]
    assert cmp["gain"] > 0.2 and cmp["t"] > 3, cmp
    plain, _ = _problem(0.0)
    _, record = choose_sensor_model(plain, opts, candidates=("brown14", "field"))
    assert record["model"] == "brown14", record["comparisons"]
    assert record["comparisons"][0]["gain"] < 0, record["comparisons"]


def test_calibration_files_carry_the_field(field_fits, tmp_path):
    rig = field_fits[3].rig
    doc = json.loads(json.dumps(rig_to_dict(rig)))
    entry = doc["scanners"][0]["sensors"][0]["correction_field"]
    assert entry["degree"] == 4 and len(entry["coefficients"]) == 19 and "u" in entry["coefficients"]["f01"]
    back = rig_from_dict(doc)
    np.testing.assert_array_equal(back.fields, rig.fields)
    np.testing.assert_array_equal(back.field_uncertainty, rig.field_uncertainty)
    (tmp_path / "c.xml").write_text(xml_text(rig))
    np.testing.assert_array_equal(read_calibration_xml(tmp_path / "c.xml").fields, rig.fields)
    np.testing.assert_array_equal(Rig.from_frame(rig.to_frame()).fields, rig.fields)
    plain = thesis_truth()[0]
    assert "correction_field" not in json.dumps(rig_to_dict(plain)) and "field_degree" not in plain.to_frame()
    del doc["scanners"][1]["sensors"][1]["correction_field"]["coefficients"]["f07"]
    with pytest.raises(CalibrationFileError, match=r"scanner 'scanner2'.*P2.*f07"):
        rig_from_dict(doc, "cal.json")


def test_a_sensor_table_with_a_field_on_some_sensors_round_trips_and_names_a_bad_cell(tmp_path):
    import pandas as pd

    from fringecal.rig import load_rig
    from fringecal.schemas import TableError

    rig = thesis_truth()[0]
    one = _with_fields(rig, 4, 1e-3).sensors[0]
    partial = replace(rig, scanners=(Scanner("scanner1", one, rig.sensors[1]), rig.scanners[1]))
    partial.to_frame().to_csv(tmp_path / "rig.csv", index=False)
    back = load_rig(tmp_path / "rig.csv")
    np.testing.assert_array_equal(back.fields, partial.fields)
    assert [s.field is not None for s in back.sensors] == [True, False, False, False]
    df = pd.read_csv(tmp_path / "rig.csv").astype(object)
    df.loc[0, "field_f03_mm"] = "abc"
    df.to_csv(tmp_path / "bad.csv", index=False)
    with pytest.raises(TableError) as err:
        load_rig(tmp_path / "bad.csv")
    assert str(err.value).endswith("line 2, column 'field_f03_mm': value 'abc' is not a number"), str(err.value)


def test_a_length_budget_holds_the_field_coefficients_through_their_principal_point_derivative():
    """The centre's derivative by each correction-field coefficient (budget.sighting_model)
    against central differences of the re-triangulated, refitted sphere."""
    from fringecal.calibration.propagation import triangulate_mm
    from fringecal.verification.budget import SightingPoints, _refit, sighting_model

    rig = _with_fields(thesis_truth()[0], 4, 1e-3)
    sc = rig.scanners[0]
    centre, radius = np.array([0.0, 0.0, 0.0]), 25.0
    # the cap of a sphere that faces the camera: points on it, seen by both sensors
    rng = np.random.default_rng(4)
    towards = sc.camera.pinhole - centre
    towards /= np.linalg.norm(towards)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d @ towards > 0.5]
    X = centre + radius * d
    cam_mm, prj_mm = sc.camera.project(X), sc.projector.project(X)
    pts = SightingPoints(sc, 0, cam_mm, prj_mm, centre, radius, 0.01)
    model = sighting_model(pts, np.full(28, 1e-4))
    assert model.J_field.shape == (3, 38)
    h = 1e-5
    worst = 0.0
    for j in range(0, 38, 5):
        moved = []
        for sign in (1, -1):
            fields = rig.fields.copy()
            fields[j // 19, j % 19] += sign * h  # camera (sensor 0), then projector (sensor 1)
            s2 = rig.with_params(rig.params, fields=fields).scanners[0]
            moved.append(_refit(triangulate_mm(s2, cam_mm, prj_mm), centre, radius, iterations=6))
        fd = (moved[0] - moved[1]) / (2 * h)
        err = np.abs(fd - model.J_field[:, j]).max() / max(np.abs(fd).max(), 1e-9)
        worst = max(worst, np.abs(fd).max())
        assert err < 1e-3, (j, fd, model.J_field[:, j])
    assert worst > 1.0  # a micrometre on the image moves the centre by tens of micrometres


def test_the_monte_carlo_check_draws_the_field_coefficients_as_the_linear_budget_holds_them():
    from fringecal.calibration.propagation import FieldCovariances, ParameterCovariances
    from fringecal.verification.budget import SightingPoints, length_budget, monte_carlo_lengths, sighting_model

    rig = _with_fields(thesis_truth()[0], 4, 1e-3)
    sc = rig.scanners[0]
    rng = np.random.default_rng(5)
    sightings = []
    for centre in (np.array([-300.0, 0.0, 0.0]), np.array([300.0, 50.0, 0.0])):
        towards = sc.camera.pinhole - centre
        towards /= np.linalg.norm(towards)
        d = rng.normal(size=(600, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        X = centre + 25.0 * d[d @ towards > 0.5]
        pts = SightingPoints(sc, 0, sc.camera.project(X), sc.projector.project(X), centre, 25.0, 1e-9)
        sightings.append(sighting_model(pts, np.full(28, 1e-4)))
    n14, K = 14 * len(rig.sensors), 19
    # only the field coefficients uncertain (0.5 um each): the length's u comes from them alone
    C = np.zeros((n14 + K * len(rig.sensors),) * 2)
    C[n14:, n14:] = np.eye(K * len(rig.sensors)) * 5e-4 ** 2
    zero = np.zeros((n14, n14))
    cov = ParameterCovariances(zero, zero, np.zeros(n14), 0.0, FieldCovariances(C, np.zeros_like(C), np.zeros(len(C)), K))
    a, b = sightings
    u = length_budget(a, b, cov, 0.0, 0.0).u_mm["calibration"]
    L = monte_carlo_lengths(a.points, b.points, cov, 0.0, 0.0, 2000, np.random.default_rng(1))
    assert u > 1e-3  # micrometres on the image move a 600 mm length by micrometres
    assert np.std(L) == pytest.approx(u, rel=0.1), (np.std(L), u)


def test_weak_directions_leave_out_what_the_field_prior_holds_but_not_a_weak_pair_beside_it():
    """Columns a, b, c of free parameters and f, a field coefficient held by a prior: f
    mimics a (the field over a small observed region), b and c are nearly one parameter."""
    from fringecal.calibration.uncertainty import NEAR_SINGULAR, weak_directions

    rng = np.random.default_rng(0)
    t = rng.normal(size=(500, 4))
    J = np.column_stack([t[:, 0], t[:, 1], t[:, 1] + 1e-6 * t[:, 2], t[:, 0] + 1e-7 * t[:, 3]])
    N = J.T @ J
    N[3, 3] += 1e-8  # the prior's lambda: a and f are told apart by it alone
    names = ["a", "b", "c", "f"]
    weak = {frozenset(w.parameters): w.ratio for w in weak_directions(N, names)[0]}
    assert set(weak) == {frozenset("af"), frozenset("bc")} and max(weak.values()) < NEAR_SINGULAR, weak
    held, _ = weak_directions(N, names, regularised=np.array([False, False, False, True]))
    assert [set(w.parameters) for w in held] == [{"b", "c"}], held
    # the b-c direction keeps its ratio (within 10 %: a is independent of it; only the
    # largest eigenvalue, which the ratio divides by, changes with the columns left)
    assert abs(held[0].ratio / weak[frozenset("bc")] - 1) < 0.1, (held[0].ratio, weak)
