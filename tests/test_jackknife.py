"""The delete-one-measurement jackknife against simulated truth (fringecal.calibration.jackknife).

Simulated thesis rig (two scanners, the 12 poses of table 6-1), control points every
40 px, 45 um epsilon-1 noise. "Lengths" are distances between a control point of
scanner one and one of scanner two, both triangulated from their observations: with the
calibrated sensors and with the true ones, from the same observations, so their
difference is the calibration's error alone.
"""

import numpy as np
import pytest

from fringecal.calibration.bundle import BundleOptions, bundle_adjust
from fringecal.calibration.jackknife import MIN_REPLICAS, NOISE_DRAWS, jackknife_calibrations
from fringecal.calibration.model import BundleProblem
from fringecal.calibration.propagation import sensor_covariance, triangulate_mm
from fringecal.calibration.results import covariance_arrays
from fringecal.simulate.control_points import simulate_control_points, thesis_truth
from fringecal.verification.budget import jackknife_variance

SPACING_PX = 40
N_LENGTHS = 40
SEEDS = (0, 1, 2)
#: per-measurement shift of each projector's phases, image-plane mm (a projector that
#: wobbles between measurements: one offset for all of a measurement's points)
WOBBLE_MM = 0.010


@pytest.fixture(scope="module")
def truth():
    rig, art, poses = thesis_truth()
    return rig, art, poses.assign(measurement=poses["measurement"].astype(str))


def _lengths(rig, problem, params, pairs):
    r = rig.with_params(np.asarray(params).reshape(rig.params.shape))
    a, b = pairs
    Pa = triangulate_mm(r.scanners[0], problem.cam_mm[a], problem.prj_mm[a])
    Pb = triangulate_mm(r.scanners[1], problem.cam_mm[b], problem.prj_mm[b])
    return np.linalg.norm(Pa - Pb, axis=1)


def _linear_u(rig, problem, params, C, pairs):
    """sqrt(g^T C g) per length, g by central differences over every sensor parameter."""
    x = params.reshape(-1)
    step = np.where(np.diag(C) > 0, np.sqrt(np.clip(np.diag(C), 0, None)), 0.0)
    G = np.zeros((len(pairs[0]), x.size))
    for j in np.flatnonzero(step):
        dx = np.zeros_like(x)
        dx[j] = step[j]
        G[:, j] = (_lengths(rig, problem, x + dx, pairs) - _lengths(rig, problem, x - dx, pairs)) / (2 * step[j])
    return np.sqrt(np.einsum("ij,jk,ik->i", G, C, G))


def _experiment(truth, seed, wobble_mm):
    """(true error, linear u, jackknife variance, noise-only jackknife variance) per length."""
    rig, art, poses = truth
    rng = np.random.default_rng(100 + seed)
    cp = simulate_control_points(rig, art, poses, spacing_px=SPACING_PX, rng=seed).control_points.copy()
    for (m, sc), rows in cp.groupby(["measurement", "scanner"]).groups.items():
        width = rig.scanner(sc).projector.format.width_mm
        cp.loc[rows, "tau_x_rad"] += rng.normal(0, wobble_mm) * 2 * np.pi / width
        cp.loc[rows, "tau_y_rad"] += rng.normal(0, wobble_mm) * 2 * np.pi / width
    problem = BundleProblem.from_tables(rig, art, cp, poses)
    fit = bundle_adjust(problem, BundleOptions(start="given"))
    jk = jackknife_calibrations(fit, workers=2)
    assert jk.usable and len(jk.left_out) == len(poses) and not jk.skipped
    assert jk.noise_params.shape == (NOISE_DRAWS, len(poses)) + rig.params.shape
    arrays = covariance_arrays(fit)
    C = sensor_covariance(arrays["sensor_index"], arrays["covariance"])
    pairs = (rng.choice(np.flatnonzero(problem.scanner_idx == 0), N_LENGTHS, replace=False),
             rng.choice(np.flatnonzero(problem.scanner_idx == 1), N_LENGTHS, replace=False))
    error = _lengths(rig, problem, fit.rig.params, pairs) - _lengths(rig, problem, rig.params, pairs)
    u = _linear_u(rig, problem, fit.rig.params, C, pairs)

    def var_j(replicas):
        values = np.stack([_lengths(rig, problem, p, pairs) for p in replicas])
        return np.array([jackknife_variance(values[:, i]) for i in range(N_LENGTHS)])

    return error, u, var_j(jk.params), np.mean([var_j(p) for p in jk.noise_params], axis=0)


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


@pytest.mark.slow
def test_model_error_from_the_jackknife_covers_errors_that_differ_between_measurements(truth):
    """Three seeds, 40 lengths each; the model error is u sqrt(max(0, var_J / var_J,noise
    - 1)), u the linear calibration term.

    Noise only: the linear u holds the error (RMS error / u 0.6-1.6), the jackknife
    scatters as its noise-only worlds do (median var_J / var_J,noise 0.7-1.5) and the
    model error adds little (RMS error / u_total still above 0.6). With each
    measurement's projector phases shifted by a random 10 um (one offset per
    measurement, which the adjustment takes for noise of its points) the errors grow
    several times; the sandwich covariance grows with the residuals but not enough (RMS
    error / u above 1.5), the jackknife scatters 2.5 or more times its noise-only worlds
    and the model error brings U to the errors (RMS error / u_total 0.5-1.3). The lengths
    of one seed share one calibration, so the pooled figures rest on a few effective
    draws, hence the wide bands (figures per seed: ``python tests/test_jackknife.py``)."""
    out = {}
    for name, wobble in (("noise", 0.0), ("wobble", WOBBLE_MM)):
        error, u, vj, vn = (np.concatenate(v) for v in zip(*[_experiment(truth, s, wobble) for s in SEEDS]))
        total = u * np.sqrt(np.maximum(1.0, vj / vn))
        out[name] = {"error/u": _rms(error / u), "error/u_total": _rms(error / total),
                     "var_J/var_noise": float(np.median(vj / vn)), "error_um": 1000 * _rms(error)}
    noise, wobble = out["noise"], out["wobble"]
    assert 0.6 < noise["error/u"] < 1.6, out
    assert 0.7 < noise["var_J/var_noise"] < 1.5, out
    assert noise["error/u_total"] > 0.6, out
    assert wobble["error_um"] > 3 * noise["error_um"], out
    assert wobble["error/u"] > 1.5, out
    assert wobble["var_J/var_noise"] > 2.5, out
    assert 0.5 < wobble["error/u_total"] < 1.3, out


def test_a_measurement_that_cannot_be_left_out_is_skipped_in_the_data_and_in_every_noise_world(truth, monkeypatch):
    """Leaving out measurement 5 is refused (as a degenerate problem would be): it has no
    replica, neither in the data nor in any noise world, the record says why, and the
    other measurements' replicas stay aligned row by row across the worlds."""
    import fringecal.calibration.jackknife as jkm
    from fringecal.calibration.diagnostics import DegenerateCalibrationError, Diagnosis

    rig, art, poses = truth
    cp = simulate_control_points(rig, art, poses, spacing_px=80, rng=0).control_points
    fit = bundle_adjust(BundleProblem.from_tables(rig, art, cp, poses), BundleOptions(start="given"))
    real = jkm.readjusted

    def refuse_five(problem, options):
        if "5" not in problem.measurements:
            raise DegenerateCalibrationError([Diagnosis("pose_unobservable", "error", "measurement 5",
                                                        "measurement 5 is needed")])
        return real(problem, options)

    monkeypatch.setattr(jkm, "readjusted", refuse_five)
    jk = jackknife_calibrations(fit, noise_draws=2)
    names = [str(m) for m in fit.problem.measurements]
    assert jk.left_out == tuple(m for m in names if m != "5") and list(jk.skipped) == ["5"]
    assert jk.skipped["5"] == "degenerate: measurement 5 is needed"
    assert jk.params.shape == (len(names) - 1,) + rig.params.shape
    assert jk.noise_params.shape == (2, len(names) - 1) + rig.params.shape
    assert jk.usable and jk.to_dict()["skipped"] == jk.skipped


def test_mirrored_noise_worlds_hold_the_noise_with_both_signs(truth):
    """noise_worlds(mirrored=True): each world is followed by its mirror, every point's
    residual with the opposite sign, so a pair's mean observation is the calibrated
    model's prediction exactly (what the Wald test's noise bias relies on), and the first
    of each pair is the plain noise world."""
    from fringecal.calibration.bootstrap import predicted_projector_mm
    from fringecal.calibration.jackknife import noise_worlds

    rig, art, poses = truth
    cp = simulate_control_points(rig, art, poses, spacing_px=80, rng=0).control_points
    fit = bundle_adjust(BundleProblem.from_tables(rig, art, cp, poses), BundleOptions(start="given", bootstrap_draws=0))
    predicted = predicted_projector_mm(fit)
    ok = np.isfinite(predicted).all(axis=1)
    worlds = noise_worlds(fit, 2, seed=3, mirrored=True)
    plain = noise_worlds(fit, 2, seed=3)
    assert len(worlds) == 4 and ok.mean() > 0.99
    residual = fit.problem.prj_mm - predicted
    for k in range(2):
        plus, minus = worlds[2 * k].prj_mm, worlds[2 * k + 1].prj_mm
        np.testing.assert_array_equal(plus, plain[k].prj_mm)
        np.testing.assert_allclose((plus + minus)[ok] / 2, predicted[ok], rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.abs(plus - predicted)[ok], np.abs(residual)[ok], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(minus[~ok], fit.problem.prj_mm[~ok])  # a ray that misses keeps its observation
    signs = np.sign((worlds[0].prj_mm - predicted)[ok] * residual[ok])
    assert 0.4 < np.mean(signs > 0) < 0.6  # random signs, not the residuals themselves


def test_jackknife_variance_and_too_few_replicas():
    """The textbook formula on known numbers; a variance of one value is refused."""
    assert jackknife_variance([1.0, 2.0, 3.0, 6.0]) == pytest.approx(3 / 4 * 14.0)
    with pytest.raises(ValueError, match="at least 2 replicas"):
        jackknife_variance([1.0])
    assert MIN_REPLICAS >= 3


if __name__ == "__main__":  # the figures docs/uncertainty.md quotes: python tests/test_jackknife.py
    world = thesis_truth()
    world = (world[0], world[1], world[2].assign(measurement=world[2]["measurement"].astype(str)))
    for name, wobble in (("noise only", 0.0), ("projector wobble 10 um", WOBBLE_MM)):
        for s in (0, 1, 2, 3, 4):
            error, u, vj, vn = _experiment(world, s, wobble)
            total = u * np.sqrt(np.maximum(1.0, vj / vn))
            print(f"{name}, seed {s}: RMS error {1000 * _rms(error):.1f} um, error / u {_rms(error / u):.2f}, "
                  f"error / u_total {_rms(error / total):.2f}, median var_J / var_J,noise "
                  f"{np.median(vj / vn):.2f}, median var_J / u^2 {np.median(vj / u**2):.2f}")
