"""No rod, end-cap or glint point survives into a sphere fit; every rejection has a reason."""

import numpy as np
import pandas as pd
import pytest

from fringecal.frames import Frame
from fringecal.spheres.fit import SphereModel
from fringecal.spheres.robust import (
    RejectionConfig,
    SphereRejectionError,
    fit_plane_robust,
    fit_sphere_robust,
    rod_directions,
)
from fringecal.spheres.synthetic import sphere_node_cloud

NOISE = 0.02


def check_fit(cloud, fit, centre, usable=None):
    truth = cloud.truth
    usable = np.ones(len(truth), bool) if usable is None else usable
    kept = truth[fit.kept]
    # nothing of a rod or an end cap survives
    assert not np.isin(kept, ["rod", "endcap"]).any(), dict(zip(*np.unique(kept, return_counts=True)))
    # glints survive only inside the noise band (their error along the ray is mostly tangential)
    glints = fit.kept & (truth == "glint")
    assert np.all(np.abs(fit.model.residuals(cloud.points[glints])) <= fit.threshold_mm)
    # most of the sphere is kept
    assert fit.kept[(truth == "sphere") & usable].mean() > 0.6  # rod cones take a share (4 rods: ~1/3)
    # the centre is as good as the noise allows: within 5 standard uncertainties and of the
    # fit to the true sphere points only
    err = fit.model.centre - centre
    assert np.all(np.abs(err) < 5 * fit.model.centre_uncertainty + 1e-4), (err, fit.model.centre_uncertainty)
    clean = SphereModel.from_estimate(cloud.points[(truth == "sphere") & usable])
    assert np.abs(fit.model.centre - clean.centre).max() < 5 * clean.centre_uncertainty.max()
    # every point has one reason, and the counts add up
    assert sum(fit.rejected.values()) == fit.n_rejected == np.count_nonzero(fit.reason >= 0)
    assert np.array_equal(fit.reason < 0, fit.kept)


@pytest.mark.parametrize("seed", range(4))
def test_first_pass_detects_rods_and_end_caps(seed):
    """Random node geometry: three rods with end caps, 40 glints, 0.02 mm noise; rods
    unknown, found among the outliers."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-300, 300, 3)
    axes = rng.normal(size=(3, 3))
    cloud = sphere_node_cloud(centre, 25.0, axes, noise_mm=NOISE, n_glints=40, glint_mm=1.0, seed=seed)
    assert (cloud.truth == "endcap").sum() > 1000 and (cloud.truth == "rod").sum() > 1000
    fit = fit_sphere_robust(cloud.points, expected_radius=25.0, viewpoints=[cloud.camera, cloud.projector])
    check_fit(cloud, fit, centre)
    assert fit.rods_detected >= 1  # a rod hidden behind the sphere leaves nothing to detect
    assert fit.rejected["rod"] > 0.9 * np.isin(cloud.truth, ["rod", "endcap"]).sum()
    assert abs(fit.model.radius - 25.0) < 0.01


def test_second_pass_with_rods_from_the_artefact_and_pose(thesis_artefact, thesis_rig, thesis_dir):
    """Sphere 7 of the thesis artefact at pose 1 of table 6-1, seen by scanner one: its four
    rods come from the rods table and the pose; the radius is fixed to the CMM value."""
    rods = pd.read_csv(thesis_dir / "rods.csv", dtype=str)
    pose = pd.read_csv(thesis_dir / "poses_scanner1_table6-1.csv").iloc[0]
    T = Frame.from_params(pose[["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]].to_numpy(float))
    dirs = rod_directions(thesis_artefact, rods, "7", T)
    assert dirs.shape == (4, 3)
    local = thesis_artefact.centres_of(["5", "9", "8", "4"]) - thesis_artefact.centres_of(["7"])
    np.testing.assert_allclose(dirs @ T.R.T, local / np.linalg.norm(local, axis=1, keepdims=True), atol=1e-12)
    centre = T.to_world(thesis_artefact.centres_of(["7"]))[0]
    radius = thesis_artefact.radii[thesis_artefact.index(["7"])[0]]
    s = thesis_rig.scanners[0]
    cloud = sphere_node_cloud(centre, radius, dirs, camera=s.camera.pinhole, projector=s.projector.pinhole,
                              noise_mm=NOISE, n_glints=30, seed=3)
    assert (cloud.truth == "endcap").sum() > 500
    fit = fit_sphere_robust(cloud.points, radius, viewpoints=[s.camera.pinhole, s.projector.pinhole],
                            rod_axes=dirs, config=RejectionConfig(detect_rods=False))
    check_fit(cloud, fit, centre)
    assert fit.model.radius_fixed and fit.model.radius == radius


def test_caller_flags_come_first_and_are_counted():
    centre = np.array([10.0, 20.0, 30.0])
    cloud = sphere_node_cloud(centre, 25.0, [[1, 0, 0.3]], noise_mm=NOISE, seed=5)
    n = len(cloud.points)
    edge = cloud.incidence_rad > np.radians(70)
    glint = np.zeros(n, bool)
    glint[::97] = True
    pts = cloud.points.copy()
    pts[::501] = np.nan
    fit = fit_sphere_robust(pts, expected_radius=25.0, flags={"edge": edge, "glint": glint},
                            viewpoints=[cloud.camera, cloud.projector])
    finite = np.all(np.isfinite(pts), axis=1)
    assert fit.reasons[:3] == ("invalid", "edge", "glint")
    assert fit.rejected["invalid"] == (~finite).sum()
    assert fit.rejected["edge"] == (edge & finite).sum()
    assert fit.rejected["glint"] == (glint & finite & ~edge).sum()
    assert not fit.kept[edge | glint | ~finite].any()
    check_fit(cloud, fit, centre, usable=finite & ~edge & ~glint)
    with pytest.raises(ValueError, match="reserved"):
        fit_sphere_robust(pts, flags={"rod": edge})


def test_too_few_sphere_points_is_an_error_with_counts():
    cloud = sphere_node_cloud([0, 0, 0], 25.0, [], noise_mm=NOISE, seed=1)
    everything = np.ones(len(cloud.points), bool)
    with pytest.raises(SphereRejectionError, match="usable point") as err:
        fit_sphere_robust(cloud.points, flags={"edge": everything})
    assert err.value.counts["edge"] == len(cloud.points)


def test_robust_plane_ignores_the_sphere_on_it():
    rng = np.random.default_rng(2)
    st = rng.uniform(-80, 80, (5000, 2))
    plate = np.c_[st, rng.normal(0, NOISE, 5000)]
    u = rng.normal(size=(1500, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    ball = [0, 0, 30.0] + 10 * u[u[:, 2] > 0]
    fit = fit_plane_robust(np.vstack([plate, ball]), noise_mm=NOISE, toward=[0, 0, 1000])
    assert fit.kept[:5000].mean() > 0.99 and not fit.kept[5000:][ball[:, 2] > 30.5].any()
    assert abs(fit.model.normal[2] - 1) < 1e-6 and abs(fit.model.offset) < 0.002
