"""Drift check (section 4.5.2) on the thesis's table 4-1 and on a synthetic constant drift."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from fringecal.hexapod.drift import drift_check, thesis_reading
from fringecal.schemas import DriftCentresTable, TableError, read_table


@pytest.fixture(scope="module")
def table41(thesis_dir):
    return read_table(thesis_dir / "drift_table4-1.csv", DriftCentresTable)


def test_table_4_1_displacements(table41):
    rep = drift_check(table41, scan_duration_s=15.0, tolerance_um=5.0, interval_s=120.0)
    pairs = rep.pairs.set_index(["sphere_id", "from_measurement"])
    # sphere 2, measurement 1 -> 2: (-0.160, -0.052, +0.002) mm
    assert pairs.loc[("2", "1"), ["dx_um", "dy_um", "dz_um"]].tolist() == pytest.approx([-160, -52, 2], abs=1e-6)
    assert pairs.loc[("2", "1"), "displacement_um"] == pytest.approx(np.sqrt(160**2 + 52**2 + 2**2))
    assert len(rep.pairs) == 6 and set(rep.pairs.dt_s) == {120.0}
    assert rep.per_sphere.set_index("sphere_id").mean_displacement_um.round(1).to_dict() == \
        {"1": 54.6, "2": 159.7, "3": 75.3}
    assert rep.mean_displacement_um == pytest.approx(96.55, abs=0.01)
    assert rep.expected_scan_drift_um == pytest.approx(96.55 * 15 / 120, abs=0.01)  # 12.07 um
    assert not rep.ok  # against the 5 um of section 4.1
    assert drift_check(table41, 15.0, 15.0, 120.0).ok


def test_how_the_thesis_numbers_follow(table41):
    """53 um, ~7 um (section 4.5.2) and ~13 um (section 4.6) from table 4-1."""
    r = thesis_reading(table41)
    assert r["mean_3d_consecutive"] == pytest.approx(96.55, abs=0.01)
    assert r["mean_3d_all_pairs"] == pytest.approx(113.58, abs=0.01)
    assert r["mean_abs_coordinate_all_pairs"] == pytest.approx(54.89, abs=0.01)
    assert r["mean_abs_dy_consecutive"] == pytest.approx(53.0, abs=1e-9)  # the only exact 53
    assert round(r["thesis_53_x_15_over_120"]) == 7  # "approximately 7 um" is 15 s / 120 s = 1/8
    assert round(r["thesis_53_x_one_quarter"]) == 13  # "one quarter" gives the 13 um of 4.6


def test_constant_velocity_drift_is_recovered(rng):
    v = np.array([0.3, -0.1, 0.2])  # um/s
    times = np.array([0.0, 90.0, 250.0, 400.0])
    base = rng.uniform(-500, 500, (4, 3))
    rows = [(str(m), f"s{k}", *(base[k] + v * t / 1000.0), t) for m, t in enumerate(times) for k in range(4)]
    df = pd.DataFrame(rows, columns=["measurement", "sphere_id", "x_mm", "y_mm", "z_mm", "time_s"])
    rep = drift_check(df.sample(frac=1.0, random_state=1), scan_duration_s=30.0, tolerance_um=11.3)
    assert rep.mean_velocity_um_s == pytest.approx(np.linalg.norm(v), rel=1e-9)
    assert rep.expected_scan_drift_um == pytest.approx(30.0 * np.linalg.norm(v), rel=1e-9)
    assert rep.ok and not drift_check(df, 30.0, 11.2).ok


def test_bad_drift_input(tmp_path):
    with pytest.raises(ValueError, match="no time_s column"):
        drift_check(pd.DataFrame({"measurement": ["1", "2"], "sphere_id": ["a", "a"], "x_mm": [0, 0.0],
                                  "y_mm": [0, 0.0], "z_mm": [0, 0.0]}))
    p = tmp_path / "c.csv"
    p.write_text("measurement,sphere_id,x_mm,y_mm\n1,1,0,0\n")
    with pytest.raises(TableError, match="missing required column"):
        read_table(p, DriftCentresTable)
    p.write_text("measurement,sphere_id,x_mm,y_mm,z_mm\n1,1,0,0,0\n1,1,0,0,x\n")
    with pytest.raises(TableError, match=r"line 3, column 'sphere_id'.*duplicate|line 3, column 'z_mm'"):
        read_table(p, DriftCentresTable)
