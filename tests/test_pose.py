"""Poses from labelled centres reproduce the thesis's tables 6-1 and 6-4."""

import numpy as np
import pandas as pd
import pytest

from fringecal.artefact import Artefact, load_artefact
from fringecal.schemas import PosePlanTable, SphereCentresTable, read_table
from fringecal.spheres.pose import estimate_poses

COLS = ["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]


def printed_and_estimated(thesis_dir, scanner, cmm):
    centres_file, poses_file = {
        1: ("centres_scanner1_table6-3.csv", "poses_scanner1_table6-1.csv"),
        2: ("centres_scanner2_table6-6.csv", "poses_scanner2_table6-4.csv"),
    }[scanner]
    art = load_artefact(thesis_dir / cmm)
    res = estimate_poses(read_table(thesis_dir / centres_file, SphereCentresTable), art)
    printed = read_table(thesis_dir / poses_file, PosePlanTable).set_index("measurement")[COLS]
    est = res.poses.set_index("measurement")[COLS].loc[printed.index]
    return printed, est, res


@pytest.mark.parametrize("scanner", [1, 2])
def test_reproduces_printed_poses_with_cmm_measurement_2(thesis_dir, scanner):
    printed, est, res = printed_and_estimated(thesis_dir, scanner, "artefact_cmm2.csv")
    assert res.skipped.empty and (res.poses.n_spheres == 4).all()
    diff = (est - printed).abs()
    # Angles are printed to 0.001 rad (phi to 0.0001 for scanner one): within half a unit.
    assert diff[["omega_rad", "kappa_rad"]].to_numpy().max() <= 0.0005
    assert diff["phi_rad"].max() <= (0.00005 if scanner == 1 else 0.0005)
    # Translations are printed to 0.001 mm; the centres they come from are rounded to
    # 0.001 mm too, which moves the fitted translation by up to ~0.002 mm.
    assert diff[["tx_mm", "ty_mm", "tz_mm"]].to_numpy().max() <= 0.002
    # table 6-2 prints R^T of pose 1 for scanner one (docs/conventions.md)
    if scanner == 1:
        from fringecal.rotation import rotation_matrix

        Rt = rotation_matrix(*est.loc["1", ["omega_rad", "phi_rad", "kappa_rad"]]).T
        np.testing.assert_allclose(Rt.round(3), [[-0.075, -0.997, -0.001], [0.001, -0.001, 1.000], [-0.997, 0.075, 0.001]], atol=1e-12)


def test_cmm_measurement_1_does_not_reproduce_scanner_two(thesis_dir):
    printed, est, _ = printed_and_estimated(thesis_dir, 2, "artefact_cmm1.csv")
    assert (est - printed)[["tx_mm", "ty_mm", "tz_mm"]].abs().to_numpy().max() > 0.05


def test_bad_groups_are_reported_and_others_still_come_out(thesis_dir, thesis_artefact):
    c = read_table(thesis_dir / "centres_scanner1_table6-3.csv", SphereCentresTable)
    c = c[~((c.measurement == "2") & c.sphere_id.isin(["8", "9"]))]  # pose 2 keeps 2 spheres
    # a ball-bar-like line of three spheres added to the artefact
    art = Artefact(thesis_artefact.ids + ("L1", "L2", "L3"),
                   np.vstack([thesis_artefact.centres, [[0, 0, -500], [0, 300, -500], [0, 600, -500]]]),
                   np.r_[thesis_artefact.diameters, 50, 50, 50])
    line = pd.DataFrame({"measurement": "L", "scanner": "scanner1", "sphere_id": ["L1", "L2", "L3"],
                         "x_mm": [0.0, 0.1, 0.2], "y_mm": [0.0, 300.0, 600.0], "z_mm": [0.0, 0.0, 0.0]})
    unknown = pd.DataFrame({"measurement": "U", "scanner": "scanner1", "sphere_id": ["5", "6", "42"],
                            "x_mm": [0.0, 1.0, 2.0], "y_mm": [3.0, 1.0, 0.0], "z_mm": [0.0, 5.0, 1.0]})
    res = estimate_poses(pd.concat([c, line, unknown], ignore_index=True), art)
    reasons = res.skipped.set_index("measurement").reason
    assert "2 points; at least 3" in reasons["2"]
    assert "collinear" in reasons["L"] and "spheres L1, L2, L3" in reasons["L"]
    assert "unknown sphere id(s) ['42']" in reasons["U"]
    assert len(res.poses) == 11
