"""Scanner frames linked through shared artefact poses, sensors carried into the reference frame."""

import numpy as np
import pandas as pd
import pytest

from fringecal.frames import Frame
from fringecal.rig import Scanner, rig_in_frame
from fringecal.schemas import PosePlanTable, ScannerLinksTable, SphereCentresTable, read_table, validate_table
from fringecal.sensor import sensor_in_frame
from fringecal.spheres.linking import link_scanners, robust_mean_frame

COLS = ["measurement", "scanner", "tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad",
        "rms_mm", "n_spheres"]
#: scanner two's own frame seen from scanner one (near what the thesis data give)
T_S1_S2 = Frame.from_params([-1428.7, 4.4, 138.4, -0.026, 0.089, 0.0006])


def table_poses(thesis_dir):
    plan = read_table(thesis_dir / "poses_scanner1_table6-1.csv", PosePlanTable)
    return {r.measurement: Frame([r.tx_mm, r.ty_mm, r.tz_mm], [r.omega_rad, r.phi_rad, r.kappa_rad])
            for r in plan.itertuples()}


def jitter(T: Frame, rng, mm=0.02, rad=2e-5) -> Frame:
    return Frame(T.t + rng.normal(0, mm, 3), T.angles + rng.normal(0, rad, 3))


def poses_frame(rows):
    return pd.DataFrame([(m, s, *T.params, 0.01, 4) for m, s, T in rows], columns=COLS)


def test_two_scanners_linked_through_shared_poses_with_an_outlier(thesis_dir):
    rng = np.random.default_rng(0)
    T_s1_art = table_poses(thesis_dir)
    rows = []
    for m, T in T_s1_art.items():
        rows.append((m, "scanner1", jitter(T, rng)))
        T2 = T_S1_S2.inverse().compose(T)
        if m == "7":  # a bad pose (a mislabelled sphere, say): 3 mm and 1 mrad off
            T2 = Frame(T2.t + [3.0, 0, 0], T2.angles + [0.001, 0, 0])
        rows.append((m, "scanner2", jitter(T2, rng)))
    res = link_scanners(poses_frame(rows), "scanner1")
    link = res.links["scanner2"]
    assert link.n_measurements == 11 and link.n_rejected == 1 and "7" not in link.measurements
    # the mean of 11 estimates, each ~0.03 mm and ~3e-5 rad (x ~1 m lever) off
    assert np.abs(link.frame.t - T_S1_S2.t).max() < 0.1
    assert np.abs(link.frame.angles - T_S1_S2.angles).max() < 3e-5
    assert 0.01 < link.translation_spread_mm < 0.3 and link.u_translation_mm < link.translation_spread_mm
    assert link.via == ("scanner1", "scanner2")
    table = validate_table(res.table(), ScannerLinksTable, "links")
    assert list(table.scanner) == ["scanner1", "scanner2"]


def test_sensors_carried_into_the_reference_frame_project_identically(thesis_rig):
    """Scanner two's truth sensors (table 6-8, scanner one's frame) expressed in its own frame
    and brought back by the link: same parameters, same projections."""
    s2 = thesis_rig.scanners[1]
    own = Scanner(s2.name, sensor_in_frame(s2.camera, T_S1_S2.inverse()),
                  sensor_in_frame(s2.projector, T_S1_S2.inverse()))
    X_s1 = np.random.default_rng(1).uniform(-400, 400, (50, 3))
    X_s2 = T_S1_S2.to_local(X_s1)
    np.testing.assert_allclose(own.camera.project(X_s2), s2.camera.project(X_s1), atol=1e-9)
    back = rig_in_frame(thesis_rig.with_params(np.vstack([thesis_rig.params[:2], own.camera.params,
                                                          own.projector.params])),
                        {"scanner1": Frame(np.zeros(3), np.zeros(3)), "scanner2": T_S1_S2})
    np.testing.assert_allclose(back.params, thesis_rig.params, atol=1e-9)
    for sensor, truth in zip(back.sensors, thesis_rig.sensors):
        np.testing.assert_allclose(sensor.project(X_s1), truth.project(X_s1), atol=1e-9)
    with pytest.raises(KeyError, match="no link"):
        rig_in_frame(thesis_rig, {"scanner1": Frame(np.zeros(3), np.zeros(3))})


def test_chained_through_an_intermediate_scanner_and_unlinked_reported():
    rng = np.random.default_rng(2)
    T_A_B = Frame.from_params([800, 0, 50, 0.01, 0.3, -0.02])
    T_B_C = Frame.from_params([700, 20, -30, -0.02, 0.25, 0.01])
    rows = []
    for m in range(8):
        T_A_art = Frame.from_params(np.r_[rng.uniform(-300, 300, 3), rng.uniform(-0.3, 0.3, 3)])
        T_B_art = T_A_B.inverse().compose(T_A_art)
        T_C_art = T_B_C.inverse().compose(T_B_art)
        if m < 4:  # A and B see the artefact
            rows += [(str(m), "A", T_A_art), (str(m), "B", T_B_art)]
        else:  # B and C see it
            rows += [(str(m), "B", T_B_art), (str(m), "C", T_C_art)]
    rows.append(("9", "D", Frame.from_params([0, 0, 0, 0, 0, 0])))
    res = link_scanners(poses_frame(rows), "A")
    assert res.links["C"].via == ("A", "B", "C")
    np.testing.assert_allclose(res.links["C"].frame.params, T_A_B.compose(T_B_C).params, atol=1e-9)
    assert set(res.unlinked) == {"D"}
    with pytest.raises(ValueError, match="reference scanner 'E' has no poses"):
        link_scanners(poses_frame(rows), "E")


def test_thesis_tables_link_scanner_two_onto_scanner_one(thesis_dir, thesis_artefact):
    """Tables 6-1 and 6-4 (angles printed to 1 mrad) link the frames to ~1.5 mm spread; the
    link carries scanner two's measured centres (table 6-6) onto scanner one's artefact
    poses (table 6-1) within a few mm."""
    p1 = read_table(thesis_dir / "poses_scanner1_table6-1.csv", PosePlanTable).assign(scanner="scanner1")
    p2 = read_table(thesis_dir / "poses_scanner2_table6-4.csv", PosePlanTable).assign(scanner="scanner2")
    poses = pd.concat([p1, p2]).assign(rms_mm=0.0, n_spheres=4)
    link = link_scanners(poses, "scanner1").links["scanner2"]
    assert link.n_measurements == 12 and link.translation_spread_mm < 3
    centres = read_table(thesis_dir / "centres_scanner2_table6-6.csv", SphereCentresTable)
    T1 = table_poses(thesis_dir)
    worst = 0.0
    for m, g in centres.groupby("measurement"):
        in_s1 = link.frame.to_world(g[["x_mm", "y_mm", "z_mm"]].to_numpy(float))
        predicted = T1[m].to_world(thesis_artefact.centres_of(g["sphere_id"]))
        worst = max(worst, np.linalg.norm(in_s1 - predicted, axis=1).max())
    assert worst < 5.0


def test_robust_mean_needs_three_estimates_to_reject():
    T = Frame.from_params([1, 2, 3, 0.1, 0.2, 0.3])
    bad = Frame(T.t + 10, T.angles)
    mean, keep = robust_mean_frame([T, bad])
    assert keep.all() and np.allclose(mean.t, T.t + 5)
    mean, keep = robust_mean_frame([T, T, T, bad])
    assert keep.tolist() == [True, True, True, False] and np.allclose(mean.params, T.params)
