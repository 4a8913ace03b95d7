"""Wild bootstrap of the bundle adjustment (fringecal.calibration.bootstrap)."""

import numpy as np
import pytest

from fringecal.calibration.bootstrap import bootstrap_calibrations, predicted_projector_mm
from fringecal.calibration.bundle import BundleOptions, bundle_adjust
from fringecal.calibration.model import BundleProblem
from fringecal.simulate.control_points import simulate_control_points, thesis_truth


@pytest.fixture(scope="module")
def truth():
    return thesis_truth()


def test_prediction_at_the_truth_is_the_noise_free_observation(truth):
    rig, art, poses = truth
    sim = simulate_control_points(rig, art, poses, spacing_px=20, noise_eps1_mm=0.0, rng=3)
    res = bundle_adjust(BundleProblem.from_tables(rig, art, sim.control_points, poses),
                        BundleOptions(start="given", max_iterations=1))
    predicted = predicted_projector_mm(res)
    assert np.isfinite(predicted).all()
    np.testing.assert_allclose(predicted, res.problem.prj_mm, atol=1e-7)


@pytest.mark.slow
def test_bootstrap_spread_matches_the_linear_uncertainty(truth):
    """40 re-adjustments of one noisy calibration (every 20 px, eps1 noise 45 um): the
    spread of each free sensor parameter against its linear standard uncertainty.
    With 40 draws a ratio scatters by about 11 %; the bias of this large,
    well-conditioned problem is below a fifth of the spread."""
    rig, art, poses = truth
    sim = simulate_control_points(rig, art, poses, spacing_px=20, rng=5)
    res = bundle_adjust(BundleProblem.from_tables(rig, art, sim.control_points, poses), BundleOptions(start="given"))
    draws = bootstrap_calibrations(res, 40, seed=1)
    assert draws.shape == (40,) + rig.params.shape
    free = res.layout.sensor_index >= 0
    spread = draws.std(axis=0, ddof=1)[free]
    linear = res.rig.uncertainty[free] if res.rig.uncertainty is not None else None
    assert linear is not None
    ratio = spread / linear
    assert 0.8 < np.median(ratio) < 1.2
    assert np.mean((ratio > 0.6) & (ratio < 1.5)) > 0.95
    bias = (draws.mean(axis=0) - res.rig.params)[free]
    assert np.median(np.abs(bias) / spread) < 0.2
    # the same seed gives the same draws; none without draws
    np.testing.assert_array_equal(bootstrap_calibrations(res, 2, seed=1), draws[:2])
    assert bootstrap_calibrations(res, 0).shape == (0,) + rig.params.shape
