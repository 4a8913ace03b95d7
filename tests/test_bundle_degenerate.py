"""Degenerate calibrations are detected and explained, not returned as numbers."""

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from fringecal.calibration.bundle import BundleOptions, bundle_adjust
from fringecal.calibration.diagnostics import DegenerateCalibrationError
from fringecal.calibration.model import POSE_COLUMNS, BundleProblem
from fringecal.simulate.control_points import simulate_control_points, thesis_truth

GIVEN = BundleOptions(start="given")


@pytest.fixture(scope="module")
def coarse():
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, spacing_px=20, rng=11)
    full = bundle_adjust(BundleProblem.from_tables(rig, art, sim.control_points, poses), GIVEN)
    return rig, art, poses, sim.control_points, full


def _u(result, name):
    return result.uncertainty.std[list(result.layout.names).index(name)]


def _kinds(result_or_error):
    return {d.kind for d in result_or_error.diagnoses} if isinstance(result_or_error, Exception) else \
        {d.kind for d in result_or_error.diagnostics}


def test_a_scanner_that_saw_one_pose(coarse):
    rig, art, poses, cp, full = coarse
    one = cp[(cp["scanner"] == "scanner1") | (cp["measurement"] == "1")]
    res = bundle_adjust(BundleProblem.from_tables(rig, art, one, poses), GIVEN)
    (d,) = [d for d in res.diagnostics if d.kind == "single_pose"]
    assert d.subject == "scanner2" and "only in measurement 1" in d.message
    assert "principal distance cannot be told from the distance to the artefact" in d.message
    assert all(p.split(".")[0] in ("C2", "P2") for p in d.parameters) and d.parameters
    # and the numbers say so: scanner two's principal distances become ~10x less certain
    assert _u(res, "C2.c") > 5 * _u(full, "C2.c") and _u(res, "P2.c") > 5 * _u(full, "P2.c")
    assert _u(res, "C1.c") < 1.5 * _u(full, "C1.c")


def test_all_poses_at_one_standoff(coarse):
    rig, art, poses, _, full = coarse
    flat = poses.copy()
    flat["tz_mm"] = poses["tz_mm"].iloc[0] + np.arange(12) * 1.0
    flat["tx_mm"] = poses["tx_mm"].iloc[0] + (np.arange(12) % 4) * 40 - 60
    flat["ty_mm"] = poses["ty_mm"].iloc[0] + (np.arange(12) // 4) * 40 - 40
    sim = simulate_control_points(rig, art, flat, spacing_px=20, rng=11)
    res = bundle_adjust(BundleProblem.from_tables(rig, art, sim.control_points, flat), GIVEN)
    found = {d.subject: d for d in res.diagnostics if d.kind == "single_standoff"}
    assert set(found) == {"scanner1", "scanner2"}
    assert "corr(c, distance) of C2 = " in found["scanner2"].message
    assert found["scanner2"].parameters == ("C2.c", "P2.c")
    assert _u(res, "C2.c") > 1.5 * _u(full, "C2.c")
    assert not [d for d in full.diagnostics if d.kind == "single_standoff"]


def test_free_but_unobservable_parameters_are_named(coarse):
    rig, art, poses, cp, _ = coarse
    free = rig.free.copy()
    free[0, :6] = True  # the reference camera's external parameters: the world frame floats
    with pytest.raises(DegenerateCalibrationError) as err:
        bundle_adjust(BundleProblem.from_tables(replace(rig, free=free), art, cp, poses), GIVEN)
    (d,) = [d for d in err.value.diagnoses if d.kind == "unobservable"]
    assert d.message.startswith("6 combination(s) of free parameters that no control point determines")
    assert "The world frame is not fixed: the reference camera C1 has free external parameters" in str(err.value)
    assert {"C1.x0", "C1.z0"} <= set(d.parameters)


def test_a_pose_seen_on_two_spheres_is_left_out(coarse):
    rig, art, poses, cp, full = coarse
    two = cp[~((cp["measurement"] == "5") & ~cp["sphere_id"].isin(["4", "5"]))]
    problem = BundleProblem.from_tables(rig, art, two, poses)
    ((m, reason),) = problem.dropped
    assert m == "5" and reason.startswith("control points on 2 sphere(s) only (4, 5): its rotation about the line")
    assert "5" not in problem.measurements and problem.n_points == int((two["measurement"] != "5").sum())
    # every point kept maps back to its own row of the table it came from
    kept = two.iloc[problem.row]
    assert (kept["measurement"] != "5").all()
    np.testing.assert_array_equal(problem.sphere_idx, art.index(kept["sphere_id"]))
    res = bundle_adjust(problem, GIVEN)
    (d,) = [d for d in res.diagnostics if d.kind == "pose_unobservable"]
    assert d.severity == "warning" and d.subject == "5" and d.message.endswith("it is left out")
    assert not res.errors() and list(res.poses_frame()["measurement"]) == [str(i) for i in range(1, 13) if i != 5]
    # eleven placements determine the sensors as twelve do, to within their uncertainty
    sensor = [i for i, n in enumerate(full.layout.names) if not n.startswith("pose")]
    names = [full.layout.names[i] for i in sensor]
    mine = np.array([res.x[list(res.layout.names).index(n)] for n in names])
    assert np.all(np.abs(mine - full.x[sensor]) < 4 * full.uncertainty.std[sensor])


def test_a_pose_seen_on_two_spheres_refuses_a_problem_that_keeps_it(coarse):
    rig, art, poses, cp, full = coarse
    problem = full.problem
    in_five = problem.meas_idx == problem.measurements.index("5")
    two = np.unique(problem.sphere_idx[in_five])[:2]
    keep = ~in_five | np.isin(problem.sphere_idx, two)
    kept = replace(problem, scanner_idx=problem.scanner_idx[keep], meas_idx=problem.meas_idx[keep],
                   sphere_idx=problem.sphere_idx[keep], cam_mm=problem.cam_mm[keep], prj_mm=problem.prj_mm[keep],
                   row=problem.row[keep])
    with pytest.raises(DegenerateCalibrationError, match="measurement 5 has control points on 2 sphere"):
        bundle_adjust(kept, GIVEN)


def test_too_few_points(coarse):
    rig, art, poses, cp, _ = coarse
    with pytest.raises(DegenerateCalibrationError) as err:
        bundle_adjust(BundleProblem.from_tables(rig, art, cp.iloc[::100], poses), GIVEN)
    assert "too_few_control_points" in _kinds(err.value)
    assert "control points give" in str(err.value)
    with pytest.raises(DegenerateCalibrationError, match="scanner scanner2 has no control points"):
        bundle_adjust(BundleProblem.from_tables(rig, art, cp[cp["scanner"] == "scanner1"], poses), GIVEN)


def test_a_measurement_without_control_points_is_left_out(coarse):
    rig, art, poses, cp, full = coarse
    extra = pd.concat([poses, poses.iloc[[0]].assign(measurement="13")], ignore_index=True)
    problem = BundleProblem.from_tables(rig, art, cp, extra)
    assert problem.dropped == (("13", "no control points"),) and "13" not in problem.measurements
    res = bundle_adjust(problem, GIVEN)
    (d,) = [d for d in res.diagnostics if d.kind == "measurement_without_control_points"]
    assert d.subject == "13" and "left out" in d.message
    np.testing.assert_allclose(res.x, full.x, rtol=0, atol=1e-6)
    assert list(res.poses_frame()["measurement"]) == [str(i) for i in range(1, 13)]
    assert res.poses_frame()[list(POSE_COLUMNS)].shape == (12, 6)
