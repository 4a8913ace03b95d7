"""Task-specific length uncertainty: the artefact sensitivity against re-adjustment, the
linear propagation against brute force and Monte Carlo, the decision rule."""

from dataclasses import replace

import numpy as np
import pytest

from fringecal.calibration.artefact_sensitivity import artefact_sensitivity
from fringecal.calibration.bundle import BundleOptions, bundle_adjust
from fringecal.calibration.model import BundleProblem
from fringecal.calibration.propagation import ParameterCovariances, sensor_covariance
from fringecal.rig import Scanner
from fringecal.simulate.control_points import simulate_control_points, thesis_truth
from fringecal.verification.budget import (
    SightingPoints,
    _draw_sqrt,
    length_budget,
    monte_carlo_lengths,
    numerical_tolerance,
    refitted_length,
    sighting_model,
    validate_linear,
)
from fringecal.verification.uncertainty import iso14253_verdict


@pytest.fixture(scope="module")
def adjusted():
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, spacing_px=20, rng=21)
    return sim, bundle_adjust(BundleProblem.from_tables(rig, art, sim.control_points, poses),
                              BundleOptions(start="given"))


def _readjust(result, artefact, sim):
    pr = BundleProblem.from_tables(result.rig, artefact, sim.control_points,
                                   result.problem.poses_frame(result.poses))
    return bundle_adjust(pr, BundleOptions(start="given"))


def test_artefact_sensitivity_predicts_the_readjusted_calibration(adjusted):
    """The implicit-function sensitivity against adjusting again with a changed table:
    a 50 ppm scale (the calibration's response is linear in it: agreement to 1e-3 of
    the largest change) and a random 10 um change of every centre and 5 um of every
    radius (agreement to 10 % in units of each parameter's uncertainty)."""
    sim, res = adjusted
    art = res.problem.artefact
    sens = artefact_sensitivity(res)
    c = art.centres.mean(0)
    s = 50e-6
    scaled = replace(art, centres=c + (art.centres - c) * (1 + s), diameters=art.diameters * (1 + s))
    dx = _readjust(res, scaled, sim).x - res.x
    assert np.abs(dx - s * sens.scale).max() < 1e-3 * np.abs(dx).max()
    da = np.random.default_rng(1).normal(0, 0.01, (len(art.ids), 4))
    da[:, 3] *= 0.5
    moved = replace(art, centres=art.centres + da[:, :3], diameters=art.diameters + 2 * da[:, 3])
    dx = (_readjust(res, moved, sim).x - res.x) / res.uncertainty.std
    pred = sens.S @ da.reshape(-1) / res.uncertainty.std
    assert np.linalg.norm(dx - pred) < 0.1 * np.linalg.norm(dx)
    # the CMM covariance is S diag(u^2) S^T with the table's 10 um per coordinate
    assert sens.u_artefact[:4] == pytest.approx([0.01, 0.01, 0.01, 0.005])
    assert np.allclose(sens.covariance_cmm, (sens.S * sens.u_artefact**2) @ sens.S.T)


def _sightings(rig, rng, n=1500, noise_mm=0.05):
    """Sphere A seen by scanner1, B by scanner2 (the thesis's set-up), about a metre apart:
    the true surface points' camera pixels and projector phases, the phases with noise
    equivalent to ``noise_mm`` along the normal."""
    centres = {"A": np.array([-222.4, 138.9, 10.5]), "B": np.array([-1230.9, 146.7, 130.3])}
    out = {}
    for block, (sid, scanner) in enumerate(zip("AB", rig.scanners)):
        c = centres[sid]
        view = scanner.camera.pinhole - c
        view /= np.linalg.norm(view)
        u = rng.normal(size=(8 * n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        u = u[u @ view > 0.5][:n]
        X = c + 25.425 * u
        cam = scanner.camera.project(X)
        prj = scanner.projector.project(X)
        out[sid] = (SightingPoints(scanner, block, cam, prj, c, 25.425, noise_mm), X, u)
    return out


def _with_noise(s: SightingPoints, X, u, rng, sd_mm=0.05):
    """The sighting as measured: points moved along the normal by ``sd_mm``, re-imaged in
    the projector (phase noise), triangulated, the centre fitted and the fit's RMS kept."""
    from fringecal.verification.budget import _refit, triangulate_mm

    prj = s.scanner.projector.project(X + u * rng.normal(0, sd_mm, len(X))[:, None])
    P = triangulate_mm(s.scanner, s.cam_mm, prj)
    c = _refit(P, s.centre, s.radius_mm)
    rms = float(np.sqrt(np.mean((np.linalg.norm(P - c, axis=1) - s.radius_mm) ** 2)))
    return replace(s, prj_mm=prj, centre=c, rms_mm=rms)


def test_linear_budget_against_repeated_measurements_and_monte_carlo():
    """Two sightings with 50 um point noise and a calibration covariance of the thesis
    rig (from a synthetic adjustment): the fits' term against the scatter of 200
    repeated noisy measurements (within 15 %: 200 repeats scatter by 5 %), the
    calibration term against the scatter of lengths re-measured with parameters drawn
    from the covariance (within 15 %), and Monte Carlo against linear within 10 %."""
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, spacing_px=20, rng=21)
    res = bundle_adjust(BundleProblem.from_tables(rig, art, sim.control_points, poses), BundleOptions(start="given"))
    C = sensor_covariance(res.layout.sensor_index, res.uncertainty.covariance)
    cov = ParameterCovariances(C, np.zeros_like(C), np.zeros(len(C)), 0.0)
    rng = np.random.default_rng(5)
    sights = _sightings(res.rig, rng)
    std = np.sqrt(np.diag(C))
    measured = {k: _with_noise(*v, rng) for k, v in sights.items()}
    models = {k: sighting_model(s, std[28 * s.block:28 * s.block + 28]) for k, s in measured.items()}
    budget = length_budget(models["A"], models["B"], cov, 0.0, 0.0)
    assert budget.length_mm == pytest.approx(np.linalg.norm(measured["A"].centre - measured["B"].centre))
    lengths = [refitted_length(_with_noise(*sights["A"], rng), _with_noise(*sights["B"], rng),
                               np.r_[res.rig.params[0], res.rig.params[1]], np.r_[res.rig.params[2], res.rig.params[3]])
               for _ in range(200)]
    assert np.std(lengths) == pytest.approx(budget.u_mm["sphere fits"], rel=0.15)
    F = _draw_sqrt(C)
    drawn = []
    for _ in range(200):
        p = res.rig.params.reshape(-1) + F @ rng.standard_normal(F.shape[1])
        drawn.append(refitted_length(sights["A"][0], sights["B"][0], p[:28], p[28:]))
    assert np.std(drawn) == pytest.approx(budget.u_mm["calibration"], rel=0.15)
    samples = monte_carlo_lengths(measured["A"], measured["B"], cov, 0.0, 0.0, 1000, rng)
    check = validate_linear(budget.length_mm, budget.combined_mm, 2.0, samples)
    assert check["ratio"] == pytest.approx(1.0, abs=0.1)
    assert abs(np.mean(samples) - budget.length_mm) < 3 * check["u_mc_mm"] / np.sqrt(1000) + 1e-6
    # the points were imaged with the adjusted rig itself: only the fits' noise is in the length
    true_length = np.linalg.norm(sights["A"][0].centre - sights["B"][0].centre)
    assert abs(budget.length_mm - true_length) < 4 * budget.u_mm["sphere fits"]


def test_draws_keep_parameters_of_very_different_scales():
    """A covariance with variances from 1 to 1e-20 (mm^2 of a position, k3) and strong
    correlation: the factor reproduces it to 1e-9 of each variance."""
    sd = np.array([1.0, 1e-3, 1e-10, 1e-6])
    R = np.array([[1, 0.99, 0.5, 0], [0.99, 1, 0.4, 0], [0.5, 0.4, 1, 0.2], [0, 0, 0.2, 1]])
    C = R * np.outer(sd, sd)
    F = _draw_sqrt(C)
    assert np.allclose((F @ F.T) / np.outer(sd, sd), R, atol=1e-9)


def test_iso14253_decision_rule_and_tolerance():
    assert iso14253_verdict(0.030, 0.020, 0.1) == "conformance"
    assert iso14253_verdict(-0.085, 0.020, 0.1) == "uncertainty zone"
    assert iso14253_verdict(0.125, 0.020, 0.1) == "non-conformance"
    assert iso14253_verdict(0.115, 0.020, 0.1) == "uncertainty zone"
    assert iso14253_verdict(float("nan"), 0.02, 0.1) == "uncertainty zone"
    # JCGM 101 7.9.2: u = 0.0123 mm written 1.2e-2 -> tolerance half of 1e-3
    assert numerical_tolerance(0.0123) == pytest.approx(0.0005)
    assert numerical_tolerance(0.0123, 1) == pytest.approx(0.005)


def test_point_uncertainty_map_against_drawn_calibrations(thesis_rig):
    """A 64 x 64 measurement of a surface 2.6 m away: the map's u against the scatter of
    the points triangulated with 400 parameter sets drawn from the covariance (within
    15 % per point: 400 draws scatter a standard deviation by 3.5 %)."""
    from fringecal.calibration.propagation import point_uncertainty_map, triangulate_mm
    from fringecal.rig import scaled_scanner

    sc = scaled_scanner(thesis_rig.scanners[0], 64)
    rng = np.random.default_rng(3)
    sd = np.r_[[0.2, 0.2, 0.2, 2e-4, 2e-4, 2e-4, 0.01, 0.01, 0.02], np.zeros(5)]
    cov = np.diag(np.r_[sd, sd] ** 2)
    v, u = np.mgrid[0:64, 0:64]
    o, d = sc.camera.rays(sc.camera.image_mm(np.stack([u, v], axis=-1).reshape(-1, 2).astype(float)))
    X = o + 2600.0 * d  # every pixel's point 2.6 m along its ray
    tau = sc.projector.measured(sc.projector.project(X))
    tx, ty = tau[:, 0].reshape(64, 64), tau[:, 1].reshape(64, 64)
    tx[~(np.abs(tx) < np.pi)], ty[~(np.abs(ty) < np.pi)] = np.nan, np.nan  # outside the SLM: no light
    ok = np.isfinite(tx) & np.isfinite(ty)
    ok[:, :32] = False  # half the image measured
    assert ok.sum() > 1000
    m = point_uncertainty_map(sc, cov, tx, ty, ok)
    assert np.isnan(m.u_mm.values[:, :32]).all() and np.isfinite(m.u_mm.values[ok]).all()
    r, c = np.nonzero(ok)
    r, c = r[::37], c[::37]
    cam = sc.camera.image_mm(np.stack([c, r], axis=-1).astype(float))
    prj = sc.projector.image_mm(np.stack([tx[r, c], ty[r, c]], axis=-1))
    p0 = np.r_[sc.camera.params, sc.projector.params]
    pts = np.array([triangulate_mm(Scanner(sc.name, sc.camera.with_params(p[:14]), sc.projector.with_params(p[14:])),
                                   cam, prj) for p in p0 + rng.normal(size=(400, 28)) * np.r_[sd, sd]])
    empirical = np.sqrt(pts.var(axis=0).sum(axis=1))
    assert np.allclose(empirical, m.u_mm.values[r, c], rtol=0.15)


def test_length_cross_validation_calls_model_error_only_when_the_points_agree_it_is_there(thesis_rig):
    """Two half-calibrations whose scanner2 projector differs by 20 um in its principal
    point while they state 1e-7 of every parameter: the lengths disagree far beyond that. The
    check states the excess only when the points' cross-validation also says model error;
    with the points consistent the lengths' verdict is inconclusive and states none."""
    import pandas as pd

    from fringecal.verification.uncertainty import _cross_validated

    rng = np.random.default_rng(8)
    sights = _sightings(thesis_rig, rng)
    std = np.full(56, 1e-4)  # the derivatives' step scale
    models = {("p", s.scanner.name, k): sighting_model(s, std[:28]) for k, (s, _, _) in sights.items()}
    lengths = pd.DataFrame({"position": ["p"], "scanner_a": [sights["A"][0].scanner.name],
                            "scanner_b": [sights["B"][0].scanner.name]})
    params = thesis_rig.params.copy()
    shifted = params.copy()
    shifted[3, 6] += 0.02
    cov = np.diag((1e-7 * np.abs(params.reshape(-1))) ** 2)  # tiny against every parameter's size
    halves = {"params_a": params, "params_b": shifted, "covariance_a": cov, "covariance_b": cov}
    found = _cross_validated(models, lengths, halves, 56, ("A", "B"), "model error")
    d = found["lengths"][0]["difference_mm"]
    assert abs(d) > 0.005 and found["verdict"] == "model error"
    assert found["halves_excess_mm"] == pytest.approx(
        np.sqrt(max(d**2 - found["lengths"][0]["u_predicted_mm"]**2, 0) / 2))
    contradicted = _cross_validated(models, lengths, halves, 56, ("A", "B"), "consistent")
    assert contradicted["verdict"] == "inconclusive" and contradicted["halves_excess_mm"] == 0.0


def test_a_monte_carlo_disagreement_is_stated_with_its_numbers_in_the_summary_and_the_report():
    """A length whose Monte Carlo distribution is wider than its linear u (25 um against
    20 um, 4000 draws): the check disagrees, and the line the console, the log and the
    report print carries both intervals, the ends' distance and the tolerance."""
    from fringecal.report.sections.budget import length_budget as report_budget
    from fringecal.run.summary import ballbar_summary
    from fringecal.verification.uncertainty import _mc_summary

    y, u = 1015.65, 0.020
    samples = y + np.random.default_rng(4).normal(0, 0.025, 4000)
    mc = validate_linear(y, u, 2.0, samples)
    assert not mc["agree"] and mc["d_high_mm"] > mc["tolerance_mm"]
    entry = {"measurement": "bb07", "error_mm": 0.0, "length_mm": y, "u_mm": u, "U_mm": 2 * u, "budget_mm": {},
             "iso14253": "conformance", "covered": True, "monte_carlo": mc}
    unc = {"coverage_factor": 2.0, "lengths": [entry], "budget": {}, "not_covered": [],
           "monte_carlo": _mc_summary([entry])}
    line = unc["monte_carlo"]["disagreements"][0]
    lo, hi = mc["mc_interval_mm"]
    assert line.startswith("bb07: linear interval [1015.6100, 1015.6900] mm, Monte Carlo [")
    assert f"[{lo:.4f}, {hi:.4f}] mm (4000 draws)" in line and "u 20.0 um linear, 2" in line
    assert f"tolerance {1000 * mc['tolerance_mm']:.1f} um" in line
    assert report_budget(unc)["disagreements"] == [line]
    verification = {"calibrated": {"reference_length_mm": y, "max_abs_error_mm": 0.0, "volume_diagonal_mm": 2638.0,
                                   "one_part_in": 1e6, "mpe_mm": 0.1, "pass": True, "mean_length_mm": y,
                                   "positions": [{"measurement": "bb07", "error_mm": 0.0}],
                                   "uncertainty": {"expanded_mm": 0.01, "coverage_factor": 2.0}},
                    "uncertainty": unc, "failures": []}
    assert ballbar_summary(verification)["monte_carlo_disagreements"] == [line]
