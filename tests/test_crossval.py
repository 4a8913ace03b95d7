"""Cross-validation of a calibration against simulated truth (fringecal.calibration.crossval).

Simulated thesis rig (two scanners, the 12 poses of table 6-1), control points every
40 px (about 800), 45 um epsilon-1 noise; halves of six poses each.
"""

import json

import numpy as np
import pytest

from fringecal.calibration.bundle import BundleOptions, bundle_adjust
from fringecal.calibration.crossval import (
    CONSISTENT_MAX,
    VERDICT_FRAMES,
    cross_validate,
    rigid_residual,
    split_measurements,
    subproblem,
)
from fringecal.calibration.model import POSE_COLUMNS, BundleProblem
from fringecal.calibration.propagation import triangulate_mm
from fringecal.registration import kabsch
from fringecal.rig import Scanner
from fringecal.simulate.control_points import simulate_control_points, thesis_truth

SPACING_PX = 40
N_SAMPLE = 300


@pytest.fixture(scope="module")
def truth():
    rig, art, poses = thesis_truth()
    return rig, art, poses.assign(measurement=poses["measurement"].astype(str))


def _problem(truth, seed, control_points=None):
    rig, art, poses = truth
    cp = simulate_control_points(rig, art, poses, spacing_px=SPACING_PX, rng=seed).control_points
    return BundleProblem.from_tables(rig, art, cp if control_points is None else control_points, poses), cp


def solved(problem):
    """The problem with its adjusted solution as start values (what cross_validate takes)."""
    res = bundle_adjust(problem, BundleOptions(start="given"))
    return problem.with_start(res.rig, res.poses)


def test_noise_only_calibration_is_consistent(truth):
    """The model is exact: in each verdict frame mean z^2 / 3 ~ chi^2_nu / nu (nu from the
    comparison itself, 6-10 here), variance 2 / nu. Averaged over the scanners of one seed
    (correlated: the average's variance is at most the mean of theirs) and then over four
    independent seeds, it lies within 3 standard deviations sqrt(mean(2 / nu) / 4) (~0.25)
    of 1. Every verdict is "consistent", and the model-error figure stays inside the band
    the verdict allows: |d| RMS below twice the predicted, i.e. model error below
    sqrt((4 - 1) / 2) = 1.22 times the predicted RMS."""
    seeds = (0, 1, 2, 3)
    per_seed = {f: [] for f in VERDICT_FRAMES}
    var = {f: [] for f in VERDICT_FRAMES}
    for seed in seeds:
        problem, _ = _problem(truth, seed)
        cv = cross_validate(solved(problem), n_points_per_scanner=N_SAMPLE,
                            seed=seed)
        for name, frames in cv.comparisons.items():
            assert cv.verdict(name) == "consistent", cv.to_dict()["scanners"][name]
            for f in VERDICT_FRAMES:
                assert frames[f].model_error_mm < np.sqrt((CONSISTENT_MAX - 1) / 2) * frames[f].rms_predicted_mm
                assert frames[f].d.shape == (N_SAMPLE, 3) and frames[f].cov_d.shape == (N_SAMPLE, 3, 3)
        for f in VERDICT_FRAMES:
            per_seed[f].append(np.mean([c[f].mean_z2_over_3 for c in cv.comparisons.values()]))
            var[f] += [2 / c[f].effective_dof for c in cv.comparisons.values()]
        params = cv.to_dict()["parameters"]
        assert 0.5 < params["rms_normalised"] < 2.0
    for f in VERDICT_FRAMES:
        sd = np.sqrt(np.mean(var[f]) / len(seeds))
        assert abs(np.mean(per_seed[f]) - 1) < 3 * sd, (f, per_seed[f], sd)
    # the ball-bar check reuses the halves
    d = cv.to_dict()
    json.dumps(d)
    assert [tuple(h["measurements"]) for h in d["halves"]] == list(cv.measurements)
    assert all(h.rig.reference == "scanner1" for h in cv.halves)
    assert cv.sensor_covariances()[0].shape == (56, 56)
    assert all(0.04 < h["rms_eps1_mm"] < 0.05 for h in d["halves"])


def test_projector_shift_in_one_half_is_model_error_of_that_scanner(truth):
    """Scanner two's projector phases in half A's measurements are shifted by 10 um on
    the image plane (a projector that moved between the halves). The model absorbs it
    exactly in half A by P2's principal point (xi_h + 10 um), so half A converges to the
    truth with that change and half B to the truth: the effect on each sampled point is
    b = P(shifted rig) - P(true rig), computed here from the truth alone. Scanner one is
    untouched. With the error in one half only the reported figure is |b|_rms / sqrt(2)
    (module docstring), in the scanner frame after removing the best-fit rigid motion of
    b, in the reference frame (aligned on scanner one, where b = 0) b itself. Tolerance:
    factor 1.5; the estimate differs from the truth by the halves' random differences
    (~0.11 and ~0.25 mm RMS against |b| ~0.6 and ~2.6 mm)."""
    rig = truth[0]
    delta_mm = 0.010
    problem, cp = _problem(truth, 7)
    half_a, _ = split_measurements(problem)
    prj = rig.scanner("scanner2").projector
    sel = (cp["scanner"] == "scanner2") & cp["measurement"].isin(half_a)
    cp = cp.copy()
    cp.loc[sel, "tau_x_rad"] += delta_mm * 2 * np.pi / prj.format.width_mm
    problem, _ = _problem(truth, 7, cp)
    cv = cross_validate(solved(problem), n_points_per_scanner=N_SAMPLE)

    assert cv.verdict("scanner1") == "consistent"
    assert cv.verdict("scanner2") == "model error"
    shifted = prj.params.copy()
    shifted[6] += delta_mm
    true2 = rig.scanner("scanner2")
    moved = Scanner("scanner2", true2.camera, prj.with_params(shifted))
    for frame in VERDICT_FRAMES:
        c = cv.comparisons["scanner2"][frame]
        assert c.verdict == "model error" and c.mean_z2_over_3 > 10
        cam, pj = problem.cam_mm[c.index], problem.prj_mm[c.index]
        P_true, P_moved = triangulate_mm(true2, cam, pj), triangulate_mm(moved, cam, pj)
        if frame == "scanner":
            M, T = kabsch(P_moved, P_true)
            b = P_moved @ M.T + T - P_true
        else:
            b = P_moved - P_true
        rms_b = np.sqrt(np.mean(np.sum(b**2, axis=1)))
        assert rms_b > 4 * c.rms_predicted_mm  # the injected effect is well above the noise
        expected = rms_b / np.sqrt(2)
        assert expected / 1.5 < c.model_error_mm < 1.5 * expected, (frame, c.model_error_mm, expected)
    assert cv.model_error_mm("scanner2") == max(cv.comparisons["scanner2"][f].model_error_mm for f in VERDICT_FRAMES)
    assert cv.to_dict()["verdict"] == "model error"


def test_split_alternates_by_standoff_whatever_the_names_and_refuses_too_few_poses(truth):
    """The thesis's 12 poses, three at each of four stand-offs: alternating nearest first
    gives each half poses at all four; renamed measurements (other natural order) give
    the same halves (issue 31: results must not depend on folder names)."""
    problem, cp = _problem(truth, 3)
    a, b = split_measurements(problem)
    assert a == ("2", "3", "4", "8", "9", "10") and b == ("1", "5", "6", "7", "11", "12")
    standoff = {m: -int(m) // 3 for m in problem.measurements}  # 1-3, 4-6, 7-9, 10-12: one stand-off each
    assert {standoff[m] for m in a} == {standoff[m] for m in b} == set(standoff.values())
    names = {m: f"m{13 - int(m):02d}" for m in problem.measurements}  # reversed natural order
    rig, art, poses = truth
    renamed, _ = _problem((rig, art, poses.assign(measurement=poses["measurement"].map(names))), 3,
                          cp.assign(measurement=cp["measurement"].map(names)))
    ra, rb = split_measurements(renamed)
    assert sorted(ra) == sorted(names[m] for m in a) and sorted(rb) == sorted(names[m] for m in b)
    ra, rb = split_measurements(problem, seed=5)
    assert len(ra) == len(rb) == 6 and sorted(ra + rb, key=int) == [str(i) for i in range(1, 13)]
    # scanner2 keeps only measurements 1, 3, 10 and 12 -> two in each half
    keep = ~((cp["scanner"] == "scanner2") & ~cp["measurement"].isin(["1", "3", "10", "12"]))
    thin, _ = _problem(truth, 3, cp[keep].reset_index(drop=True))
    with pytest.raises(ValueError, match=r"scanner scanner2 has control points in 2 measurement\(s\) of half A "
                                         r"\(3, 10; 4 in all\).*half B \(1, 12; 4 in all\)") as err:
        split_measurements(thin)
    assert "scanner1" not in str(err.value)


def test_subproblem_keeps_exactly_the_chosen_measurements(truth):
    problem, cp = _problem(truth, 4)
    sub = subproblem(problem, ["7", "1", "3"])
    assert sub.measurements == ("1", "3", "7")  # table order
    chosen = cp["measurement"].isin(["1", "3", "7"]).to_numpy()
    assert sub.n_points == int(chosen.sum())
    assert sorted(sub.row) == list(np.flatnonzero(chosen))
    # every control point keeps its own data and names its own measurement
    full_pos = {r: i for i, r in enumerate(problem.row)}
    pos = np.array([full_pos[r] for r in sub.row])
    np.testing.assert_array_equal(sub.cam_mm, problem.cam_mm[pos])
    np.testing.assert_array_equal(sub.prj_mm, problem.prj_mm[pos])
    np.testing.assert_array_equal(sub.sphere_idx, problem.sphere_idx[pos])
    np.testing.assert_array_equal(sub.scanner_idx, problem.scanner_idx[pos])
    assert list(np.asarray(sub.measurements)[sub.meas_idx]) == list(cp["measurement"].to_numpy()[sub.row])
    poses = truth[2].set_index("measurement").loc[["1", "3", "7"], list(POSE_COLUMNS)].to_numpy(float)
    np.testing.assert_array_equal(sub.poses, poses)
    assert sub.pose_free.shape == (3, 6) and (sub.gamma1, sub.gamma2) == (problem.gamma1, problem.gamma2)
    with pytest.raises(ValueError, match="not in the problem"):
        subproblem(problem, ["1", "13"])


def test_rigid_residual_removes_exactly_the_small_rigid_motions():
    """Displacements t + w x p of a small rigid motion leave nothing (to rounding); the
    residual is idempotent and orthogonal to the motions; fitting on a subset removes
    that subset's motion from all points."""
    rng = np.random.default_rng(8)
    p = rng.normal(0, 300, (50, 3)) + [0, 0, -3000]
    t, w = rng.normal(0, 1, 3), rng.normal(0, 1e-3, 3)
    rigid = t + np.cross(w, p)
    assert np.abs(rigid_residual(p, rigid)).max() < 1e-9
    v = rng.normal(0, 0.1, (50, 3))
    r = rigid_residual(p, v)
    np.testing.assert_allclose(rigid_residual(p, r), r, atol=1e-12)
    assert abs(np.sum(r * rigid)) < 1e-9 * np.linalg.norm(r) * np.linalg.norm(rigid)
    part = rigid_residual(p, np.where(np.arange(50)[:, None] < 20, rigid, v), np.arange(20))
    assert np.abs(part[:20]).max() < 1e-9
    np.testing.assert_allclose(part[20:], v[20:] - rigid[20:], atol=1e-9)
    cols = rigid_residual(p, np.stack([rigid, v], axis=2))
    np.testing.assert_allclose(cols[:, :, 1], r, atol=1e-12)
