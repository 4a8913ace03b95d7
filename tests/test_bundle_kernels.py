"""The compiled residuals and their analytic derivatives."""

from dataclasses import replace

import numpy as np
import pytest

from fringecal.calibration.bundle import BundleOptions, StartValueError, bundle_adjust
from fringecal.calibration.model import POSE_COLUMNS, BundleProblem, Evaluator
from fringecal.frames import Frame
from fringecal.schemas import TableError
from fringecal.simulate.control_points import simulate_control_points, thesis_truth
from fringecal.triangulation import triangulate


@pytest.fixture(scope="module")
def small():
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, spacing_px=40, rng=7)
    return rig, art, poses, sim


def test_residuals_match_triangulation_and_the_sphere_distance(small):
    rig, art, poses, sim = small
    pr = BundleProblem.from_tables(rig, art, sim.control_points, poses)
    ev = Evaluator(pr, chunk_size=13)
    e = ev.evaluate(ev.layout.pack(rig.params, pr.poses), want_jac=False)
    cp = sim.control_points.iloc[pr.row]
    for si, sc in enumerate(rig.scanners):
        sel = pr.scanner_idx == si
        S, eps1 = triangulate(sc.camera, sc.projector, cp[["u_px", "v_px"]].to_numpy()[sel],
                              cp[["tau_x_rad", "tau_y_rad"]].to_numpy()[sel])
        np.testing.assert_allclose(e.res[sel, 0], eps1, atol=1e-11)
        centres = np.stack([Frame.from_params(pr.poses[m]).to_world(art.centres[s])
                            for m, s in zip(pr.meas_idx[sel], pr.sphere_idx[sel])])
        alpha2 = np.linalg.norm(S - centres, axis=1) - art.radii[pr.sphere_idx[sel]]
        np.testing.assert_allclose(e.res[sel, 1], alpha2, atol=1e-9)
    assert e.ok.all()
    assert e.cost == pytest.approx(np.sum(e.res**2), rel=1e-12)


def _dense_jacobian(ev, x):
    res, J, ok = ev.jacobian_rows(x)
    cols = ev.global_columns()
    n, p = len(res), ev.layout.n
    Jd = np.zeros((n, 2, p))
    for s in range(cols.shape[1]):
        m = cols[:, s] >= 0
        np.add.at(Jd, (np.flatnonzero(m), slice(None), cols[m, s]), J[m, :, s])
    return res, Jd


def _jacobian_errors(ev, x, Jd, steps):
    """(name, relative max difference) of each parameter's analytic Jacobian column
    ``Jd[:, :, i]`` against central differences (step ``steps[name]``, else 1e-6 of the
    value)."""
    for i, name in enumerate(ev.layout.names):
        h = steps.get(name.split(".")[-1], 1e-6 * max(1.0, abs(x[i])))
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        fd = (ev.evaluate(xp, False).res - ev.evaluate(xm, False).res) / (2 * h)
        yield name, np.abs(fd - Jd[:, :, i]).max() / np.abs(fd).max()


def test_analytic_jacobian_matches_finite_differences(small):
    """All 14 parameters of every sensor and all pose parameters, away from the truth and
    with distortion (the implicit-function derivatives of the undistortion are exercised)."""
    rig, art, poses, sim = small
    cp = sim.control_points.iloc[::9]
    rng = np.random.default_rng(3)
    p = rig.params.copy()
    p[:, :3] += rng.normal(0, 2, (4, 3))
    p[:, 3:6] += rng.normal(0, 2e-3, (4, 3))
    p[:, 9:12] *= 3.0  # stronger distortion than the truth
    start = replace(rig, free=np.ones((4, 14), bool)).with_params(p)
    pposes = poses.copy()
    pposes["tx_mm"] += 1.5
    pr = BundleProblem.from_tables(start, art, cp, pposes)
    ev = Evaluator(pr, chunk_size=5)
    x = ev.layout.pack(pr.rig.params, pr.poses)
    res, Jd = _dense_jacobian(ev, x)
    steps = {"k1": 1e-8, "k2": 1e-10, "k3": 1e-12, "p1": 1e-8, "p2": 1e-8}
    worst = 0.0
    for name, err in _jacobian_errors(ev, x, Jd, steps):
        worst = max(worst, err)
        assert err < 1e-5, f"{name}: relative difference {err:.2e}"
    assert worst > 0  # the comparison did compare something


@pytest.mark.parametrize("loss", ["none", "huber", "cauchy"])
def test_normal_equations_equal_the_dense_products(small, loss):
    rig, art, poses, sim = small
    pr = replace(BundleProblem.from_tables(rig, art, sim.control_points, poses), gamma1=1.7, gamma2=0.6)
    scales = (0.05, 0.1)
    ev = Evaluator(pr, chunk_size=17, loss=loss, scales=scales)
    x = ev.layout.pack(rig.params, pr.poses)
    e = ev.evaluate(x, True)
    res, Jd = _dense_jacobian(ev, x)
    a = np.abs(res) / np.array(scales)
    w = {"none": np.ones_like(a), "huber": np.where(a <= 1, 1, 1 / a), "cauchy": 1 / (1 + a * a)}[loss]
    N1 = np.einsum("n,ni,nj->ij", w[:, 0], Jd[:, 0], Jd[:, 0])
    N2 = np.einsum("n,ni,nj->ij", w[:, 1], Jd[:, 1], Jd[:, 1])
    b = 1.7 * np.einsum("n,ni->i", w[:, 0] * res[:, 0], Jd[:, 0]) + 0.6 * np.einsum("n,ni->i", w[:, 1] * res[:, 1], Jd[:, 1])
    np.testing.assert_allclose(e.N1, N1, rtol=1e-10, atol=1e-12 * np.abs(N1).max())
    np.testing.assert_allclose(e.N2, N2, rtol=1e-10, atol=1e-12 * np.abs(N2).max())
    np.testing.assert_allclose(e.b, b, rtol=1e-9, atol=1e-12 * np.abs(b).max())
    assert np.allclose(Jd[:, 0, ev.layout.pose_index.ravel()], 0)  # alpha1 ignores the pose


def test_unusable_start_values_and_bad_tables_are_explained(small):
    rig, art, poses, sim = small
    p = rig.params.copy()
    p[0, 9] = -5e-3  # k1 so strong that the lens model folds over inside the image
    pr = BundleProblem.from_tables(rig.with_params(p), art, sim.control_points, poses)
    with pytest.raises(StartValueError, match="cannot form rays at .* of scanner scanner1"):
        bundle_adjust(pr, BundleOptions(start="given"))
    bad = sim.control_points.copy()
    bad.loc[3, "sphere_id"] = "99"
    bad.loc[5, "scanner"] = "scanner9"
    bad.loc[6, "measurement"] = "77"
    with pytest.raises(TableError) as err:
        BundleProblem.from_tables(rig, art, bad, poses, source="cp.csv")
    text = str(err.value)
    assert "cp.csv" in text and "line 5, column 'sphere_id'" in text and "'99'" in text
    assert "line 7, column 'scanner'" in text and "line 8, column 'measurement'" in text
    off = sim.control_points.copy()
    off.loc[0, "u_px"] = 2048.0
    with pytest.raises(TableError, match="lies outside camera C1"):
        BundleProblem.from_tables(rig, art, off, poses)
    assert list(POSE_COLUMNS) == ["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]
