"""Sphere and plane fits checked the way ISO 10360-6 checks CMM software."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from fringecal.spheres.fit import FitError, PlaneModel, SphereModel
from fringecal.spheres.reference_data import plane_reference_data, reference_suite, sphere_reference_data

SUITE = reference_suite(seed=7)


def test_reference_data_are_exact_least_squares_optima():
    for ds in SUITE:
        if ds.kind == "sphere":
            u = (ds.points - ds.centre) / np.linalg.norm(ds.points - ds.centre, axis=1, keepdims=True)
            grad = np.r_[ds.residuals @ u, ds.residuals.sum()]  # J^T e with J = [-u, -1]
            assert np.abs(grad).max() < 1e-12 * max(1.0, np.abs(ds.residuals).sum()), ds.name
        else:
            rel = ds.points - ds.point
            in_plane = rel - np.outer(rel @ ds.normal, ds.normal)
            assert np.abs(ds.residuals.sum()) < 1e-12 and np.abs(in_plane.T @ ds.residuals).max() < 1e-9, ds.name
        noise = float(ds.name.split("noise=")[1].rstrip("mm"))
        assert np.sqrt(np.mean(ds.residuals**2)) == pytest.approx(noise, rel=1e-12, abs=1e-15)


@pytest.mark.parametrize("fixed", [False, True])
def test_sphere_fits_reproduce_reference_solutions_within_0_1_um(fixed):
    """Full spheres, 70 and 35 degree caps, R 25 and 10 mm, offsets 0..1e4 mm, noise 0..0.1 mm."""
    cases = [ds for ds in SUITE if ds.kind == "sphere"]
    assert len(cases) == 48
    for ds in cases:
        fit = SphereModel.from_estimate(ds.points, radius=ds.radius if fixed else None)
        assert np.abs(fit.centre - ds.centre).max() < 1e-4, ds.name
        assert abs(fit.radius - ds.radius) < 1e-4, ds.name
        # the fit's residuals are the constructed ones: it found the exact optimum
        np.testing.assert_allclose(fit.residuals(ds.points), ds.residuals, atol=1e-7)


def test_plane_fits_reproduce_reference_solutions():
    """Position within 0.1 um, normal within 1e-7 rad, offsets up to 1e4 mm."""
    cases = [ds for ds in SUITE if ds.kind == "plane"]
    assert len(cases) == 12
    for ds in cases:
        fit = PlaneModel.from_estimate(ds.points, toward=ds.point + ds.normal)
        angle = np.arctan2(np.linalg.norm(np.cross(fit.normal, ds.normal)), fit.normal @ ds.normal)
        assert angle < 1e-7, ds.name
        assert abs((fit.point - ds.point) @ ds.normal) < 1e-4, ds.name  # plane position
        assert abs(fit.offset - ds.point @ ds.normal) < 1e-4, ds.name
        np.testing.assert_allclose(fit.residuals(ds.points), ds.residuals, atol=1e-7)


@pytest.mark.parametrize("fixed", [False, True])
def test_identical_to_full_geometric_least_squares(fixed):
    """Few Gauss-Newton steps from the algebraic start = the full geometric fit: scipy's
    Levenberg-Marquardt from a start 0.5 mm off, its stopping slack (gradient ~1e-7)
    then polished by QR-solved Gauss-Newton steps on the full Jacobian."""
    rng = np.random.default_rng(11)
    for trial in range(5):
        centre = rng.uniform(-2000, 2000, 3)
        ds = sphere_reference_data(centre, 25.0, 3000, rng.uniform(30, 90), rng.normal(size=3), 0.0, seed=trial)
        pts = ds.points + rng.normal(0, 0.03, ds.points.shape)
        fit = SphereModel.from_estimate(pts, radius=25.0 if fixed else None)
        npar = 3 if fixed else 4

        def residuals_and_jacobian(x):
            d = pts - x[:3]
            dist = np.linalg.norm(d, axis=1)
            J = np.c_[-d / dist[:, None], -np.ones(len(d))][:, :npar]
            return dist - (25.0 if fixed else x[3]), J

        x0 = np.r_[centre + 0.5, 24.0][:npar]
        ref = least_squares(lambda x: residuals_and_jacobian(x)[0], x0, method="lm",
                            xtol=1e-15, ftol=1e-15, gtol=1e-15).x
        for _ in range(5):
            r, J = residuals_and_jacobian(ref)
            ref = ref + np.linalg.lstsq(J, -r, rcond=None)[0]
        np.testing.assert_allclose(fit.params[:npar], ref, atol=1e-9, rtol=0)
        r, J = residuals_and_jacobian(fit.params[:npar])
        assert np.abs(J.T @ r).max() < 1e-8  # the gradient of the sum of squares vanishes
        assert fit.iterations <= 8


def test_covariance_predicts_the_scatter_of_centres():
    rng = np.random.default_rng(5)
    centres, predicted = [], []
    for k in range(200):
        ds = sphere_reference_data([0, 0, 2500], 25.0, 400, 70.0, (0, 0, 1), 0.0, seed=k)
        u = (ds.points - ds.centre) / 25.0
        pts = ds.points + rng.normal(0, 0.02, (400, 1)) * u
        fit = SphereModel.from_estimate(pts)
        centres.append(fit.centre)
        predicted.append(fit.centre_uncertainty)
    sd = np.std(centres, axis=0, ddof=1)
    ratio = sd / np.mean(predicted, axis=0)
    assert np.all((ratio > 0.8) & (ratio < 1.2)), ratio
    # along the cap axis the centre is worst determined
    assert sd[2] > 2 * sd[0]


def test_angular_coverage():
    full = SphereModel.from_estimate(sphere_reference_data([0, 0, 0], 25, 5000, 180, seed=1).points)
    assert full.cap_angle_rad > 3.0 and full.coverage > 0.95  # directions surround the centre
    half = SphereModel.from_estimate(sphere_reference_data([0, 0, 0], 25, 5000, 90, (0, 0, 1), seed=1).points)
    assert half.cap_angle_rad == pytest.approx(np.pi / 2, abs=0.05)  # about the sample mean direction
    assert half.coverage == pytest.approx(0.5, abs=0.05)


def test_bad_point_sets_raise_fit_error():
    with pytest.raises(FitError, match="at least 4"):
        SphereModel.from_estimate(np.zeros((3, 3)))
    with pytest.raises(FitError, match="not finite"):
        SphereModel.from_estimate([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.nan], [1, 1, 1]])
    flat = np.c_[np.random.default_rng(0).uniform(-10, 10, (50, 2)), np.zeros(50)]
    with pytest.raises(FitError, match="do not determine a sphere|singular"):
        SphereModel.from_estimate(flat)
    with pytest.raises(FitError, match="collinear"):
        PlaneModel.from_estimate(np.outer(np.arange(10.0), [1, 2, 3]))
    with pytest.raises(FitError, match=r"shape \(n, 3\)"):
        SphereModel.from_estimate(np.zeros((10, 2)))


def test_plane_distance_uncertainty_matches_monte_carlo():
    rng = np.random.default_rng(9)
    probe = np.array([30.0, -20.0, 50.0])
    dists, predicted = [], []
    for k in range(300):
        ds = plane_reference_data([0, 0, 0], [0, 0, 1], 200, (160, 80), 0.0, seed=k)
        pl = PlaneModel.from_estimate(ds.points + np.c_[np.zeros((200, 2)), rng.normal(0, 0.02, 200)],
                                      toward=[0, 0, 1e3])
        dists.append(pl.distance(probe))
        predicted.append(np.sqrt(pl.distance_variance(probe)))
    assert np.std(dists, ddof=1) / np.mean(predicted) == pytest.approx(1.0, abs=0.15)
