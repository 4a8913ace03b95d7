"""The bundle adjustment on simulated rigs: the noise floor and the truth within 3 sigma.

Simulation (fringecal.simulate.control_points): table 6-8 sensors, table 6-1 poses, CMM set 2,
control points every 10 px on every visible sphere, phase noise sized for an epsilon-1 RMS
of 45 um. Tolerances from the issue: epsilon-1 and epsilon-2 RMS within 5 % of their
values with the true parameters and poses on the same control points; sensor positions,
angles and principal distances within 3 reported standard uncertainties of the truth.
"""

from dataclasses import replace

import numpy as np
import pytest

from fringecal.calibration.bundle import BundleOptions, ResidualStatistics, bundle_adjust
from fringecal.calibration.model import POSE_COLUMNS, BundleProblem, Evaluator
from fringecal.simulate.control_points import (
    dlt_start,
    perturbed_start,
    simulate_control_points,
    thesis_truth,
    three_scanner_truth,
)

EXTERNAL_AND_C = [0, 1, 2, 3, 4, 5, 8]  # x0 y0 z0 omega phi kappa c


def _truth_statistics(problem, rig, poses):
    ev = Evaluator(problem.with_start(rig, poses))
    return ResidualStatistics.of(ev.evaluate(ev.layout.pack(rig.params, poses), False).res)


def _assert_recovered(result, truth_rig, truth_poses, problem):
    truth = _truth_statistics(problem, truth_rig, truth_poses)
    assert result.converged, result.report.message
    assert result.after.rms_eps1_mm == pytest.approx(truth.rms_eps1_mm, rel=0.05)
    assert result.after.rms_eps2_mm == pytest.approx(truth.rms_eps2_mm, rel=0.05)
    u = result.rig.uncertainty
    free = truth_rig.free
    z = (result.rig.params - truth_rig.params)[:, EXTERNAL_AND_C] / np.where(u > 0, u, np.inf)[:, EXTERNAL_AND_C]
    assert np.all(np.abs(z[free[:, EXTERNAL_AND_C]]) < 3.0), np.round(z, 2)
    assert np.all(u[free] > 0) and np.all(u[~free] == 0)
    zp = (result.poses - truth_poses) / result.pose_std
    assert np.all(np.abs(zp) < 3.0), np.round(zp, 2)
    return truth


@pytest.fixture(scope="module")
def thesis():
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, rng=2)
    return rig, art, poses, sim, poses[list(POSE_COLUMNS)].to_numpy(float)


def test_simulation_matches_the_thesis_scale(thesis):
    rig, art, poses, sim, truth_poses = thesis
    cp = sim.control_points
    assert 11000 < len(cp) < 16000  # thesis: 13,604 control points
    assert set(cp["scanner"]) == {"scanner1", "scanner2"}
    assert cp.groupby(["measurement", "scanner"]).size().min() > 300
    ev = Evaluator(BundleProblem.from_tables(rig, art, cp, poses))
    truth = ResidualStatistics.of(ev.evaluate(ev.layout.pack(rig.params, truth_poses), False).res)
    assert truth.rms_eps1_mm == pytest.approx(0.045, rel=0.03)  # the noise floor asked for


def test_thesis_rig_from_dlt_estimates(thesis):
    rig, art, poses, sim, truth_poses = thesis
    start_rig, start_poses = dlt_start(sim, rng=2)
    np.testing.assert_array_equal(start_rig.params[0, :6], rig.params[0, :6])  # the gauge
    problem = BundleProblem.from_tables(start_rig, art, sim.control_points, start_poses)
    result = bundle_adjust(problem)
    truth = _assert_recovered(result, rig, truth_poses, problem)
    assert result.before.rms_f_mm > 10 * result.after.rms_f_mm
    costs = [h["cost"] for h in result.report.history]
    assert all(b <= a for a, b in zip(costs, costs[1:]))  # F never increases
    assert result.after.rms_f_mm <= truth.rms_f_mm * 1.0001  # a minimum, at or below the truth's F
    assert not result.errors()
    table = result.parameter_table()
    assert len(table) == 122 == 4 * 14 - 6 + 12 * 6 and (table["u"] > 0).all()
    assert table.loc[table["parameter"] == "P2.c", "value"].item() == pytest.approx(39.013, abs=0.05)


def test_thesis_rig_from_a_start_perturbed_by_5_mm_and_20_mrad(thesis):
    """From this start plain LM stops in a separate minimum (F ~ 4.4 mm RMS); that is
    detected and the adjustment from start values computed from the control points wins.
    (With rotations stepped as rotations, plain LM reaches the floor from some starts of
    this size, e.g. rng=4, that used to end in a separate minimum.)"""
    rig, art, poses, sim, truth_poses = thesis
    start_rig, start_p = perturbed_start(rig, truth_poses, rng=5)
    d = np.abs(start_rig.params - rig.params)
    assert np.allclose(d[1:, :3], 5.0) and np.allclose(d[1:, 3:6], 0.02) and np.allclose(np.abs(start_p - truth_poses)[:, 3:], 0.02)
    start_poses = poses.assign(**{c: start_p[:, j] for j, c in enumerate(POSE_COLUMNS)})
    problem = BundleProblem.from_tables(start_rig, art, sim.control_points, start_poses)
    result = bundle_adjust(problem)
    _assert_recovered(result, rig, truth_poses, problem)
    assert result.before.rms_eps1_mm > 30  # the start really is far off
    tried = result.extra["alternatives"]
    assert result.extra["start"] == "control points" and tried["control points"]["shape_ratio"] < 1.2
    assert tried["given"]["shape_ratio"] > 5 and tried["given"]["rms_f_mm"] > 1.0
    given_only = bundle_adjust(problem, BundleOptions(start="given"))
    assert given_only.after.rms_f_mm == pytest.approx(tried["given"]["rms_f_mm"], rel=1e-9)
    (d,) = [d for d in given_only.diagnostics if d.kind == "separate_minimum"]
    assert "probably stopped in a separate minimum" in d.message


def test_three_scanners_side_by_side(thesis):
    rig3, art, poses3, spheres_of = three_scanner_truth()
    sim = simulate_control_points(rig3, art, poses3, rng=4, require_all_views=True, spheres_of=spheres_of)
    cp = sim.control_points
    # non-overlapping: no sphere is seen by two scanners in one measurement; all see all poses
    assert cp.groupby(["measurement", "sphere_id"])["scanner"].nunique().max() == 1
    assert cp.groupby("scanner")["measurement"].nunique().min() == 12
    start_rig, start_poses = dlt_start(sim, rng=4)
    problem = BundleProblem.from_tables(start_rig, art, cp, start_poses)
    result = bundle_adjust(problem)
    _assert_recovered(result, rig3, poses3[list(POSE_COLUMNS)].to_numpy(float), problem)
    assert [s.name for s in result.rig.scanners] == ["scanner1", "scanner2", "scanner3"]


def test_robust_loss_resists_outliers(thesis):
    """2 % of the control points get random phases (e.g. a glint): least squares is pulled
    off, a Cauchy loss is not."""
    rig, art, poses, sim, truth_poses = thesis
    cp = sim.control_points.copy()
    rng = np.random.default_rng(5)
    bad = rng.choice(len(cp), len(cp) // 50, replace=False)
    cp.loc[cp.index[bad], "tau_x_rad"] += rng.uniform(-0.05, 0.05, len(bad))
    problem = BundleProblem.from_tables(rig, art, cp, poses)
    plain = bundle_adjust(problem, BundleOptions(start="given"))
    robust = bundle_adjust(problem, BundleOptions(start="given", robust_loss="cauchy"))
    ext = replace(rig, free=rig.free & np.isin(np.arange(14), EXTERNAL_AND_C)[None, :]).free
    err_plain = np.abs(plain.rig.params - rig.params)[ext] / robust.rig.uncertainty[ext]
    err_robust = np.abs(robust.rig.params - rig.params)[ext] / robust.rig.uncertainty[ext]
    assert np.median(err_robust) < 0.5 * np.median(err_plain)
    assert np.all(err_robust < 3.0)
    assert robust.robust_scales[0] == pytest.approx(2.385 * 0.045, rel=0.15)


def test_large_problems_start_on_a_subsample_and_end_at_the_same_minimum(thesis):
    rig, art, poses, sim, truth_poses = thesis
    start_rig, start_poses = dlt_start(sim, rng=2)
    problem = BundleProblem.from_tables(start_rig, art, sim.control_points, start_poses)
    whole = bundle_adjust(problem, BundleOptions(start="given", coarse_points=0))
    staged = bundle_adjust(problem, BundleOptions(start="given", coarse_points=3000))
    assert whole.extra["coarse"] is None
    assert staged.extra["coarse"]["every"] == int(np.ceil(problem.n_points / 3000))
    assert staged.iterations < whole.iterations
    assert staged.after.rms_f_mm == pytest.approx(whole.after.rms_f_mm, rel=1e-9)
    assert np.all(np.abs(staged.x - whole.x) <= 1e-3 * whole.uncertainty.std)  # same point, to 0.001 sigma
    thin = problem.thinned(7)
    assert len(thin.measurements) == 12 and set(thin.sphere_idx) == set(problem.sphere_idx)
