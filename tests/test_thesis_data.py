"""The thesis tables typed into configs/thesis, checked against printed values."""

import numpy as np
import pandas as pd
import pytest
import yaml

from fringecal.artefact import load_artefact, load_rods
from fringecal.config import RigConfig, load_yaml_model
from fringecal.schemas import PosePlanTable, SphereCentresTable, ThermalLogTable, read_table


def test_artefact_both_cmm_sets_table_3_13(thesis_dir):
    m1 = load_artefact(thesis_dir / "artefact_cmm1.csv")
    m2 = load_artefact(thesis_dir / "artefact_cmm2.csv")
    assert len(m1) == len(m2) == 15
    np.testing.assert_array_equal(m1.centres_of(["7"]), [[0, 0, 0]])
    np.testing.assert_array_equal(m1.centres_of(["2"]), [[-298.716, 972.905, 520.204]])
    np.testing.assert_array_equal(m2.centres_of(["2"]), [[-298.899, 972.832, 520.098]])
    np.testing.assert_array_equal(m1.centres_of(["15"]), [[-597.998, 1463.597, 348.008]])
    np.testing.assert_array_equal(m2.centres_of(["15"]), [[-598.162, 1463.537, 347.917]])
    np.testing.assert_array_equal(m2.centres_of(["11"]), [[-303.592, 1954.133, 527.371]])
    # sum over all coordinates, a checksum against typing errors in any cell
    assert m1.centres.sum() == pytest.approx(12778.165, abs=1e-6)
    assert m2.centres.sum() == pytest.approx(12777.268, abs=1e-6)


def test_sphere_diameters_table_3_14(thesis_dir, thesis_artefact):
    d = pd.read_csv(thesis_dir / "sphere_diameters.csv")
    assert d.loc[d.sphere_id == 13, "diameter_mm"].item() == 50.013
    assert d.loc[d.sphere_id == 8, "diameter_mm"].item() == 49.989
    # printed averages are the mean of the two measurements, rounded
    np.testing.assert_allclose(d[["diameter_1_mm", "diameter_2_mm"]].mean(axis=1), d.diameter_mm, atol=0.00051)
    np.testing.assert_array_equal(thesis_artefact.diameters, d.diameter_mm)


def test_rods_tables_3_11_and_3_12(thesis_dir, thesis_artefact):
    single = load_rods(thesis_dir / "rods.csv", thesis_artefact)
    assembled = load_rods(thesis_dir / "rods_assembled.csv", thesis_artefact)
    assert len(single) == len(assembled) == 39 == 3 * 15 - 6  # Maxwell-Laman count
    r = single.set_index("rod_id")
    assert (r.loc["36", "sphere_a"], r.loc["36", "sphere_b"], r.loc["36", "length_mm"]) == ("12", "15", 600.832)
    assert r.loc["8", "length_mm"] == 596.134
    a = assembled.set_index("rod_id")
    assert a.loc["13", "length_mm"] == 596.793 and float(a.loc["13", "sd_mm"]) == 0.1064
    # the printed means come from unrounded repeats: within 2 um of the mean of the printed ones
    np.testing.assert_allclose(single[["length_1_mm", "length_2_mm", "length_3_mm"]].astype(float).mean(axis=1),
                               single.length_mm, atol=0.002)
    # every rod joins two spheres once; each sphere carries 4 to 7 rods
    pairs = {frozenset(p) for p in zip(single.sphere_a, single.sphere_b)}
    assert len(pairs) == 39
    deg = pd.concat([single.sphere_a, single.sphere_b]).value_counts()
    assert deg.min() >= 3 and deg.sum() == 78


def test_assembled_lengths_agree_with_coordinates(thesis_dir, thesis_artefact):
    """Table 3-12 is the same CMM session as table 3-13: lengths agree to tens of um."""
    a = load_rods(thesis_dir / "rods_assembled.csv")
    idx_a = thesis_artefact.index(a.sphere_a)
    idx_b = thesis_artefact.index(a.sphere_b)
    from_coords = np.linalg.norm(thesis_artefact.centres[idx_a] - thesis_artefact.centres[idx_b], axis=1)
    diff = from_coords - a.length_mm.to_numpy(float)
    assert np.sqrt(np.mean(diff**2)) < 0.08
    assert np.abs(diff).max() < 0.2


def test_octahedral_tables_3_7_to_3_10(thesis_dir):
    for name, row13 in [("rods_individual_table3-7.csv", 600.016), ("rods_assembled_table3-9.csv", 599.995),
                        ("rods_assembled_repeat_table3-10.csv", 599.713)]:
        t = pd.read_csv(thesis_dir / "octahedral" / name, dtype={"rod_id": str})
        assert len(t) == 12 == 3 * 6 - 6
        assert t.set_index("rod_id").loc["13", "length_mm"] == row13
    s = pd.read_csv(thesis_dir / "octahedral" / "spheres_table3-8.csv")
    assert s.diameter_mm.tolist() == [50.000, 50.001, 50.001, 50.000, 50.000, 50.003]


def test_ballbar_section_6_9_3(thesis_dir):
    bb = load_artefact(thesis_dir / "ballbar.csv")
    assert bb.ids == ("A", "B")
    assert np.linalg.norm(bb.centres[1] - bb.centres[0]) == pytest.approx(1015.650, abs=1e-9)
    assert bb.diameters.tolist() == [50.850, 50.850]


def test_materials_table_3_1_and_magnets(thesis_dir):
    m = yaml.safe_load((thesis_dir / "materials.yaml").read_text())
    assert m["materials"]["carbon_fibre_t300"] == {"elastic_modulus_gpa": 160, "density_kg_m3": 1800, "cte_per_c": -0.38e-6}
    assert m["materials"]["mild_steel"]["elastic_modulus_gpa"] == 205
    assert m["materials"]["chrome_steel"]["density_kg_m3"] == 7830
    assert m["tube"]["outer_diameter_mm"] == 21.8 and m["tube"]["wall_mm"] == 1.4
    assert m["magnet"]["pull_off_rating_n"] == 62.8
    pull = pd.read_csv(thesis_dir / "endcap_pulloff_table3-4.csv")
    assert pull.pull_off_force_n.mean() == pytest.approx(62.9, abs=0.05)


def test_rig_tables_6_7_6_8_and_formats(thesis_dir, thesis_rig):
    assert [s.name for s in thesis_rig.sensors] == ["C1", "P1", "C2", "P2"]
    c1, p1, c2, p2 = thesis_rig.sensors
    np.testing.assert_array_equal(c1.params[:9], [694.018, -211.648, 2585.780, -3.037, -0.264, 3.139, -0.060, 0.291, 52.701])
    np.testing.assert_array_equal(p2.params[9:], [-6.58e-5, 5.01e-7, -2.47e-9, 6.33e-5, 4.46e-5])
    assert (c1.format.width_px, c1.format.width_mm) == (2048, 15.1)
    assert (p1.format.width_px, p1.format.height_px, p1.format.width_mm, p1.format.height_mm) == (1400, 1050, 19.0, 14.3)
    # thesis: 56 parameters, six fixed (camera one's external), 50 free
    assert thesis_rig.free.size == 56 and thesis_rig.free.sum() == 50
    assert not thesis_rig.free[0, :6].any()
    from fringecal.rig import load_rig

    dlt = load_rig(thesis_dir / "sensors_dlt_table6-7.csv")
    np.testing.assert_array_equal(dlt.sensors[1].params[:9], [-358.630, -290.442, 2571.045, -3.036, 0.137, -3.136, 1.006, -0.209, 39.154])
    assert not dlt.params[:, 9:].any()


def test_thesis_poses_and_centres_tables(thesis_dir):
    p1 = read_table(thesis_dir / "poses_scanner1_table6-1.csv", PosePlanTable)
    assert len(p1) == 12
    assert p1.iloc[10][["tx_mm", "ty_mm", "tz_mm", "kappa_rad"]].tolist() == [-9.333, -89.770, -892.113, 1.656]
    c1 = read_table(thesis_dir / "centres_scanner1_table6-3.csv", SphereCentresTable)
    c2 = read_table(thesis_dir / "centres_scanner2_table6-6.csv", SphereCentresTable)
    assert len(c1) == len(c2) == 48
    last = c1.iloc[-1]
    assert (last.measurement, last.sphere_id, last.x_mm, last.y_mm, last.z_mm) == ("12", "9", 241.914, -89.945, -285.504)
    assert set(c2.sphere_id) == {"11", "12", "14", "15"}


def test_rig_yaml_resolves(thesis_dir):
    cfg = load_yaml_model(thesis_dir / "rig.yaml", RigConfig)
    assert cfg.reference_scanner == "scanner1"
    assert cfg.artefact.name == "artefact_cmm2.csv" and cfg.artefact.exists()


def test_chapter_3_and_4_data_sets(thesis_dir):
    log = read_table(thesis_dir / "thermal_log_table3-5.csv", ThermalLogTable)
    assert log.temperature_c.tolist()[0] == 40.3 and log.length_mm.tolist()[-1] == 593.389
    forces = pd.read_csv(thesis_dir / "truss_forces_table3-3.csv")
    assert len(forces) == 39 and forces.force_n.max() == 35.4 and forces.force_n.min() == -55.2
    drift = pd.read_csv(thesis_dir / "drift_table4-1.csv")
    assert len(drift) == 9 and drift.iloc[4][["x_mm", "y_mm", "z_mm"]].tolist() == [43.232, 321.797, -485.860]
    bb = pd.read_csv(thesis_dir / "ballbar_lengths_table6-9.csv")
    assert bb.length_mm.mean() == pytest.approx(1015.612, abs=0.0005)
