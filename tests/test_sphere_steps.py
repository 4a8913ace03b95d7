"""Sphere fits -> labels -> poses -> linked frames, as tables, with bad groups reported."""

import numpy as np
import pandas as pd
import pytest

from fringecal.frames import Frame
from fringecal.schemas import (
    REJECTION_REASONS,
    LabelOutcomesTable,
    PosePlanTable,
    SphereFitsTable,
    TableError,
    read_table,
    write_table,
)
from fringecal.spheres.labelling import LabellingConfig
from fringecal.spheres.poses_and_links import centres_from_fits, label_pose_link, sphere_fit_row
from fringecal.spheres.reference_data import sphere_reference_data
from fringecal.spheres.robust import RejectionConfig, fit_sphere_robust

T_S1_S2 = Frame.from_params([-1428.7, 4.4, 138.4, -0.026, 0.089, 0.0006])
VISIBLE = {"scanner1": [str(i) for i in range(4, 10)], "scanner2": [str(i) for i in range(10, 16)]}


def candidate_fit(centre, radius, rng, seed):
    """A 70-degree cap of 400 points with 10 um noise and 20 outliers, fitted robustly."""
    ds = sphere_reference_data(centre, radius, 400, 70.0, rng.normal(size=3), 0.0, seed=seed)
    pts = ds.points + rng.normal(0, 0.01, (400, 1)) * (ds.points - centre) / radius
    pts[:20] += rng.normal(0, 2.0, (20, 3))
    return fit_sphere_robust(pts, expected_radius=radius, config=RejectionConfig(noise_mm=0.01))


@pytest.fixture(scope="module")
def simulated_fits(thesis_artefact, thesis_dir):
    rng = np.random.default_rng(8)
    plan = read_table(thesis_dir / "poses_scanner1_table6-1.csv", PosePlanTable)
    truth = {}
    rows = []
    for r in plan.itertuples():
        T_s1 = Frame([r.tx_mm, r.ty_mm, r.tz_mm], [r.omega_rad, r.phi_rad, r.kappa_rad])
        for scanner, T in (("scanner1", T_s1), ("scanner2", T_S1_S2.inverse().compose(T_s1))):
            truth[(r.measurement, scanner)] = T
            ids = list(VISIBLE[scanner])
            if r.measurement == "2" and scanner == "scanner1":
                ids = ids[:2]  # the artefact mostly out of view: two spheres only
            elif int(r.measurement) % 2:
                ids.remove(ids[int(r.measurement) % 6])  # one sphere occluded
            centres = T.to_world(thesis_artefact.centres_of(ids))
            if r.measurement == "5" and scanner == "scanner2":
                centres = T.to_world(rng.uniform(-600, 600, (5, 3)))  # clutter, no artefact
            if r.measurement == "3":  # a false candidate (a hexapod ball joint, say)
                centres = np.vstack([centres, T.to_world([[-300.0, 250.0, -400.0]])])
            for k in rng.permutation(len(centres)):
                fit = candidate_fit(centres[k], 25.0, rng, seed=len(rows))
                rows.append(sphere_fit_row(r.measurement, scanner, f"c{k}", fit, bbox=(10, 20, 110, 120)))
    return pd.DataFrame(rows), truth


def test_fits_table_round_trips_with_empty_sphere_ids(simulated_fits, tmp_path):
    fits, _ = simulated_fits
    assert (fits["sphere_id"] == "").all()
    assert {f"rejected_{r}" for r in ("invalid", "rod", "silhouette", "residual")} <= set(fits.columns)
    assert set(REJECTION_REASONS) >= {"edge", "glint", "rod", "residual"}
    assert fits["rejected_residual"].between(15, 40).all()  # the 20 planted outliers (+ tail)
    path = write_table(fits, tmp_path / "sphere_fits.csv", SphereFitsTable)
    back = read_table(path, SphereFitsTable)
    assert (back["sphere_id"] == "").all() and len(back) == len(fits)
    np.testing.assert_allclose(back["x_mm"], fits["x_mm"], rtol=1e-9)
    bad = fits.copy()
    bad.loc[3, "radius_mm"] = -1.0
    bad.loc[5, "candidate"] = bad.loc[4, "candidate"]
    bad.loc[5, ["measurement", "scanner"]] = bad.loc[4, ["measurement", "scanner"]]
    write_table(bad, tmp_path / "bad.csv")
    with pytest.raises(TableError) as err:
        read_table(tmp_path / "bad.csv", SphereFitsTable)
    msg = str(err.value)
    assert "line 5, column 'radius_mm'" in msg and "line 7, column 'measurement, scanner, candidate'" in msg


def test_label_pose_link_recovers_poses_and_the_scanner_frame(simulated_fits, thesis_artefact, tmp_path):
    fits, truth = simulated_fits
    res = label_pose_link(fits, thesis_artefact, "scanner1", LabellingConfig(centre_u_mm=0.01))
    out = res.labels.set_index(["measurement", "scanner"])
    assert out.loc[("5", "scanner2"), "status"] == "refused"
    assert out.loc[("5", "scanner2"), "reason"] == "inconsistent"
    assert out.loc[("2", "scanner1"), "reason"] == "too_few_candidates"
    assert (out.drop(index=[("5", "scanner2"), ("2", "scanner1")])["status"] == "labelled").all()
    # the false candidate of measurement 3 is left unlabelled, the rest are right
    m3 = res.fits[(res.fits.measurement == "3")]
    assert (m3["sphere_id"] == "").sum() == 2
    # poses: every group with three or more labelled spheres, against the truth
    poses = res.poses.poses.set_index(["measurement", "scanner"])
    assert len(poses) == 22
    skipped = res.poses.skipped.set_index(["measurement", "scanner"])["reason"]
    assert "labelling refused: too_few_candidates" in skipped[("2", "scanner1")]
    assert "labelling refused: inconsistent" in skipped[("5", "scanner2")]
    for key, row in poses.iterrows():
        T = truth[key]
        assert np.abs(row[["tx_mm", "ty_mm", "tz_mm"]].to_numpy(float) - T.t).max() < 0.05
        assert np.abs(row[["omega_rad", "phi_rad", "kappa_rad"]].to_numpy(float) - T.angles).max() < 5e-5
    link = res.links.links["scanner2"]
    assert np.abs(link.frame.t - T_S1_S2.t).max() < 0.03 and link.n_measurements == 10
    assert np.abs(link.frame.angles - T_S1_S2.angles).max() < 2e-5
    # tables are schema-valid and write cleanly
    write_table(res.fits, tmp_path / "fits.csv", SphereFitsTable)
    write_table(res.labels, tmp_path / "labels.csv", LabelOutcomesTable)
    labels_back = read_table(tmp_path / "labels.csv", LabelOutcomesTable)
    assert labels_back["rms_mm"].isna().sum() == 2
    assert len(centres_from_fits(res.fits)) == (res.fits["sphere_id"] != "").sum()
    assert list(res.links_table()["scanner"]) == ["scanner1", "scanner2"]


def test_label_step_writes_every_table_and_reports_bad_groups(simulated_fits, thesis_artefact, tmp_path):
    from fringecal.run.config import RunConfig
    from fringecal.rundir import RunDir, measurement_id
    from fringecal.schemas import PosesTable, ScannerLinksTable
    from fringecal.steps import get_step, run_step

    fits, truth = simulated_fits
    rd = RunDir(tmp_path / "run").create()
    rd.artefact.save(thesis_artefact)
    groups = list(fits.groupby(["measurement", "scanner"], sort=False))
    ids = [measurement_id(m, s) for (m, s), _ in groups]
    rd.acquisition.save(pd.DataFrame({"measurement": ids, "kind": "artefact", "pose": [m for (m, _), _ in groups],
                                      "scanner": [s for (_, s), _ in groups], "store": [rd.store(i).rel for i in ids],
                                      "source": "test"}))
    for i, (_, g) in zip(ids, groups):
        rd.fits_first(i).save(g.reset_index(drop=True))
    cfg = RunConfig(reference_scanner="scanner1",
                    extraction={"labelling": {"centre_u_mm": 0.01}, "use_planned_poses": False})
    record = run_step(get_step("label"), rd, cfg)
    assert set(record["outputs"]) == {f.rel for f in (rd.sphere_fits_labelled, rd.label_outcomes, rd.sphere_centres,
                                                      rd.poses, rd.poses_skipped, rd.scanner_links)}
    outcomes = rd.label_outcomes.load()
    refused = outcomes[outcomes.status == "refused"]
    assert set(zip(refused.measurement, refused.scanner)) == {("2", "scanner1"), ("5", "scanner2")}
    assert len(read_table(rd.poses.path, PosesTable)) == 22
    links = read_table(rd.scanner_links.path, ScannerLinksTable).set_index("scanner")
    assert abs(links.loc["scanner2", "tx_mm"] - T_S1_S2.t[0]) < 0.03
    assert not [p for p in rd.label_outcomes.path.parent.iterdir() if p.name.startswith(".")]  # nothing half-written
