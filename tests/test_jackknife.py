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
from fringecal.calibration.jackknife import MIN_REPLICAS, jackknife_calibrations
from fringecal.calibration.model import BundleProblem
from fringecal.calibration.propagation import triangulate_mm
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


def _lengths(problem, params, pairs):
    rig = problem.rig.with_params(params)
    (a, b) = pairs
    sa, sb = rig.scanners[0], rig.scanners[1]
    Pa = triangulate_mm(sa, problem.cam_mm[a], problem.prj_mm[a])
    Pb = triangulate_mm(sb, problem.cam_mm[b], problem.prj_mm[b])
    return np.linalg.norm(Pa - Pb, axis=1)


def _experiment(truth, seed, wobble_mm):
    rig, art, poses = truth
    rng = np.random.default_rng(100 + seed)
    cp = simulate_control_points(rig, art, poses, spacing_px=SPACING_PX, rng=seed).control_points.copy()
    for (m, sc), rows in cp.groupby(["measurement", "scanner"]).groups.items():
        width = rig.scanner(sc).projector.format.width_mm
        cp.loc[rows, "tau_x_rad"] += rng.normal(0, wobble_mm) * 2 * np.pi / width
        cp.loc[rows, "tau_y_rad"] += rng.normal(0, wobble_mm) * 2 * np.pi / width
    problem = BundleProblem.from_tables(rig, art, cp, poses)
    fit = bundle_adjust(problem, BundleOptions(start="given"))
    jk = jackknife_calibrations(problem.with_start(fit.rig, fit.poses), BundleOptions(start="given"), workers=2)
    assert jk.usable and len(jk.left_out) == len(poses) and not jk.skipped
    a = rng.choice(np.flatnonzero(problem.scanner_idx == 0), N_LENGTHS, replace=False)
    b = rng.choice(np.flatnonzero(problem.scanner_idx == 1), N_LENGTHS, replace=False)
    error = _lengths(problem, fit.rig.params, (a, b)) - _lengths(problem, rig.params, (a, b))
    replicas = np.stack([_lengths(problem, p, (a, b)) for p in jk.params])
    spread = np.sqrt([jackknife_variance(replicas[:, i]) for i in range(N_LENGTHS)])
    return error, spread


def test_jackknife_spread_follows_the_calibrations_error_with_and_without_errors_between_measurements(truth):
    """Three seeds, 40 lengths each. Noise only: the jackknife's spread matches the
    calibration's true error, RMS of error / spread 0.5-2 (the lengths of one seed share
    one calibration, so the pooled RMS rests on a few effective draws, hence the wide
    band). With each measurement's projector phases shifted by a random 10 um (one
    offset per measurement, which the adjustment takes for noise of its points): the
    errors grow several times, and the spread grows with them (same band), where a
    spread that did not see the wobble would leave error / spread far above 2."""
    still = [_experiment(truth, s, 0.0) for s in SEEDS]
    wobbly = [_experiment(truth, s, WOBBLE_MM) for s in SEEDS]

    def rms(x):
        return float(np.sqrt(np.mean(np.square(x))))

    err0, spr0 = (np.concatenate(v) for v in zip(*still))
    err1, spr1 = (np.concatenate(v) for v in zip(*wobbly))
    assert 0.5 < rms(err0 / spr0) < 2.0, rms(err0 / spr0)
    assert rms(err1) > 3 * rms(err0), (rms(err1), rms(err0))
    assert 0.5 < rms(err1 / spr1) < 2.0, rms(err1 / spr1)
    assert rms(err1 / spr0) > 2.5  # the noise-only spread would not have covered it


def test_jackknife_variance_and_too_few_replicas():
    """The textbook formula on known numbers; fewer than MIN_REPLICAS replicas are not
    usable, and a variance of one value is refused."""
    assert jackknife_variance([1.0, 2.0, 3.0, 6.0]) == pytest.approx(3 / 4 * 14.0)
    with pytest.raises(ValueError, match="at least 2 replicas"):
        jackknife_variance([1.0])
    assert MIN_REPLICAS >= 3
