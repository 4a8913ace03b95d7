"""Labelling fitted centres against the thesis artefact: right or refused, never guessed."""

import numpy as np
import pandas as pd
import pytest

from fringecal.frames import Frame
from fringecal.schemas import PosePlanTable, SphereCentresTable, read_table
from fringecal.spheres.label_scanners import label_sphere_fits
from fringecal.spheres.labelling import LabellingConfig, LabellingRefused, ambiguous_subsets, label_spheres
from fringecal.spheres.poses_and_links import label_pose_link

SCANNER_ONE = [str(i) for i in range(4, 10)]
SCANNER_TWO = [str(i) for i in range(10, 16)]
NOISE = 0.005  # per coordinate, the simulated rig's fitted-centre accuracy
#: centres from true (calibrated) sensors: what LabellingConfig's defaults were before they
#: were sized for prior calibrations (0.75 mm, 0.8 % in scale)
TIGHT = LabellingConfig(centre_u_mm=0.02, scale_tol=1e-4)


def random_pose(rng) -> Frame:
    return Frame.from_params(np.r_[rng.uniform(-1500, 1500, 3), rng.uniform(-np.pi, np.pi, 3)])


def observe(artefact, ids, rng, noise=NOISE):
    T = random_pose(rng)
    X = T.to_world(artefact.centres_of(ids)) + rng.normal(0, noise, (len(ids), 3))
    order = rng.permutation(len(ids))
    return X[order], [ids[i] for i in order], T


@pytest.mark.parametrize("visible", [SCANNER_ONE, SCANNER_TWO])
def test_visible_sets_with_drops_and_false_candidates(thesis_artefact, visible):
    rng = np.random.default_rng(int(visible[0]))
    for trial in range(15):
        # all six, or five of them (one dropped: occluded or out of view)
        ids = visible if trial % 3 == 0 else [s for s in visible if s != visible[trial % 6]]
        X, truth, T = observe(thesis_artefact, ids, rng)
        n_false = trial % 3
        false = T.to_world(rng.uniform([-700, -100, -200], [100, 1000, 600], (n_false, 3)))
        cand = np.vstack([X, false])
        lab = label_spheres(cand, thesis_artefact, uncertainties=np.full(len(cand), NOISE), config=TIGHT)
        assert list(lab.sphere_ids) == truth + [None] * n_false
        assert set(lab.unlabelled) == set(range(len(X), len(cand)))
        np.testing.assert_allclose(lab.T_scanner_artefact.params[:3], T.params[:3], atol=0.05)
        assert lab.rms_mm < 4 * NOISE


def test_partial_fits_and_foreign_spheres(thesis_artefact):
    rng = np.random.default_rng(1)
    X, truth, _ = observe(thesis_artefact, SCANNER_ONE, rng)
    # a poorly seen sphere, 0.15 mm off, honest about it (u = 0.06 mm): still labelled
    X_partial = X.copy()
    X_partial[0] += [0.09, -0.09, 0.09]
    u = np.full(6, NOISE)
    u[0] = 0.06
    assert list(label_spheres(X_partial, thesis_artefact, u, config=TIGHT).sphere_ids) == truth
    # 2 mm off and overconfident: left out, the other five still labelled
    X_bad = X.copy()
    X_bad[0] += [2.0, 0.0, 0.0]
    lab = label_spheres(X_bad, thesis_artefact, np.full(6, NOISE), config=TIGHT)
    assert list(lab.sphere_ids) == [None] + truth[1:]
    assert "does not fit" in lab.unlabelled[0]
    # a 20 mm ball next to the artefact (radius check)
    radii = np.full(6, 25.0)
    radii[2] = 10.0
    lab = label_spheres(X, thesis_artefact, np.full(6, NOISE), radii=radii, config=TIGHT)
    assert lab.sphere_ids[2] is None and "radius 10.000 mm" in lab.unlabelled[2]


def test_ambiguous_subsets_are_refused_with_the_alternatives(thesis_artefact):
    """Spheres 10, 11, 12, 14 are symmetric within 0.1 mm (swap 10<->12 and 11<->14):
    exact centres, and still refused."""
    ids = ["10", "11", "12", "14"]
    X = thesis_artefact.centres_of(ids)
    with pytest.raises(LabellingRefused) as err:
        label_spheres(X, thesis_artefact, np.full(4, 0.005))
    assert err.value.reason == "ambiguous"
    assert tuple(ids) in err.value.alternatives and ("12", "14", "10", "11") in err.value.alternatives
    # a triangle of three ~600 mm rods: refused too (1 and 3 are 599.889/599.893 mm from 2)
    with pytest.raises(LabellingRefused, match="ambiguous"):
        label_spheres(thesis_artefact.centres_of(["1", "2", "3"]), thesis_artefact)
    # what a planner should avoid: the ambiguous four-sphere subsets of scanner one's view
    amb = [s for s, _ in ambiguous_subsets(thesis_artefact, 4, SCANNER_ONE, TIGHT)]
    assert ("4", "5", "6", "8") in amb and len(amb) < 15
    assert not list(ambiguous_subsets(thesis_artefact, 5, SCANNER_ONE, TIGHT))
    # with the tolerances of prior calibrations (the defaults) no view of one octahedron is
    # unambiguous: the plan is needed (docs/spheres.md, benchmarks/labelling_rigs.py)
    assert len(list(ambiguous_subsets(thesis_artefact, 6, SCANNER_ONE))) == 1


def test_a_prior_pose_resolves_the_ambiguity(thesis_artefact):
    rng = np.random.default_rng(4)
    ids = ["10", "11", "12", "14"]
    X, truth, T = observe(thesis_artefact, ids, rng)
    # the prior may be off by centimetres and degrees (a planned hexapod pose)
    prior = Frame(T.t + [20.0, -15.0, 10.0], T.angles + [0.02, -0.01, 0.02])
    lab = label_spheres(X, thesis_artefact, prior=prior)
    assert list(lab.sphere_ids) == truth


def test_inconsistent_and_too_few_candidates(thesis_artefact):
    rng = np.random.default_rng(2)
    with pytest.raises(LabellingRefused, match="too_few_candidates"):
        label_spheres(thesis_artefact.centres_of(["4", "5"]), thesis_artefact)
    with pytest.raises(LabellingRefused, match="inconsistent"):
        label_spheres(rng.uniform(0, 1000, (5, 3)), thesis_artefact)
    # the mirror image of six spheres: every distance matches, no rotation does. (Some
    # four-sphere subsets are nearly mirror-symmetric, so the refusal may say ambiguous.)
    mirror = thesis_artefact.centres_of(SCANNER_ONE) * [-1, 1, 1]
    with pytest.raises(LabellingRefused) as err:
        label_spheres(mirror, thesis_artefact)
    assert err.value.reason in ("inconsistent", "ambiguous")
    # allowed ids that exclude the truth
    X, _, _ = observe(thesis_artefact, SCANNER_ONE, rng)
    with pytest.raises(LabellingRefused) as err:
        label_spheres(X, thesis_artefact, allowed_ids=SCANNER_TWO)
    assert err.value.reason in ("inconsistent", "ambiguous")


def thesis_fits(thesis_dir):
    frames = []
    for name in ("centres_scanner1_table6-3.csv", "centres_scanner2_table6-6.csv"):
        c = read_table(thesis_dir / name, SphereCentresTable).sample(frac=1, random_state=3)
        c = c.rename(columns={"sphere_id": "truth"}).reset_index(drop=True)
        c["candidate"] = c.groupby(["measurement", "scanner"]).cumcount().astype(str)
        frames.append(c)
    return pd.concat(frames, ignore_index=True)


def test_thesis_centres_need_the_plan_or_each_other_and_get_it_right(thesis_dir, thesis_artefact):
    """The thesis's own fitted centres (tables 6-3, 6-6) are 0.2-0.5 mm off the CMM shape
    before calibration and show four spheres of near-regular octahedra: distances alone
    cannot tell them apart, so every measurement is refused. With the planned poses
    (table 6-1, in scanner one's frame; scanner two's frame is found by consensus) all 24
    are labelled, all correctly; without them the two scanners' views together label all
    24 the same way."""
    fits = thesis_fits(thesis_dir)
    cfg = LabellingConfig(centre_u_mm=0.15)
    labelled, outcomes = label_sphere_fits(fits, thesis_artefact, cfg)
    assert (outcomes["status"] == "refused").all() and (outcomes["reason"] == "ambiguous").all()
    assert (labelled["sphere_id"] == "").all()
    plan = read_table(thesis_dir / "poses_scanner1_table6-1.csv", PosePlanTable)
    planned = {r.measurement: Frame([r.tx_mm, r.ty_mm, r.tz_mm], [r.omega_rad, r.phi_rad, r.kappa_rad])
               for r in plan.itertuples()}
    labelled, outcomes = label_sphere_fits(fits, thesis_artefact, cfg, planned=planned)
    assert (outcomes["status"] == "labelled").all() and (outcomes["method"] == "planned pose").all()
    assert (labelled["sphere_id"] == labelled["truth"]).all()
    assert outcomes["n_labelled"].eq(4).all()
    # without the plan (issue 28): the link both scanners' possible labellings agree on in
    # all 12 measurements, then each measurement by the two views together: all right too
    fits = fits.assign(sphere_id="", radius_mm=25.0, rms_mm=0.01, n_points=1000, u_x_mm=0.01, u_y_mm=0.01,
                       u_z_mm=0.01, cap_angle_deg=60.0, coverage=0.5, n_rejected=0)
    res = label_pose_link(fits.drop(columns="truth"), thesis_artefact, "scanner1", cfg)
    assert (res.labels["status"] == "labelled").all() and (res.labels["method"] == "linked pose").all()
    assert (res.fits["sphere_id"] == fits["truth"]).all() and not res.links.unlinked
